// Checks the kNN's packed candidate loop (csrc/core/offer_packs.h) against
// the scalar loop it replaces (grid_search.h's offer_range): from the same
// full heap, offering the same range of points must leave the heap's slots
// exactly alike, in float and float64, for ranges of 1 to 40 points (every
// pack tail), with and without an index array and an excluded point, on
// random points, lattices (equal distances) and repeated points.
//   usage: offer_packs SEED      exit 0: all equal; 1: a mismatch (printed); 77: no AVX2
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <random>
#include <vector>

#include "core/grid_search.h"

using namespace torchvor::core;

namespace {

template <typename T>
void scalar_offer(const T* points, const int32_t* sorted_index, int32_t s, int32_t end, Vec3<T> query,
                  int32_t excluded, NeighborHeap<T>& heap) {
  HeapKey<T> worst = heap.key[0];
  for (; s < end; ++s) {
    const T dist2 = squared_distance(load_vec3(points + 3 * s), query);
    if (dist2 > worst.dist2()) continue;
    const int32_t original = sorted_index ? sorted_index[s] : s;
    const HeapKey<T> item = HeapKey<T>::make(dist2, original);
    if (item < worst && original != excluded) {
      heap.replace_root(item);
      worst = heap.key[0];
    }
  }
}

template <typename T>
int check(std::mt19937& rng, int trials) {
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  int failures = 0;
  for (int trial = 0; trial < trials; ++trial) {
    const int kind = trial % 3;  // random, lattice, repeated points
    const int32_t count = 1 + trial % 40, k = 1 + int32_t(rng() % 48), n = 48 + count;
    std::vector<T> points(3 * n);
    for (int32_t i = 0; i < n; ++i) {
      for (int a = 0; a < 3; ++a) {
        const double u = unit(rng);
        points[3 * i + a] = kind == 0 ? T(u) : kind == 1 ? T(double(rng() % 5) * 0.25) : T(double(rng() % 2));
      }
    }
    std::vector<int32_t> index(n);
    for (int32_t i = 0; i < n; ++i) index[i] = int32_t(rng() % 1000);
    const bool with_index = trial % 2 == 0;
    const int32_t first = 48;  // the range [48, 48 + count); the heap from the points before it
    const int32_t* sorted_index = with_index ? index.data() : nullptr;
    const Vec3<T> query = trial % 4 == 1 ? load_vec3(points.data() + 3 * (first + count / 2))
                                         : Vec3<T>{T(unit(rng)), T(unit(rng)), T(unit(rng))};
    const int32_t excluded = trial % 4 == 1 ? (with_index ? index[first + count / 2] : first + count / 2) : -1;
    std::vector<HeapKey<T>> slots_a(k), slots_b(k);
    NeighborHeap<T> a{StridedArray<HeapKey<T>>{slots_a.data(), 1}, k, 0};
    for (int32_t s = 0; s < first && !a.full(); ++s) {
      a.push(HeapKey<T>::make(squared_distance(load_vec3(points.data() + 3 * s), query),
                              sorted_index ? sorted_index[s] : s));
    }
    if (!a.full()) continue;
    NeighborHeap<T> b{StridedArray<HeapKey<T>>{slots_b.data(), 1}, k, k};
    slots_b = slots_a;
    scalar_offer(points.data(), sorted_index, first, first + count, query, excluded, a);
    offer_packs<T, NeighborHeap<T>, HeapKey<T>>(points.data(), sorted_index, first, first + count, query, excluded, b);
    for (int32_t e = 0; e < k; ++e) {
      if (slots_a[e] < slots_b[e] || slots_b[e] < slots_a[e]) {
        std::printf("%s trial %d (kind %d, %d points, k %d, index %d, excluded %d): slot %d differs\n",
                    sizeof(T) == 4 ? "float" : "double", trial, kind, count, k, int(with_index), excluded, e);
        ++failures;
        break;
      }
    }
  }
  return failures;
}

}  // namespace

int main(int argc, char** argv) {
  if (!cpu_has_avx2()) return 77;
  std::mt19937 rng(argc > 1 ? unsigned(std::strtoul(argv[1], nullptr, 10)) : 1u);
  const int failures = check<float>(rng, 20000) + check<double>(rng, 20000);
  std::printf("%d mismatches\n", failures);
  return failures == 0 ? 0 : 1;
}
