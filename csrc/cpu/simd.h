// Vectorisation of the CPU inner loops without building for one machine: with GCC on x86-64
// each marked function is compiled for AVX-512 (x86-64-v4), AVX2+FMA (x86-64-v3) and the
// baseline, and the loader picks the best one for the CPU at hand (function multiversioning).
// Mark functions that do a whole chunk of work per call; the helpers they inline are compiled
// for the same target.
#pragma once

#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__)
#define T3FAST_SIMD_CLONES \
  __attribute__((target_clones("arch=x86-64-v4", "arch=x86-64-v3", "default")))
#else
#define T3FAST_SIMD_CLONES
#endif
