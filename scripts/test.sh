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
ctest --test-dir build-asan --output-on-failure -j 2 -R 'corner_table_test|io_test|fuzz_replay'
build-asan/tests/refine_test --gtest_filter='*AdaptiveWithEverything*:*Planar*:*Cancellation*:*Budget*:*SmallestAngle*:*RingBlock*' --gtest_brief=1
ITEAS_BIN="$PWD/build-asan/iteas" ITEAS_SOURCE_DIR="$PWD" ITEAS_JS_ONLY=broken node --test tests/js/corpus.test.mjs
# The server's integration tests against the ASan binary (the shipped meshes):
# every group but trim, threads and bounds (which measure the allocator, the
# cores and RSS) and openapi (a linter).
ITEAS_BIN="$PWD/build-asan/iteas" ITEAS_SOURCE_DIR="$PWD" ITEAS_CORPUS=/nonexistent \
  ITEAS_JS_ONLY=errors,auth,backpressure,api,replicas,slowread node --test tests/js/server.test.mjs

echo "[test] ThreadSanitizer build: the core on two threads, the job's parallel steps, the server tests"
cmake -S . -B build-tsan -G Ninja -DCMAKE_BUILD_TYPE=Tsan >/dev/null
ninja -C build-tsan iteas io_test refine_test
# One and two threads on the shipped meshes of up to 4,000 triangles (both
# modes), the spatial sort in parts (a generated mesh of 81,920 triangles),
# several meshes refined and several Draco payloads encoded at once. The
# corpus's meshes of that size are left to the release stage (with them this
# step took 254 s instead of 22–24).
ITEAS_CORPUS=/nonexistent ITEAS_TEST_MAX_FACES=4000 TSAN_OPTIONS="halt_on_error=1:second_deadlock_stack=1" \
  build-tsan/tests/refine_test --gtest_filter='*SameOutputForOneAndTwoThreads*:*ReportedQuality*:*SpatialOrderIsTheSameOnAnyThreads*' --gtest_brief=1
TSAN_OPTIONS="halt_on_error=1:second_deadlock_stack=1" ITEAS_CORPUS=/nonexistent \
  build-tsan/tests/io_test --gtest_filter='Io.SeveralMeshes*:Io.DracoPrim*' --gtest_brief=1
# The server's groups but bounds (its 3-million-triangle jobs) and openapi
# (a linter); ITEAS_TEST_SANITIZER sizes the replicas' queued jobs for TSan.
TSAN_OPTIONS="halt_on_error=1:second_deadlock_stack=1:suppressions=$PWD/tests/tsan.supp" ITEAS_BIN="$PWD/build-tsan/iteas" ITEAS_SOURCE_DIR="$PWD" \
  ITEAS_CORPUS=/nonexistent ITEAS_TEST_SANITIZER=thread ITEAS_JS_ONLY=api,errors,auth,backpressure,replicas,trim,threads,slowread \
  node --test tests/js/server.test.mjs
echo "[test] all passed"
