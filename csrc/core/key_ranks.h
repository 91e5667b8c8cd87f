// Host-only: the rank of each of n distinct non-negative 64-bit keys (the
// number of smaller keys), which is its position in sorted order; and of
// pairs of them (pair_ranks, ranks_by_first_of_pairs: float64 distances,
// then indices).
//
// The kNN's last step sorts its k best keys. For k up to ~100 a rank count
// is quadratic but branch-free and vectorised, and beats std::sort, whose
// branches mispredict on these keys (docs/performance.md, kNN on the CPU).
// Each pass over the keys ranks two of them (one load, two compares). The
// AVX-512 and AVX2 forms are chosen at run time, so the build stays
// portable; CPUs without AVX2 use std::sort.
#pragma once

#if !defined(__CUDACC__) && defined(__GNUC__) && (defined(__x86_64__) || defined(__i386__))
#define TORCHVOR_HAS_KEY_RANKS 1

#include <immintrin.h>

#include <cstdint>

namespace torchvor {
namespace core {

// Largest n ranked (the stack array's size): ranking beats std::sort for
// the k of most searches, and is quadratic beyond.
constexpr int32_t kMaxRankedKeys = 128;

// Inlined (a load and a test once the first call has set it): the kNN asks
// once a row range.
inline __attribute__((always_inline)) bool cpu_has_avx2() {
  static const bool has = __builtin_cpu_supports("avx2");
  return has;
}

inline __attribute__((always_inline)) bool cpu_has_avx512() {
  static const bool has = __builtin_cpu_supports("avx512f");
  return has;
}

// key_ranks with AVX2: four keys a compare, two ranked a pass.
__attribute__((target("avx2"))) inline void key_ranks_avx2(const int64_t* key, int32_t n, int32_t* rank) {
  const int32_t whole = n & ~3;
  for (int32_t i = 0; i < n; i += 2) {
    const int32_t second = i + 1 < n ? i + 1 : i;  // an odd n ranks its last key twice
    const __m256i item_a = _mm256_set1_epi64x(key[i]), item_b = _mm256_set1_epi64x(key[second]);
    __m256i count_a = _mm256_setzero_si256(), count_b = _mm256_setzero_si256();
    for (int32_t j = 0; j < whole; j += 4) {
      const __m256i other = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(key + j));
      count_a = _mm256_sub_epi64(count_a, _mm256_cmpgt_epi64(item_a, other));  // -1 where smaller
      count_b = _mm256_sub_epi64(count_b, _mm256_cmpgt_epi64(item_b, other));
    }
    alignas(32) int64_t lanes_a[4], lanes_b[4];
    _mm256_store_si256(reinterpret_cast<__m256i*>(lanes_a), count_a);
    _mm256_store_si256(reinterpret_cast<__m256i*>(lanes_b), count_b);
    int64_t smaller_a = lanes_a[0] + lanes_a[1] + lanes_a[2] + lanes_a[3];
    int64_t smaller_b = lanes_b[0] + lanes_b[1] + lanes_b[2] + lanes_b[3];
    for (int32_t j = whole; j < n; ++j) {
      smaller_a += key[j] < key[i];
      smaller_b += key[j] < key[second];
    }
    rank[i] = static_cast<int32_t>(smaller_a);
    rank[second] = static_cast<int32_t>(smaller_b);
  }
}

// key_ranks with AVX-512: eight keys a compare into a mask, two ranked a pass.
__attribute__((target("avx512f,popcnt"))) inline void key_ranks_avx512(const int64_t* key, int32_t n,
                                                                       int32_t* rank) {
  const int32_t whole = n & ~7;
  const __mmask8 tail = static_cast<__mmask8>((1u << (n - whole)) - 1u);
  for (int32_t i = 0; i < n; i += 2) {
    const int32_t second = i + 1 < n ? i + 1 : i;  // an odd n ranks its last key twice
    const __m512i item_a = _mm512_set1_epi64(key[i]), item_b = _mm512_set1_epi64(key[second]);
    int32_t smaller_a = 0, smaller_b = 0;
    for (int32_t j = 0; j < whole; j += 8) {
      const __m512i other = _mm512_loadu_si512(key + j);
      smaller_a += __builtin_popcount(_mm512_cmpgt_epi64_mask(item_a, other));
      smaller_b += __builtin_popcount(_mm512_cmpgt_epi64_mask(item_b, other));
    }
    if (tail) {
      const __m512i other = _mm512_maskz_loadu_epi64(tail, key + whole);
      smaller_a += __builtin_popcount(_mm512_mask_cmpgt_epi64_mask(tail, item_a, other));
      smaller_b += __builtin_popcount(_mm512_mask_cmpgt_epi64_mask(tail, item_b, other));
    }
    rank[i] = smaller_a;
    rank[second] = smaller_b;
  }
}

// rank[i] = number of keys smaller than key[i]; keys must be distinct and
// below 2^63 (compared as signed integers). Call only where AVX2 is.
inline void key_ranks(const int64_t* key, int32_t n, int32_t* rank) {
  if (cpu_has_avx512()) {
    key_ranks_avx512(key, n, rank);
  } else {
    key_ranks_avx2(key, n, rank);
  }
}

// The same for distinct pairs (first[i], second[i]) in lexicographic order,
// each element below 2^63.
__attribute__((target("avx2"))) inline void pair_ranks(const int64_t* first, const int64_t* second, int32_t n,
                                                        int32_t* rank) {
  for (int32_t i = 0; i < n; ++i) {
    const __m256i item_first = _mm256_set1_epi64x(first[i]);
    const __m256i item_second = _mm256_set1_epi64x(second[i]);
    __m256i count = _mm256_setzero_si256();
    int32_t j = 0;
    for (; j + 4 <= n; j += 4) {
      const __m256i other_first = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(first + j));
      const __m256i other_second = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(second + j));
      const __m256i tie_smaller = _mm256_and_si256(_mm256_cmpeq_epi64(item_first, other_first),
                                                   _mm256_cmpgt_epi64(item_second, other_second));
      count = _mm256_sub_epi64(count, _mm256_or_si256(_mm256_cmpgt_epi64(item_first, other_first), tie_smaller));
    }
    alignas(32) int64_t lanes[4];
    _mm256_store_si256(reinterpret_cast<__m256i*>(lanes), count);
    int64_t smaller = lanes[0] + lanes[1] + lanes[2] + lanes[3];
    for (; j < n; ++j) {
      smaller += first[j] < first[i] || (first[j] == first[i] && second[j] < second[i]);
    }
    rank[i] = static_cast<int32_t>(smaller);
  }
}

// pair_ranks for pairs whose first elements are nearly always distinct
// (float64 distances, then indices): ranks by the first alone, which holds
// when those ranks are all different; else by the pairs.
__attribute__((target("avx2"))) inline void ranks_by_first_of_pairs(const int64_t* first, const int64_t* second,
                                                                     int32_t n, int32_t* rank) {
  key_ranks(first, n, rank);
  uint64_t taken[(kMaxRankedKeys + 63) / 64] = {};
  int32_t distinct = 0;
  for (int32_t i = 0; i < n; ++i) {
    const uint64_t bit = uint64_t(1) << (rank[i] & 63);
    distinct += int32_t((taken[rank[i] >> 6] & bit) == 0u);
    taken[rank[i] >> 6] |= bit;
  }
  if (distinct != n) pair_ranks(first, second, n, rank);
}

}  // namespace core
}  // namespace torchvor

#endif
