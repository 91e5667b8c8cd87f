// Host-only: the rank of each of n distinct non-negative 64-bit keys (the
// number of smaller keys), which is its position in sorted order; and of
// pairs of them (pair_ranks, ranks_by_first_of_pairs: float64 distances,
// then indices).
//
// The kNN's last step sorts its k best keys. For k up to ~100 a rank count
// is quadratic but branch-free, and with AVX2 (four 64-bit compares per
// instruction) it takes about half the time of std::sort, whose branches
// mispredict on these keys (k = 35: 190 vs 460 ns, k = 63: 540 vs 1000 ns per
// query on the development machine). AVX2 is chosen at run time, so the
// build stays portable; CPUs without it use std::sort.
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

inline bool cpu_has_avx2() {
  static const bool has = __builtin_cpu_supports("avx2");
  return has;
}

// rank[i] = number of keys smaller than key[i]; keys must be distinct and
// below 2^63 (compared as signed integers).
__attribute__((target("avx2"))) inline void key_ranks(const int64_t* key, int32_t n,
                                                       int32_t* rank) {
  for (int32_t i = 0; i < n; ++i) {
    const __m256i item = _mm256_set1_epi64x(key[i]);
    __m256i count = _mm256_setzero_si256();
    int32_t j = 0;
    for (; j + 4 <= n; j += 4) {
      const __m256i other = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(key + j));
      count = _mm256_sub_epi64(count, _mm256_cmpgt_epi64(item, other));  // -1 where smaller
    }
    alignas(32) int64_t lanes[4];
    _mm256_store_si256(reinterpret_cast<__m256i*>(lanes), count);
    int64_t smaller = lanes[0] + lanes[1] + lanes[2] + lanes[3];
    for (; j < n; ++j) smaller += key[j] < key[i];
    rank[i] = static_cast<int32_t>(smaller);
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
