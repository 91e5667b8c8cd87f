// Checks the kNN's rank counts (csrc/core/key_ranks.h) against std::sort:
// key_ranks' AVX2 and AVX-512 forms (each where the CPU has it), pair_ranks and
// ranks_by_first_of_pairs, for every n from 1 to kMaxRankedKeys on random,
// sorted, reversed and nearly equal keys, and pairs with tied first elements.
//   usage: key_ranks SEED      exit 0: all equal; 1: a mismatch (printed); 77: no AVX2
#include <algorithm>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <numeric>
#include <random>
#include <vector>

#include "core/key_ranks.h"

using namespace torchvor::core;

namespace {

// Rank by sorting positions on (first, second).
std::vector<int32_t> sorted_ranks(const std::vector<int64_t>& first, const std::vector<int64_t>& second) {
  std::vector<int32_t> order(first.size()), rank(first.size());
  std::iota(order.begin(), order.end(), 0);
  std::sort(order.begin(), order.end(), [&](int32_t a, int32_t b) {
    return first[a] < first[b] || (first[a] == first[b] && second[a] < second[b]);
  });
  for (size_t r = 0; r < order.size(); ++r) rank[order[r]] = int32_t(r);
  return rank;
}

int failures = 0;

void expect(const char* what, const char* shape, int32_t n, const std::vector<int32_t>& got,
            const std::vector<int32_t>& want) {
  if (got == want) return;
  if (++failures <= 10) std::printf("MISMATCH %s, %s keys, n=%d\n", what, shape, n);
}

}  // namespace

int main(int argc, char** argv) {
  if (!cpu_has_avx2()) return 77;
  std::mt19937_64 rng(argc > 1 ? std::strtoull(argv[1], nullptr, 10) : 1);
  const int64_t top = INT64_MAX;
  const char* shapes[] = {"random", "ascending", "descending", "near the top", "one apart"};
  for (int32_t n = 1; n <= kMaxRankedKeys; ++n) {
    for (int shape = 0; shape < 5; ++shape) {
      std::vector<int64_t> key(n), index(n);
      const int64_t base = int64_t(rng() >> 2);
      for (int32_t i = 0; i < n; ++i) {
        switch (shape) {
          case 0: key[i] = int64_t(rng() >> 1); break;
          case 1: key[i] = base + i; break;
          case 2: key[i] = base - i; break;
          case 3: key[i] = top - int64_t(rng() % 1000000); break;
          default: key[i] = base + ((i * 37) % n); break;  // a permutation of n consecutive keys
        }
        index[i] = int64_t(rng() % 1000000);
      }
      std::sort(key.begin(), key.end());
      key.erase(std::unique(key.begin(), key.end()), key.end());  // distinct keys
      if (shape == 0 || shape == 3 || shape == 4) std::shuffle(key.begin(), key.end(), rng);
      if (shape == 2) std::reverse(key.begin(), key.end());
      const int32_t m = int32_t(key.size());
      const std::vector<int64_t> none(m, 0);
      const std::vector<int32_t> want = sorted_ranks(key, none);
      std::vector<int32_t> got(m);
      key_ranks_avx2(key.data(), m, got.data());
      expect("key_ranks_avx2", shapes[shape], m, got, want);
      if (cpu_has_avx512()) {
        key_ranks_avx512(key.data(), m, got.data());
        expect("key_ranks_avx512", shapes[shape], m, got, want);
      }
      key_ranks(key.data(), m, got.data());
      expect("key_ranks", shapes[shape], m, got, want);
      // pairs: first elements with ties (drawn from a few values), distinct pairs
      std::vector<int64_t> first(m), second(m);
      for (int32_t i = 0; i < m; ++i) {
        first[i] = key[rng() % (m < 4 ? 1 : m / 4 + 1)];
        second[i] = i;
      }
      std::shuffle(second.begin(), second.end(), rng);
      const std::vector<int32_t> pair_want = sorted_ranks(first, second);
      pair_ranks(first.data(), second.data(), m, got.data());
      expect("pair_ranks", shapes[shape], m, got, pair_want);
      ranks_by_first_of_pairs(first.data(), second.data(), m, got.data());
      expect("ranks_by_first_of_pairs (ties)", shapes[shape], m, got, pair_want);
      ranks_by_first_of_pairs(key.data(), index.data(), m, got.data());
      expect("ranks_by_first_of_pairs (distinct)", shapes[shape], m, got, want);
    }
  }
  std::printf("%s: AVX-512 %s\n", failures ? "FAILED" : "ok", cpu_has_avx512() ? "checked" : "not on this CPU");
  return failures ? 1 : 0;
}
