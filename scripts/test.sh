#!/usr/bin/env bash
# Quick start, second command: install, build, and run the whole test suite:
# unit and property tests, the OpenMesh differential test, the CLI over every
# mesh checked by the Khronos validator and draco3d, then the readers and the
# broken-file checks and the server tests again under AddressSanitizer + UBSan,
# and the core's and the job's parallel steps and the server tests under
# ThreadSanitizer.
set -euo pipefail
cd "$(dirname "$0")/.."
ITEAS_TEST_PACKAGES=1 scripts/setup.sh build Release
(cd tests/js && npm ci --no-audit --no-fund --loglevel=error)

echo "[test] release build"
ctest --test-dir build --output-on-failure -j 2

echo "[test] AddressSanitizer + UndefinedBehaviorSanitizer build"
cmake -S . -B build-asan -G Ninja -DCMAKE_BUILD_TYPE=Asan >/dev/null
ninja -C build-asan iteas corner_table_test io_test refine_test fuzz_read_replay fuzz_options_replay fuzz_refine_replay fuzz_http_replay
export ASAN_OPTIONS=detect_leaks=1:abort_on_error=1 UBSAN_OPTIONS=print_stacktrace=1:halt_on_error=1
# The unit tests, the fuzz replays, and the asan_* entries of tests/CMakeLists.txt
# (part of refine_test over every mesh, the broken files through the CLI, the
# server's tests on the shipped meshes), two at a time.
ctest --test-dir build-asan --output-on-failure -j 2 -R '^(corner_table_test|io_test|fuzz_replay_.*|asan_.*)$'

echo "[test] ThreadSanitizer build: the core on two threads, the job's parallel steps, the server tests"
cmake -S . -B build-tsan -G Ninja -DCMAKE_BUILD_TYPE=Tsan >/dev/null
ninja -C build-tsan iteas io_test refine_test
# The tsan_* entries of tests/CMakeLists.txt: the core on one and two threads,
# several meshes refined and encoded at once, the server's tests.
ctest --test-dir build-tsan --output-on-failure -j 2 -R '^tsan_'
echo "[test] all passed"
