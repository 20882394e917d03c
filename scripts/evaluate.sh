#!/usr/bin/env bash
# The thesis evaluation (issue 5): builds, refines the thesis-like objects of
# ../shared/meshes with uniform, fixed thresholds and IteAS at levels 1-4,
# measures deviation from the uniform surface, and writes docs/evaluation/
# (Markdown tables, gnuplot data and PNG plots). Not part of the test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh build Release
if ! command -v gnuplot >/dev/null 2>&1; then
  SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
  $SUDO apt-get install -y -qq -o DPkg::Lock::Timeout=600 gnuplot-nox >/dev/null
fi
CORPUS=${ITEAS_CORPUS:-../shared/meshes}
mkdir -p docs/evaluation
build/bench/evaluate docs/evaluation "$CORPUS"
(cd docs/evaluation && for g in *.gp; do gnuplot "$g"; done)
echo "[evaluate] wrote docs/evaluation/"
