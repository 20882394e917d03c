// What the processor can run, for the code paths compiled for more than the
// x86-64 baseline (chosen at run time, each with an SSE2 twin that gives the
// same results).
#pragma once

#include <atomic>

// Loops written as plain C++ for GCC to vectorise.
// ITEAS_SELECTS_VECTORISE: GCC if-converts selects (a ? b : c on floats)
// only without trapping-math semantics (the default masks every floating
// point exception, so nothing traps either way). Clang vectorises them as is.
#if defined(__GNUC__) && !defined(__clang__)
#define ITEAS_SELECTS_VECTORISE __attribute__((optimize("no-trapping-math")))
#else
#define ITEAS_SELECTS_VECTORISE
#endif
// ITEAS_WIDE_CLONES: GCC's target_clones makes the loop's AVX-512 (x86-64-v4:
// sixteen floats or eight doubles a register) and AVX versions (butterfly.cpp's
// sums are written with AVX intrinsics instead and pick their version with
// cpu_has()). Every version computes the same bits: the loops work element by
// element, and the core is built with -ffp-contract=off, so no version fuses
// a multiply and an add that the baseline rounds twice (AVX-512 brings FMA);
// IEEE division and square root are exact in every width. With the AVX-512
// versions of the statistics' loops (core/angles.cpp), uniform jobs with the
// statistics took 15-18 % less time (bunny-npm levels 1-3, one thread, AMD
// Zen 5 class: level 1 0.385 -> 0.327 ms, level 3 4.9 -> 4.2 ms).
// The AVX clones are chosen by an ifunc resolver, which runs while the
// program is being loaded: under ThreadSanitizer, before its runtime is
// set up, where the resolver's instrumented code crashes (the sanitizer
// build then uses the baseline loops).
#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__) && !defined(__SANITIZE_THREAD__)
#define ITEAS_WIDE_CLONES __attribute__((target_clones("arch=x86-64-v4", "avx", "default")))
#else
#define ITEAS_WIDE_CLONES
#endif

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
