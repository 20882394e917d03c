// What the processor can run, for the code paths compiled for more than the
// x86-64 baseline (chosen at run time, each with an SSE2 twin that gives the
// same results).
#pragma once

#include <atomic>

namespace iteas {

#if defined(__GNUC__) && defined(__x86_64__)
#define ITEAS_X86_FEATURES 1
enum class CpuFeature { kAvx, kAvx2, kAvx512 };
// For tests: the widest feature cpu_has() may answer yes for, so that the
// routines for narrower registers run on a processor with wider ones.
inline std::atomic<int>& cpu_feature_cap() {
  static std::atomic<int> cap{int(CpuFeature::kAvx512)};
  return cap;
}
// Asked once, on first use (__builtin_cpu_init: safe even before the libgcc
// constructor that would set the answers up has run).
inline bool cpu_has(CpuFeature f) {
  struct Answers {
    bool avx, avx2, avx512;
  };
  static const Answers yes = [] {
    __builtin_cpu_init();
    // kAvx512: the foundation and the 128/256-bit forms (every AVX-512
    // processor but the Xeon Phi's).
    return Answers{__builtin_cpu_supports("avx") != 0, __builtin_cpu_supports("avx2") != 0,
                   __builtin_cpu_supports("avx512f") != 0 && __builtin_cpu_supports("avx512vl") != 0};
  }();
  if (int(f) > cpu_feature_cap().load(std::memory_order_relaxed)) return false;
  return f == CpuFeature::kAvx ? yes.avx : (f == CpuFeature::kAvx2 ? yes.avx2 : yes.avx512);
}
#else
#define ITEAS_X86_FEATURES 0
#endif

}  // namespace iteas
