#!/usr/bin/env bash
# Quick start, first command: install what is missing, build, and start the
# service on its defaults (127.0.0.1:8080; ITEAS_* variables or flags change them).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh build Release
cat <<MSG
[run] starting iteas serve on ${ITEAS_HOST:-127.0.0.1}:${ITEAS_PORT:-8080}. Try, from another shell:
  curl -s --data-binary @tests/data/bunny-npm.obj -H 'Content-Type: application/octet-stream' \\
       -D - -o bunny.smooth.glb 'http://127.0.0.1:${ITEAS_PORT:-8080}/v1/refine?levels=3'
MSG
exec build/iteas serve "$@"
