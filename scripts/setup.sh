#!/usr/bin/env bash
# Installs what a fresh Debian 12 machine lacks (as root), then builds IteAS.
#   scripts/setup.sh [build-dir] [build-type]
set -euo pipefail
cd "$(dirname "$0")/.."
BUILD_DIR=${1:-build}
BUILD_TYPE=${2:-Release}

# (binutils: objdump, which core_rounding_test reads the core library with.)
packages=(build-essential binutils cmake ninja-build pkg-config git ca-certificates
  libcpp-httplib-dev nlohmann-json3-dev libtinygltf-dev libdraco-dev draco libspdlog-dev libstb-dev
  libgtest-dev libgmock-dev libbenchmark-dev libopenmesh-dev)
# The test suite also drives the web page in Debian's Chromium and puts nginx in
# front of several replicas (ITEAS_TEST_PACKAGES=1, set by scripts/test.sh).
[ -z "${ITEAS_TEST_PACKAGES:-}" ] || packages+=(chromium nginx-light curl)
command -v node >/dev/null 2>&1 || packages+=(nodejs)
command -v npm >/dev/null 2>&1 || packages+=(npm)
missing=()
for p in "${packages[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
  SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
  echo "[setup] installing: ${missing[*]}"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq -o DPkg::Lock::Timeout=600 "${missing[@]}" >/dev/null
fi

# three.js for the web page, vendored into the build from the npm registry.
[ -d web/node_modules/three ] || (cd web && npm ci --no-audit --no-fund --loglevel=error)

cmake -S . -B "$BUILD_DIR" -G Ninja -DCMAKE_BUILD_TYPE="$BUILD_TYPE" >/dev/null
ninja -C "$BUILD_DIR"
