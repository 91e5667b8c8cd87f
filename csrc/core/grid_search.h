// k-nearest-neighbour search on a uniform grid (paper §2, Alg. 1).
//
// Points are sorted by grid cell; a query visits cells in concentric rings
// (Chebyshev shells) around its own cell, keeps the k best candidates in a
// max-heap and stops once no point outside the visited cube can beat the
// heap's worst candidate. Ragged batches: every batch element has its own grid
// (origin, cell size, dims), all stored in one cell-start array.
#pragma once

#include "common.h"

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

// Max-heap of (squared distance, index) pairs ordered lexicographically, so
// that ties are broken by the lower index. `stride` lets several queries
// interleave their heaps (element e of a heap lives at e * stride).
template <typename T>
struct NeighborHeap {
  T* dist2;
  int32_t* index;
  int64_t stride;
  int32_t capacity;
  int32_t size;

  TV_HD static bool less(T da, int32_t ia, T db, int32_t ib) {
    return da < db || (da == db && ia < ib);
  }
  TV_HD T& d(int32_t e) const { return dist2[e * stride]; }
  TV_HD int32_t& i(int32_t e) const { return index[e * stride]; }
  TV_HD bool full() const { return size == capacity; }
  TV_HD T worst() const { return d(0); }

  TV_HD void offer(T dist, int32_t idx) {
    if (size < capacity) {  // sift up
      int32_t e = size++;
      while (e > 0) {
        const int32_t parent = (e - 1) >> 1;
        if (!less(d(parent), i(parent), dist, idx)) break;
        d(e) = d(parent);
        i(e) = i(parent);
        e = parent;
      }
      d(e) = dist;
      i(e) = idx;
    } else if (less(dist, idx, d(0), i(0))) {
      sift_down(0, size, dist, idx);
    }
  }

  // Place (dist, idx) at position e of the heap [0, n) and restore heap order.
  TV_HD void sift_down(int32_t e, int32_t n, T dist, int32_t idx) {
    while (true) {
      int32_t child = 2 * e + 1;
      if (child >= n) break;
      if (child + 1 < n && less(d(child), i(child), d(child + 1), i(child + 1))) ++child;
      if (!less(dist, idx, d(child), i(child))) break;
      d(e) = d(child);
      i(e) = i(child);
      e = child;
    }
    d(e) = dist;
    i(e) = idx;
  }

  // Heap sort into increasing order; pad unused slots with (inf, -1).
  TV_HD void sort_and_pad(T infinity) {
    for (int32_t n = size - 1; n > 0; --n) {
      const T top_d = d(0);
      const int32_t top_i = i(0);
      sift_down(0, n, d(n), i(n));
      d(n) = top_d;
      i(n) = top_i;
    }
    for (int32_t e = size; e < capacity; ++e) {
      d(e) = infinity;
      i(e) = -1;
    }
  }
};

// Offer every point of the sorted range [begin, end) to the heap.
template <typename T>
TV_HD void offer_range(const GridView<T>& grid, int32_t begin, int32_t end, Vec3<T> query,
                       int32_t excluded, NeighborHeap<T>& heap) {
  for (int32_t s = begin; s < end; ++s) {
    const int32_t original = grid.sorted_index[s];
    if (original == excluded) continue;
    heap.offer(squared_distance(load_vec3(grid.sorted_points + 3 * s), query), original);
  }
}

// Fill `heap` with the k nearest points of batch element `batch` to `query`
// (excluding the point whose original index is `excluded`, or none if -1),
// sorted by (distance, index) and padded with (inf, -1).
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
      const bool z_face = (z == cz - r || z == cz + r);
      for (int32_t y = y0; y <= y1; ++y) {
        const int32_t row = offset + (z * dy + y) * dx;
        if (z_face || y == cy - r || y == cy + r) {
          // a full row of the shell: its cells are contiguous in sorted order
          offer_range(grid, grid.cell_start[row + x0], grid.cell_start[row + x1 + 1], query,
                      excluded, heap);
        } else {
          if (cx - r >= 0)
            offer_range(grid, grid.cell_start[row + cx - r], grid.cell_start[row + cx - r + 1],
                        query, excluded, heap);
          if (r > 0 && cx + r < dx)
            offer_range(grid, grid.cell_start[row + cx + r], grid.cell_start[row + cx + r + 1],
                        query, excluded, heap);
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
  heap.sort_and_pad(infinity);
}

}  // namespace core
}  // namespace torchvor
