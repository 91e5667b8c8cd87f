// Packs of scalars for the host's vector units: W floats or doubles in one
// 32-byte vector (GCC's vector extension), with the operators the geometry
// core's templates use, so that the same formulas (CellMoments) run on a
// pack of vertices at once. In the AVX2 copy of the clip loop (cpu/isa.h) a
// pack is one AVX register; in the baseline build, two SSE registers.
// Host only (not for nvcc, which neither needs nor parses them):
// TORCHVOR_HOST_PACKS says where they exist.
#pragma once

#include "common.h"

#if !defined(__CUDACC__) && defined(__GNUC__)
#define TORCHVOR_HOST_PACKS 1

#include <type_traits>

namespace torchvor {
namespace core {

template <typename F>
struct PackTraits;
template <>
struct PackTraits<float> {
  static constexpr int kWidth = 8;
  using Int = int32_t;
};
template <>
struct PackTraits<double> {
  static constexpr int kWidth = 4;
  using Int = int64_t;
};

// Lane masks: all bits set where true, as the vector comparisons give them.
template <typename F>
struct PackMask {
  typedef typename PackTraits<F>::Int Vector
      __attribute__((vector_size(sizeof(F) * PackTraits<F>::kWidth)));
  Vector lanes;
};

template <typename F>
struct Pack {
  static constexpr int kWidth = PackTraits<F>::kWidth;
  typedef F Vector __attribute__((vector_size(sizeof(F) * kWidth)));
  Vector lanes;

  Pack() = default;
  TV_HD Pack(F x) : lanes(Vector{} + x) {}  // every lane x
  TV_HD static Pack of(Vector v) {
    Pack p;
    p.lanes = v;
    return p;
  }
  TV_HD F sum() const {  // lane 0 + lane 1 + ... in that order
    F total = lanes[0];
    for (int i = 1; i < kWidth; ++i) total += lanes[i];
    return total;
  }
  TV_HD F max() const {
    F largest = lanes[0];
    for (int i = 1; i < kWidth; ++i) largest = largest < lanes[i] ? lanes[i] : largest;
    return largest;
  }
};

template <typename F>
struct IsPack<Pack<F>> : std::true_type {};

#define TORCHVOR_PACK_OPERATOR(op)                                                                  \
  template <typename F>                                                                             \
  TV_HD Pack<F> operator op(const Pack<F>& a, const Pack<F>& b) {                                   \
    return Pack<F>::of(a.lanes op b.lanes);                                                         \
  }                                                                                                 \
  template <typename F>                                                                             \
  TV_HD Pack<F>& operator op##=(Pack<F>& a, const Pack<F>& b) {                                     \
    a.lanes = a.lanes op b.lanes;                                                                   \
    return a;                                                                                       \
  }
TORCHVOR_PACK_OPERATOR(+)
TORCHVOR_PACK_OPERATOR(-)
TORCHVOR_PACK_OPERATOR(*)
TORCHVOR_PACK_OPERATOR(/)
#undef TORCHVOR_PACK_OPERATOR

#define TORCHVOR_PACK_COMPARISON(op)                                                                \
  template <typename F>                                                                             \
  TV_HD PackMask<F> operator op(const Pack<F>& a, const Pack<F>& b) {                               \
    return {a.lanes op b.lanes};                                                                    \
  }
TORCHVOR_PACK_COMPARISON(<)
TORCHVOR_PACK_COMPARISON(>)
TORCHVOR_PACK_COMPARISON(==)
#undef TORCHVOR_PACK_COMPARISON

template <typename F>
TV_HD Pack<F> operator-(const Pack<F>& a) {
  return Pack<F>::of(-a.lanes);
}
template <typename F>
TV_HD PackMask<F> operator&(const PackMask<F>& a, const PackMask<F>& b) {
  return {a.lanes & b.lanes};
}
template <typename F>
TV_HD PackMask<F> operator|(const PackMask<F>& a, const PackMask<F>& b) {
  return {a.lanes | b.lanes};
}
template <typename F>
TV_HD PackMask<F> operator~(const PackMask<F>& a) {
  return {~a.lanes};
}
// Lane by lane: a where the mask is set, else b (common.h's select).
template <typename F>
TV_HD Pack<F> select(const PackMask<F>& mask, const Pack<F>& a, const Pack<F>& b) {
  return Pack<F>::of(mask.lanes ? a.lanes : b.lanes);
}
template <typename F>
TV_HD Pack<F> max_of(const Pack<F>& a, const Pack<F>& b) {
  return Pack<F>::of(a.lanes < b.lanes ? b.lanes : a.lanes);
}
// 1 / sqrt, lane by lane (vectorised: the build has no errno for sqrt).
template <typename F>
TV_HD Pack<F> rsqrt_of(const Pack<F>& a) {
  Pack<F> root;
  for (int i = 0; i < Pack<F>::kWidth; ++i) root.lanes[i] = __builtin_sqrt(a.lanes[i]);
  return Pack<F>(F(1)) / root;
}
template <>
TV_HD Pack<float> rsqrt_of(const Pack<float>& a) {
  Pack<float> root;
  for (int i = 0; i < Pack<float>::kWidth; ++i) root.lanes[i] = __builtin_sqrtf(a.lanes[i]);
  return Pack<float>(1.0f) / root;
}
// A product rounded on its own (common.h's mul_rn): a pack held in memory
// between the multiplication and the addition, so that no FMA fuses them
// (a register constraint would not fit a 32-byte vector in the baseline
// build).
template <typename F>
TV_HD Pack<F> mul_rn(const Pack<F>& a, const Pack<F>& b) {
  Pack<F> product = a * b;
  __asm__("" : "+m"(product.lanes));
  return product;
}
// Lanes 0, 1, ..., kWidth - 1 as integers.
template <typename F>
TV_HD typename PackMask<F>::Vector lane_indices() {
  typename PackMask<F>::Vector index;
  for (int i = 0; i < Pack<F>::kWidth; ++i) index[i] = i;
  return index;
}
// Bit i set where lane i of the mask is.
template <typename F>
TV_HD uint32_t mask_bits(const PackMask<F>& mask) {
  uint32_t bits = 0u;
  for (int i = 0; i < Pack<F>::kWidth; ++i) bits |= uint32_t(mask.lanes[i] & 1) << i;
  return bits;
}

}  // namespace core
}  // namespace torchvor

#endif
