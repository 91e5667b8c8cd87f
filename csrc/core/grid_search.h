// k-nearest-neighbour search on a uniform grid (paper §2, Alg. 1).
//
// Points are sorted by grid cell; a query visits cells in concentric rings
// (Chebyshev shells) around its own cell, keeps the k best candidates in a
// max-heap and stops once no point outside the visited cube can beat the
// heap's worst candidate. Ragged batches: every batch element has its own grid
// (origin, cell size, dims), all stored in one cell-start array.
#pragma once

#include <cmath>
#include <cstring>
#include <type_traits>

#if !defined(__CUDA_ARCH__)
#include <algorithm>
#endif

#include "common.h"
#include "key_ranks.h"

namespace torchvor {
namespace core {

template <typename T>
struct GridView {
  const T* sorted_points;        // (N, 3) points in cell order
  const int32_t* sorted_index;   // (N,) original index of each sorted point
  const int32_t* cell_start;     // (num_cells + 1,) first sorted point of each cell
  const T* origin;               // (B, 3) low corner of each batch element's grid
  const T* cell_size;            // (B,) edge length of the cubic grid cells
  const int32_t* dims;           // (B, 3) number of cells along x, y, z
  const int32_t* cell_offset;    // (B,) id of each batch element's first cell
};

// Cell coordinate of x along one axis, clamped into the grid.
template <typename T>
TV_HD int32_t grid_coordinate(T x, T origin, T cell_size, int32_t dim) {
  const T u = (x - origin) / cell_size;
  if (!(u > T(0))) return 0;  // also catches NaN
  if (u >= T(dim)) return dim - 1;
  const int32_t c = static_cast<int32_t>(u);
  return c < dim ? c : dim - 1;
}

// Distance along one axis from x to the slab of grid cells [c, c + 1),
// reduced by `margin` (points are assigned to cells by a rounded division).
template <typename T>
TV_HD T slab_gap(T x, T origin, T cell_size, int32_t c, T margin) {
  const T low = origin + T(c) * cell_size;
  const T gap = max_of(low - x, x - (low + cell_size));
  return max_of(gap - margin, T(0));
}

TV_HD float sqrt_of(float x) { return x > 0.0f ? sqrtf(x) : 0.0f; }
TV_HD double sqrt_of(double x) { return x > 0.0 ? sqrt(x) : 0.0; }

// A candidate neighbour as one comparable key, ordered by (squared distance,
// index) so that ties go to the lower index. For float32 the two fit in one
// uint64 (non-negative float bits sort like unsigned integers): one integer
// compare per heap step. float64 keeps the pair.
template <typename T> struct HeapKey;

template <> struct HeapKey<float> {
  uint64_t bits;
  TV_HD static HeapKey make(float dist2, int32_t index) {
    uint32_t d;
    memcpy(&d, &dist2, sizeof d);
    return {(uint64_t(d) << 32) | uint32_t(index)};
  }
  TV_HD float dist2() const {
    const uint32_t d = uint32_t(bits >> 32);
    float f;
    memcpy(&f, &d, sizeof f);
    return f;
  }
  TV_HD int32_t index() const { return int32_t(uint32_t(bits)); }
  TV_HD bool operator<(const HeapKey& other) const { return bits < other.bits; }
  // `when ? a : b` as bit operations: host compilers turn the ternary into an
  // unpredictable branch here.
  TV_HD static HeapKey select(bool when, HeapKey a, HeapKey b) {
    const uint64_t mask = uint64_t(0) - uint64_t(when);
    return {(a.bits & mask) | (b.bits & ~mask)};
  }
};

template <> struct HeapKey<double> {
  double d;
  int32_t i;
  TV_HD static HeapKey make(double dist2, int32_t index) { return {dist2, index}; }
  TV_HD double dist2() const { return d; }
  TV_HD int32_t index() const { return i; }
  TV_HD bool operator<(const HeapKey& other) const {
    return d < other.d || (d == other.d && i < other.i);
  }
  TV_HD static HeapKey select(bool when, HeapKey a, HeapKey b) { return when ? a : b; }
};

// Max-heap of candidate keys: the root is the worst of the k best so far.
// Four children per node: half the depth of a binary heap, and the children
// of a node share a cache line on the host. The larger-child choice is a
// select, not a branch; replacing the root costs ~30% less than with a
// binary heap (CPU, 1M points, k=35).
template <typename T>
struct NeighborHeap {
  static constexpr int32_t kArity = 4;

  StridedArray<HeapKey<T>> key;  // capacity slots
  int32_t capacity;
  int32_t size;

  TV_HD bool full() const { return size == capacity; }
  TV_HD T worst() const { return key[0].dist2(); }

  // Add a candidate to a heap that is not full yet (sift up).
  TV_HD void push(HeapKey<T> item) {
    int32_t e = size++;
    while (e > 0) {
      const int32_t parent = (e - 1) / kArity;
      const HeapKey<T> above = key[parent];
      if (!(above < item)) break;
      key[e] = above;
      e = parent;
    }
    key[e] = item;
  }

  // Replace the root (the worst key) by a better `item`.
  TV_HD void replace_root(HeapKey<T> item) { sift_down(0, size, item); }

  // Place `item` at position e of the heap [0, n) and restore heap order.
  TV_HD void sift_down(int32_t e, int32_t n, HeapKey<T> item) {
    for (int32_t first = kArity * e + 1; first < n; first = kArity * e + 1) {
      int32_t child = first;
      HeapKey<T> larger = key[first];
      TV_UNROLL
      for (int32_t c = first + 1; c < first + kArity; ++c) {
        if (c < n) {
          const HeapKey<T> other = key[c];
          const bool bigger = larger < other;
          larger = HeapKey<T>::select(bigger, other, larger);
          child += (c - child) & -int32_t(bigger);
        }
      }
      if (!(item < larger)) break;
      key[e] = larger;
      e = child;
    }
    key[e] = item;
  }

  // Write the keys in increasing order as (dist2, index), padded with
  // (inf, -1), element e at e * stride; `dist2_out` may be null. The heap is
  // consumed. Host: an AVX2 rank count for float keys (key_ranks.h), else
  // std::sort; device: heap sort in place (no extra memory).
  template <typename index_t>
  TV_HD void write_sorted(T* dist2_out, index_t* index_out, int64_t stride, T infinity) {
    const auto write = [&](int32_t e, const HeapKey<T>& item) {
      index_out[e * stride] = item.index();
      if (dist2_out) dist2_out[e * stride] = item.dist2();
    };
    bool ranked = false;
#if defined(TORCHVOR_HAS_KEY_RANKS) && !defined(__CUDA_ARCH__)
    if constexpr (std::is_same<T, float>::value) {
      if (key.stride == 1 && size <= kMaxRankedKeys && cpu_has_avx2()) {
        // float keys are one uint64 with a clear top bit: distinct and signed-comparable
        int32_t rank[kMaxRankedKeys];
        key_ranks(reinterpret_cast<const int64_t*>(key.data), size, rank);
        for (int32_t i = 0; i < size; ++i) write(rank[i], key.data[i]);
        ranked = true;
      }
    }
#endif
    if (!ranked) {
#if !defined(__CUDA_ARCH__)
      if (key.stride == 1) {
        std::sort(key.data, key.data + size);
      } else
#endif
      {
        for (int32_t n = size - 1; n > 0; --n) {
          const HeapKey<T> top = key[0];
          sift_down(0, n, key[n]);
          key[n] = top;
        }
      }
      for (int32_t e = 0; e < size; ++e) write(e, key[e]);
    }
    for (int32_t e = size; e < capacity; ++e) {
      index_out[e * stride] = -1;
      if (dist2_out) dist2_out[e * stride] = infinity;
    }
  }
};

// Offer every point of the sorted range [begin, end) to the heap. Two
// phases: fill the heap, then compare each candidate with the worst key kept
// in a register (most candidates stop there).
template <typename T>
TV_HD void offer_range(const GridView<T>& grid, int32_t begin, int32_t end, Vec3<T> query,
                       int32_t excluded, NeighborHeap<T>& heap) {
  const auto candidate = [&](int32_t s, int32_t original) {
    return HeapKey<T>::make(squared_distance(load_vec3(grid.sorted_points + 3 * s), query), original);
  };
  int32_t s = begin;
  for (; s < end && !heap.full(); ++s) {
    const int32_t original = grid.sorted_index[s];
    if (original != excluded) heap.push(candidate(s, original));
  }
  if (s == end) return;
  HeapKey<T> worst = heap.key[0];
  for (; s < end; ++s) {
    const int32_t original = grid.sorted_index[s];
    const HeapKey<T> item = candidate(s, original);
    // The excluded point (the query itself, at distance 0) passes the first test.
    if (item < worst && original != excluded) {
      heap.replace_root(item);
      worst = heap.key[0];
    }
  }
}

// Fill `heap` with the k nearest points of batch element `batch` to `query`
// (excluding the point whose original index is `excluded`, or none if -1).
template <typename T>
TV_HD void knn_search(const GridView<T>& grid, int64_t batch, Vec3<T> query, int32_t excluded,
                      NeighborHeap<T>& heap, T infinity) {
  heap.size = 0;
  const T h = grid.cell_size[batch];
  const Vec3<T> origin = load_vec3(grid.origin + 3 * batch);
  const int32_t dx = grid.dims[3 * batch], dy = grid.dims[3 * batch + 1], dz = grid.dims[3 * batch + 2];
  const int32_t offset = grid.cell_offset[batch];
  const int32_t cx = grid_coordinate(query.x, origin.x, h, dx);
  const int32_t cy = grid_coordinate(query.y, origin.y, h, dy);
  const int32_t cz = grid_coordinate(query.z, origin.z, h, dz);
  // Points are assigned to cells by a rounded division: keep a margin so that
  // the ring bound below never overestimates the distance to unvisited cells.
  const T margin = h * T(1e-3);

  for (int32_t r = 0;; ++r) {
    const int32_t z0 = max_of(cz - r, 0), z1 = min_of(cz + r, dz - 1);
    const int32_t y0 = max_of(cy - r, 0), y1 = min_of(cy + r, dy - 1);
    const int32_t x0 = max_of(cx - r, 0), x1 = min_of(cx + r, dx - 1);
    for (int32_t z = z0; z <= z1; ++z) {
      // Once the heap is full, skip cells farther than its worst candidate
      // (strictly: an equally far point with a lower index would still win).
      const T gap_z = slab_gap(query.z, origin.z, h, z, margin);
      if (heap.full() && gap_z * gap_z > heap.worst()) continue;
      const bool z_face = (z == cz - r || z == cz + r);
      for (int32_t y = y0; y <= y1; ++y) {
        const T gap_y = slab_gap(query.y, origin.y, h, y, margin);
        const T gap_yz2 = gap_z * gap_z + gap_y * gap_y;
        if (heap.full() && gap_yz2 > heap.worst()) continue;
        const int32_t row = offset + (z * dy + y) * dx;
        if (z_face || y == cy - r || y == cy + r) {
          // A full row of the shell (contiguous in sorted order), narrowed to
          // the cells within reach of the worst candidate.
          int32_t xa = x0, xb = x1;
          if (heap.full()) {
            const T reach = sqrt_of(heap.worst() - gap_yz2) + margin;
            xa = max_of(xa, grid_coordinate(query.x - reach, origin.x, h, dx));
            xb = min_of(xb, grid_coordinate(query.x + reach, origin.x, h, dx));
          }
          if (xa <= xb)
            offer_range(grid, grid.cell_start[row + xa], grid.cell_start[row + xb + 1], query,
                        excluded, heap);
        } else {
          for (int32_t x = cx - r; x <= cx + r; x += 2 * r) {
            if (x < 0 || x >= dx) continue;
            const T gap_x = slab_gap(query.x, origin.x, h, x, margin);
            if (heap.full() && gap_x * gap_x + gap_yz2 > heap.worst()) continue;
            offer_range(grid, grid.cell_start[row + x], grid.cell_start[row + x + 1], query,
                        excluded, heap);
          }
        }
      }
    }
    // Distance from the query to the nearest cell outside the visited cube.
    T bound = infinity;
    bool covers_grid = true;
    const int32_t c[3] = {cx, cy, cz};
    const int32_t dim[3] = {dx, dy, dz};
    const T q[3] = {query.x, query.y, query.z};
    const T o[3] = {origin.x, origin.y, origin.z};
    for (int a = 0; a < 3; ++a) {
      if (c[a] - r > 0) {
        covers_grid = false;
        bound = min_of(bound, q[a] - (o[a] + T(c[a] - r) * h));
      }
      if (c[a] + r < dim[a] - 1) {
        covers_grid = false;
        bound = min_of(bound, (o[a] + T(c[a] + r + 1) * h) - q[a]);
      }
    }
    if (covers_grid) break;
    bound -= margin;
    if (heap.full() && bound > T(0) && heap.worst() < bound * bound) break;
  }
}

}  // namespace core
}  // namespace torchvor
