// The hot CPU loop (clipping cells) compiled a second time for AVX2 and FMA,
// chosen at run time, in a build that otherwise targets baseline x86-64.
//
// Why an attribute on a loop, not a translation unit built with -mavx2: the
// linker keeps one copy of each inline function and template instantiation
// across translation units, and it might keep the AVX2 copy for callers that
// run on a CPU without AVX2. Here AVX2 code exists only inside run_avx2_fma:
// `flatten` inlines the whole call tree of the loop body into it, and a call
// that is not inlined goes to the ordinary baseline function.
//
// Options::cpu_baseline_isa forces the baseline loop: the tests compare the two.
#pragma once

#include <cstdint>

namespace torchvor {
namespace cpu {

enum class Isa { kBaseline, kAvx2Fma };

// What run_range will use on this CPU, unless `force_baseline`.
inline Isa cpu_isa(bool force_baseline) {
  if (force_baseline) return Isa::kBaseline;
#if defined(__x86_64__) && defined(__GNUC__)
  static const bool has_avx2_fma = __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma");
  return has_avx2_fma ? Isa::kAvx2Fma : Isa::kBaseline;
#else
  return Isa::kBaseline;
#endif
}

inline const char* isa_name(Isa isa) { return isa == Isa::kAvx2Fma ? "avx2+fma" : "baseline"; }

#if defined(__x86_64__) && defined(__GNUC__)
#define TORCHVOR_HAS_AVX2_FMA_COPY 1
// a * b + c may round once here, as it does on the GPU (nvcc fuses by
// default): not for code that needs separately rounded products.
template <typename Body>
__attribute__((target("avx2,fma"), flatten)) void run_avx2_fma(int64_t begin, int64_t end,
                                                               const Body& body) {
  for (int64_t i = begin; i < end; ++i) body(i);
}
#endif

// body(i) for i in [begin, end), from the copy compiled for `isa`.
template <typename Body>
void run_range(Isa isa, int64_t begin, int64_t end, const Body& body) {
#if defined(TORCHVOR_HAS_AVX2_FMA_COPY)
  if (isa == Isa::kAvx2Fma) return run_avx2_fma(begin, end, body);
#endif
  (void)isa;
  for (int64_t i = begin; i < end; ++i) body(i);
}

}  // namespace cpu
}  // namespace torchvor
