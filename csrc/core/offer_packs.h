// Host-only: the kNN's candidate loop (grid_search.h's offer_range, once the
// heap is full) a pack of points at a time with AVX2. The points stay in
// their (x, y, z) rows: a pack of 8 float or 4 double points is three loads,
// sorted into x, y and z columns by blends and a permute (no gather, no
// copy of the grid), then 8 or 4 distances and one compare with the heap's
// worst distance rule most of them out. The survivors go to the heap in
// the scalar loop's order with its keys, so the heap ends exactly as the
// scalar loop leaves it. The distances round as squared_distance's
// ((dx^2 + dy^2) + dz^2, each product rounded: no FMA in the target).
#pragma once

#if !defined(__CUDACC__) && defined(__GNUC__) && (defined(__x86_64__) || defined(__i386__))
#define TORCHVOR_HAS_OFFER_PACKS 1

#include <immintrin.h>

#include <cstdint>
#include <type_traits>

#include "common.h"

namespace torchvor {
namespace core {

// 8 float points: their squared distances to a query, from `rows` (x, y, z
// of consecutive points), the first `count` of them read (never past the
// rows' end); and which of them are at most a bound.
struct FloatPack {
  using Vec = __m256;
  static constexpr int32_t kPoints = 8;
  __attribute__((target("avx2"))) static Vec broadcast(float v) { return _mm256_set1_ps(v); }
  __attribute__((target("avx2"))) static Vec squared_distances(const float* rows, int32_t count, Vec qx, Vec qy,
                                                               Vec qz) {
    __m256 a, b, c;
    if (count == kPoints) {
      a = _mm256_loadu_ps(rows);
      b = _mm256_loadu_ps(rows + 8);
      c = _mm256_loadu_ps(rows + 16);
    } else {
      const __m256i floats = _mm256_set1_epi32(3 * count), lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
      a = _mm256_maskload_ps(rows, _mm256_cmpgt_epi32(floats, lane));
      b = _mm256_maskload_ps(rows + 8, _mm256_cmpgt_epi32(floats, _mm256_add_epi32(lane, _mm256_set1_epi32(8))));
      c = _mm256_maskload_ps(rows + 16, _mm256_cmpgt_epi32(floats, _mm256_add_epi32(lane, _mm256_set1_epi32(16))));
    }
    // Point p's x sits in lane 3p of (a, b, c): blend each lane from the
    // register that holds an x there, then permute into point order.
    const __m256 x = _mm256_permutevar8x32_ps(_mm256_blend_ps(_mm256_blend_ps(a, b, 0x92), c, 0x24),
                                              _mm256_setr_epi32(0, 3, 6, 1, 4, 7, 2, 5));
    const __m256 y = _mm256_permutevar8x32_ps(_mm256_blend_ps(_mm256_blend_ps(a, b, 0x24), c, 0x49),
                                              _mm256_setr_epi32(1, 4, 7, 2, 5, 0, 3, 6));
    const __m256 z = _mm256_permutevar8x32_ps(_mm256_blend_ps(_mm256_blend_ps(a, b, 0x49), c, 0x92),
                                              _mm256_setr_epi32(2, 5, 0, 3, 6, 1, 4, 7));
    const __m256 dx = _mm256_sub_ps(x, qx), dy = _mm256_sub_ps(y, qy), dz = _mm256_sub_ps(z, qz);
    return _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(dx, dx), _mm256_mul_ps(dy, dy)), _mm256_mul_ps(dz, dz));
  }
  __attribute__((target("avx2"))) static unsigned at_most(Vec d2, Vec bound) {
    return unsigned(_mm256_movemask_ps(_mm256_cmp_ps(d2, bound, _CMP_LE_OQ)));
  }
  __attribute__((target("avx2"))) static void store(float* out, Vec d2) { _mm256_storeu_ps(out, d2); }
};

// The same for 4 double points.
struct DoublePack {
  using Vec = __m256d;
  static constexpr int32_t kPoints = 4;
  __attribute__((target("avx2"))) static Vec broadcast(double v) { return _mm256_set1_pd(v); }
  __attribute__((target("avx2"))) static Vec squared_distances(const double* rows, int32_t count, Vec qx, Vec qy,
                                                               Vec qz) {
    __m256d a, b, c;
    if (count == kPoints) {
      a = _mm256_loadu_pd(rows);
      b = _mm256_loadu_pd(rows + 4);
      c = _mm256_loadu_pd(rows + 8);
    } else {
      const __m256i doubles = _mm256_set1_epi64x(3 * count), lane = _mm256_setr_epi64x(0, 1, 2, 3);
      a = _mm256_maskload_pd(rows, _mm256_cmpgt_epi64(doubles, lane));
      b = _mm256_maskload_pd(rows + 4, _mm256_cmpgt_epi64(doubles, _mm256_add_epi64(lane, _mm256_set1_epi64x(4))));
      c = _mm256_maskload_pd(rows + 8, _mm256_cmpgt_epi64(doubles, _mm256_add_epi64(lane, _mm256_set1_epi64x(8))));
    }
    // a = x0 y0 z0 x1, b = y1 z1 x2 y2, c = z2 x3 y3 z3; blended: x0 x3 x2 x1,
    // y1 y0 y3 y2 and z2 z1 z0 z3, then permuted into point order
    const __m256d x = _mm256_permute4x64_pd(_mm256_blend_pd(_mm256_blend_pd(a, b, 0x4), c, 0x2), 0x6C);
    const __m256d y = _mm256_permute4x64_pd(_mm256_blend_pd(_mm256_blend_pd(a, b, 0x9), c, 0x4), 0xB1);
    const __m256d z = _mm256_permute4x64_pd(_mm256_blend_pd(_mm256_blend_pd(a, b, 0x2), c, 0x9), 0xC6);
    const __m256d dx = _mm256_sub_pd(x, qx), dy = _mm256_sub_pd(y, qy), dz = _mm256_sub_pd(z, qz);
    return _mm256_add_pd(_mm256_add_pd(_mm256_mul_pd(dx, dx), _mm256_mul_pd(dy, dy)), _mm256_mul_pd(dz, dz));
  }
  __attribute__((target("avx2"))) static unsigned at_most(Vec d2, Vec bound) {
    return unsigned(_mm256_movemask_pd(_mm256_cmp_pd(d2, bound, _CMP_LE_OQ)));
  }
  __attribute__((target("avx2"))) static void store(double* out, Vec d2) { _mm256_storeu_pd(out, d2); }
};

template <typename T>
using PointPack = typename std::conditional<std::is_same<T, float>::value, FloatPack, DoublePack>::type;

// Sorted points [s, end) offered to a full `heap` (NeighborHeap), as
// offer_range's scalar loop does: a point within the worst key's distance
// replaces the root where its key is smaller and it is not `excluded`.
template <typename T, typename Heap, typename Key>
__attribute__((target("avx2"))) void offer_packs(const T* sorted_points, const int32_t* sorted_index, int32_t s,
                                                 int32_t end, Vec3<T> query, int32_t excluded, Heap& heap) {
  using Pack = PointPack<T>;
  const typename Pack::Vec qx = Pack::broadcast(query.x), qy = Pack::broadcast(query.y),
                           qz = Pack::broadcast(query.z);
  Key worst = heap.key[0];
  typename Pack::Vec bound = Pack::broadcast(worst.dist2());
  alignas(32) T distance[Pack::kPoints];
  for (; s < end; s += Pack::kPoints) {
    const int32_t count = end - s < Pack::kPoints ? end - s : Pack::kPoints;
    const typename Pack::Vec d2 = Pack::squared_distances(sorted_points + 3 * int64_t(s), count, qx, qy, qz);
    unsigned near = Pack::at_most(d2, bound) & ((1u << count) - 1u);
    if (near == 0u) continue;
    Pack::store(distance, d2);
    while (near != 0u) {
      const int p = __builtin_ctz(near);
      near &= near - 1u;
      const int32_t original = sorted_index ? sorted_index[s + p] : s + p;
      const Key item = Key::make(distance[p], original);
      if (item < worst && original != excluded) {
        heap.replace_root(item);
        worst = heap.key[0];
        bound = Pack::broadcast(worst.dist2());
        near &= Pack::at_most(d2, bound);  // the pack's later points against the new worst
      }
    }
  }
}

}  // namespace core
}  // namespace torchvor

#endif
