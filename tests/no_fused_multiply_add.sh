#!/usr/bin/env bash
# The core's loops have versions for wider instruction sets (AVX, AVX-512;
# core/angles.cpp) that must round as the baseline does, so that the output
# is the same bits on any processor: the core is built with
# -ffp-contract=off (CMakeLists.txt), and no multiply and add may be fused
# into an FMA, which AVX-512 brings. Fails when the library holds an FMA
# instruction, or when it holds no AVX-512 code at all (then the check would
# prove nothing).
#   tests/no_fused_multiply_add.sh path/to/libiteas_core.a
set -euo pipefail
lib=$1
dis=$(objdump -d --no-show-raw-insn "$lib")
zmm=$(grep -c 'zmm' <<<"$dis" || true)
fma=$(grep -cE '[[:space:]]vfn?m(add|sub)' <<<"$dis" || true)
echo "$lib: $zmm instructions on zmm registers, $fma fused multiply-adds"
if [ "$zmm" -eq 0 ]; then echo "no AVX-512 code: the versions for it are missing" >&2; exit 1; fi
if [ "$fma" -ne 0 ]; then
  { grep -E "[[:space:]]vfn?m(add|sub)|>:\$" <<<"$dis" | grep -B1 -E "vfn?m(add|sub)" | head -20 >&2; } || true
  echo "the core holds fused multiply-adds: a version would round unlike the baseline" >&2
  exit 1
fi
