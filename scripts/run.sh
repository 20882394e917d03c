#!/usr/bin/env bash
# Quick start, first command: install, build, and run the main job.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh build Release
echo "[run] refining tests/data/bunny-npm.obj with IteAS defaults"
build/iteas refine tests/data/bunny-npm.obj -o build/bunny.refined.glb --stats -
echo "[run] wrote build/bunny.refined.glb"
