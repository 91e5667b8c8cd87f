// k-nearest-neighbour search on a uniform grid (paper §2, Alg. 1).
//
// Points are sorted by grid cell; a query visits cells in concentric rings
// (Chebyshev shells) around its own cell, keeps the k best candidates in a
// max-heap and stops once no point outside the visited cube can beat the
// heap's worst candidate. Ragged batches: every batch element has its own grid
// (origin, cell size, dims), all stored in one cell-start array.
#pragma once

#include <cmath>
#include <type_traits>

#if !defined(__CUDA_ARCH__)
#include <algorithm>
#endif

#include "common.h"
#include "key_ranks.h"
#include "offer_packs.h"
#include "stream_stores.h"

namespace torchvor {
namespace core {

template <typename T>
struct GridView {
  const T* sorted_points;        // (N, 3) points in cell order
  const int32_t* sorted_index;   // (N,) original index of each sorted point, or nullptr:
                                 // the points are numbered in sorted order (voronoi's grid)
  const int32_t* cell_start;     // (num_cells + 1,) first sorted point of each cell
  const T* origin;               // (B, 3) low corner of each batch element's grid
  const T* cell_size;            // (B,) edge length of the cubic grid cells
  const int32_t* dims;           // (B, 3) number of cells along x, y, z
  const int32_t* cell_offset;    // (B,) id of each batch element's first cell
  const T* cell_bounds = nullptr;  // (num_cells, 6): low x, y, z and high x, y, z of each cell's
                                   // points (+inf, -inf where empty), or nullptr (the vertex-ball sweep's)

  // Original index of sorted point s. Without the index array, one load
  // fewer a candidate in the search loops.
  TV_HD int32_t original_index(int32_t s) const { return sorted_index ? sorted_index[s] : s; }
};

// The cell of position u (in cell edges from the grid's origin) along one
// axis, clamped into the grid.
template <typename T>
TV_HD int32_t cell_of_position(T u, int32_t dim) {
  if (!(u > T(0))) return 0;  // also catches NaN
  if (u >= T(dim)) return dim - 1;
  const int32_t c = static_cast<int32_t>(u);
  return c < dim ? c : dim - 1;
}

// Cell coordinate of x along one axis, clamped into the grid: how points
// are assigned to cells.
template <typename T>
TV_HD int32_t grid_coordinate(T x, T origin, T cell_size, int32_t dim) {
  return cell_of_position((x - origin) / cell_size, dim);
}

// Distance along one axis from x to the slab of grid cells [c, c + 1),
// reduced by `margin` (points are assigned to cells by a rounded division).
// The position is taken relative to the origin (u = x - origin, as
// grid_coordinate divides it): far from zero, origin + c * cell_size would
// round to the coordinates' spacing, which can exceed a cell.
template <typename T>
TV_HD T slab_gap(T u, T cell_size, int32_t c, T margin) {
  const T low = T(c) * cell_size;
  const T gap = max_of(low - u, u - (low + cell_size));
  return max_of(gap - margin, T(0));
}

// Points are assigned to grid cells by a rounded division: bounds on the
// distance to a cell keep this margin (of a cell's edge) so that they never
// overestimate it.
template <typename T>
TV_HD T cell_margin(T cell_size) {
  return cell_size * T(1e-3);
}

// The i-th grid coordinate counted from c outwards: c, c - 1, c + 1, c - 2,
// c + 2, ...
TV_HD int32_t center_out(int32_t c, int32_t i) { return c + ((i & 1) ? -((i + 1) >> 1) : (i >> 1)); }

// A candidate neighbour as one comparable key, ordered by (squared distance,
// index) so that ties go to the lower index. For float32 the two fit in one
// uint64 (non-negative float bits sort like unsigned integers): one integer
// compare per heap step. float64 keeps the pair (packed into two words on
// the host).
template <typename T> struct HeapKey;

template <> struct HeapKey<float> {
  uint64_t bits;
  TV_HD static HeapKey make(float dist2, int32_t index) {
    return {(uint64_t(float_bits(dist2)) << 32) | uint32_t(index)};
  }
  TV_HD float dist2() const { return bits_float(uint32_t(bits >> 32)); }
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
#if defined(__CUDA_ARCH__) || !defined(__SIZEOF_INT128__)
  double d;
  int32_t i;
  TV_HD static HeapKey make(double dist2, int32_t index) { return {dist2, index}; }
  TV_HD double dist2() const { return d; }
  TV_HD int32_t index() const { return i; }
  TV_HD bool operator<(const HeapKey& other) const {
    return d < other.d || (d == other.d && i < other.i);
  }
  TV_HD static HeapKey select(bool when, HeapKey a, HeapKey b) { return when ? a : b; }
#else
  // Host: the distance's bits above the index as one 96-bit unsigned
  // integer (non-negative doubles order as their bits), in two words: one
  // 128-bit compare where the pair takes several, and selects by masks (host
  // compilers make mispredicted branches of || and of a ternary on a pair).
  // The same size and alignment as the device's pair (the scratch's layout).
  uint64_t low;   // the distance's low 32 bits, then the index
  uint64_t high;  // the distance's high 32 bits
  static HeapKey make(double dist2, int32_t index) {
    uint64_t bits;
    memcpy(&bits, &dist2, sizeof bits);
    return {(bits << 32) | uint32_t(index), bits >> 32};
  }
  double dist2() const {
    const uint64_t bits = (high << 32) | (low >> 32);
    double d;
    memcpy(&d, &bits, sizeof d);
    return d;
  }
  int32_t index() const { return int32_t(uint32_t(low)); }
  bool operator<(const HeapKey& other) const {
    return ((unsigned __int128)high << 64 | low) < ((unsigned __int128)other.high << 64 | other.low);
  }
  static HeapKey select(bool when, HeapKey a, HeapKey b) {
    const uint64_t mask = uint64_t(0) - uint64_t(when);
    return {(a.low & mask) | (b.low & ~mask), (a.high & mask) | (b.high & ~mask)};
  }
#endif
};
static_assert(sizeof(HeapKey<double>) == 16 && alignof(HeapKey<double>) == 8,
              "the host's and the device's float64 keys must lay out the scratch alike");

#if defined(TORCHVOR_HAS_KEY_RANKS) && !defined(__CUDA_ARCH__)
// Host, AVX2 (the caller checks cpu_has_avx2()): the rank of each of n <=
// kMaxRankedKeys distinct keys, its place in increasing order.
template <typename T>
void heap_key_ranks(const HeapKey<T>* keys, int32_t n, int32_t* rank) {
  if constexpr (std::is_same<T, float>::value) {
    // float keys are one uint64 with a clear top bit: distinct and signed-comparable
    key_ranks(reinterpret_cast<const int64_t*>(keys), n, rank);
  } else {
    // double keys: the distance's bits (non-negative: signed-comparable), then the index
    int64_t distance[kMaxRankedKeys], index[kMaxRankedKeys];
    for (int32_t i = 0; i < n; ++i) {
      const double d = keys[i].dist2();
      memcpy(&distance[i], &d, sizeof(int64_t));
      index[i] = keys[i].index();
    }
    ranks_by_first_of_pairs(distance, index, n, rank);
  }
}
#endif

// Max-heap of candidate keys: the root is the worst of the k best so far.
// Four children per node: half the depth of a binary heap, and the children
// of a node share a cache line on the host. The larger-child choice is a
// select, not a branch; replacing the root costs less than with a binary
// heap.
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

  // Add a candidate to a heap that is not full yet. Host: without order,
  // the heap order made once, when the last slot fills (make_heap), where a
  // push each time sifts up through branches that mispredict; until then
  // only the count is read (worst() is read only when full()). The device
  // pushes: there the one make_heap costs more than the pushes.
  TV_HD void fill(HeapKey<T> item) {
#if defined(__CUDA_ARCH__)
    push(item);
#else
    key[size++] = item;
    if (size == capacity) make_heap();
#endif
  }

  // Heap order over the `size` keys, bottom-up: a sift_down from each inner node.
  TV_HD void make_heap() {
    for (int32_t e = (size - 2) / kArity; size > 1 && e >= 0; --e) sift_down(e, size, key[e]);
  }

  // Replace the root (the worst key) by a better `item`.
  TV_HD void replace_root(HeapKey<T> item) { sift_down(0, size, item); }

  // Place `item` at position e of the heap [0, n) and restore heap order.
  // A node with all its children (every node but the last inner one) takes
  // them without a test each: a per-child bounds test makes each level of
  // the GPU's sift three branches, and replacing the root is a large share
  // of the kNN kernel's instructions.
  TV_HD void sift_down(int32_t e, int32_t n, HeapKey<T> item) {
    for (int32_t first = kArity * e + 1; first < n; first = kArity * e + 1) {
      int32_t child = first;
      HeapKey<T> larger = key[first];
      const auto take = [&](int32_t c) {
        const HeapKey<T> other = key[c];
        const bool bigger = larger < other;
        larger = HeapKey<T>::select(bigger, other, larger);
        child += (c - child) & -int32_t(bigger);
      };
      if (first + kArity <= n) {
        TV_UNROLL
        for (int32_t c = first + 1; c < first + kArity; ++c) take(c);
      } else {
        for (int32_t c = first + 1; c < n; ++c) take(c);
      }
      if (!(item < larger)) break;
      key[e] = larger;
      e = child;
    }
    key[e] = item;
  }

  // Whether `a` comes before `b` in the output: by distance, then by
  // tie_order where given (else by index, as the keys compare).
  TV_HD static bool before(const HeapKey<T>& a, const HeapKey<T>& b, const int32_t* tie_order) {
    if (tie_order == nullptr || a.dist2() != b.dist2()) return a < b;
    return tie_order[a.index()] < tie_order[b.index()];
  }

  // Whether two of the `size` sorted keys share a distance.
  TV_HD bool has_ties() const {
    for (int32_t e = 1; e < size; ++e) {
      if (key[e].dist2() == key[e - 1].dist2()) return true;
    }
    return false;
  }

  // write(e, key[e]) for the `size` sorted keys; whether two of them share a distance.
  template <typename Write>
  TV_HD bool write_in_order(const Write& write) const {
    bool tied = false;
    T previous = T(-1);
    for (int32_t e = 0; e < size; ++e) {
      const HeapKey<T> item = key[e];
      write(e, item);
      tied |= item.dist2() == previous;
      previous = item.dist2();
    }
    return tied;
  }

  // Keys sorted by (distance, index): each run at one distance reordered by
  // tie_order (an insertion sort; runs are rare but on lattices).
  TV_HD void order_ties(const int32_t* tie_order) {
    for (int32_t e = 1; e < size; ++e) {
      const HeapKey<T> item = key[e];
      int32_t j = e;
      while (j > 0 && key[j - 1].dist2() == item.dist2() && before(item, key[j - 1], tie_order)) {
        key[j] = key[j - 1];
        --j;
      }
      key[j] = item;
    }
  }

  // write_sorted by a group of lanes over a heap they share: each lane
  // places its keys at their ranks (keys are distinct), so no lane sorts.
  template <typename index_t, typename Lanes>
  TV_HD void write_ranked(T* dist2_out, index_t* index_out, int64_t stride, T infinity,
                          Lanes lanes, const int32_t* tie_order = nullptr) const {
    for (int32_t e = lanes.index(); e < capacity; e += Lanes::kCount) {
      int32_t at = e;
      HeapKey<T> item = HeapKey<T>::make(infinity, -1);
      if (e < size) {
        item = key[e];
        at = 0;
        for (int32_t m = 0; m < size; ++m) at += int32_t(before(key[m], item, tie_order));
      }
      index_out[at * stride] = item.index();
      if (dist2_out) dist2_out[at * stride] = item.dist2();
    }
  }

  // Write the keys in increasing order as (dist2, index), padded with
  // (inf, -1), element e at e * stride; `dist2_out` may be null. The heap is
  // consumed. Host: an AVX2 rank count (key_ranks.h), else std::sort;
  // device: heap sort in place (no extra memory). `stream` (host, stride 1):
  // the row goes out by non-temporal stores (stream_stores.h), for results
  // far larger than the caches.
  template <typename index_t>
  TV_HD void write_sorted(T* dist2_out, index_t* index_out, int64_t stride, T infinity,
                          const int32_t* tie_order = nullptr, bool stream = false) {
    const auto write = [&](int32_t e, const HeapKey<T>& item) {
      index_out[e * stride] = item.index();
      if (dist2_out) dist2_out[e * stride] = item.dist2();
    };
    const auto pad = [&] {
      for (int32_t e = size; e < capacity; ++e) write(e, HeapKey<T>::make(infinity, -1));
    };
    bool sorted = false;
#if defined(TORCHVOR_HAS_KEY_RANKS) && !defined(__CUDA_ARCH__)
    if (key.stride == 1 && size <= kMaxRankedKeys && cpu_has_avx2()) {
      int32_t rank[kMaxRankedKeys];
      heap_key_ranks(key.data, size, rank);
      if (tie_order == nullptr && !stream) {  // each key straight to its place
        for (int32_t i = 0; i < size; ++i) write(rank[i], key.data[i]);
        pad();
        return;
      }
      HeapKey<T> in_order[kMaxRankedKeys];
      for (int32_t i = 0; i < size; ++i) in_order[rank[i]] = key.data[i];
      for (int32_t i = 0; i < size; ++i) key.data[i] = in_order[i];
      sorted = true;
    }
#endif
    if (!sorted) {
#if !defined(__CUDA_ARCH__)
      if (key.stride == 1) {
        std::sort(key.data, key.data + size);
      } else
#endif
      {
        if (!full()) make_heap();  // the host's fill() leaves a heap that never filled unordered
        for (int32_t n = size - 1; n > 0; --n) {
          const HeapKey<T> top = key[0];
          sift_down(0, n, key[n]);
          key[n] = top;
        }
      }
    }
#if defined(TORCHVOR_HAS_STREAM_STORES) && !defined(__CUDA_ARCH__)
    if (stream && stride == 1 && key.stride == 1) {  // each element stored once
      if (tie_order != nullptr && has_ties()) order_ties(tie_order);
      stream_row(key.data, size, capacity, dist2_out, index_out, infinity);
      return;
    }
#endif
    // Where two keys share a distance, again with the ties ordered.
    if (write_in_order(write) && tie_order != nullptr) {
      order_ties(tie_order);
      write_in_order(write);
    }
    pad();
  }
};

// Offer every point of the sorted range [begin, end) to the heap. Two
// phases: fill the heap, then compare each candidate with the worst key kept
// in a register (most candidates stop there); on a host with AVX2, a pack
// of candidates a compare (offer_packs.h).
template <typename T>
TV_HD void offer_range(const GridView<T>& grid, int32_t begin, int32_t end, Vec3<T> query,
                       int32_t excluded, NeighborHeap<T>& heap) {
  const auto candidate = [&](int32_t s, int32_t original) {
    return HeapKey<T>::make(squared_distance(load_vec3(grid.sorted_points + 3 * s), query), original);
  };
  int32_t s = begin;
  for (; s < end && !heap.full(); ++s) {
    const int32_t original = grid.original_index(s);
    if (original != excluded) heap.fill(candidate(s, original));
  }
  if (s == end) return;
#if defined(TORCHVOR_HAS_OFFER_PACKS) && !defined(__CUDA_ARCH__)
  if (cpu_has_avx2()) {
    offer_packs<T, NeighborHeap<T>, HeapKey<T>>(grid.sorted_points, grid.sorted_index, s, end, query, excluded, heap);
    return;
  }
#endif
  HeapKey<T> worst = heap.key[0];
  for (; s < end; ++s) {
    const T dist2 = squared_distance(load_vec3(grid.sorted_points + 3 * s), query);
#if !defined(__CUDA_ARCH__)
    // Host: most candidates are farther than the worst key; one compare of
    // distances rules them out before the key's (for float64, a pair's).
    if (dist2 > worst.dist2()) continue;
#endif
    const int32_t original = grid.original_index(s);
    const HeapKey<T> item = HeapKey<T>::make(dist2, original);
    // The excluded point (the query itself, at distance 0) passes the first test.
    if (item < worst && original != excluded) {
      heap.replace_root(item);
      worst = heap.key[0];
    }
  }
}

// Two ranges [begin, end) of sorted points (either may be empty).
struct RowRanges {
  int32_t begin[2], end[2];
};

// One query's ring search (Chebyshev shells of grid cells around its own
// cell, in its batch element's grid): which points of a shell's row to
// offer, and when to stop. The thread and the cooperative searches share it.
template <typename T>
struct Rings {
  Vec3<T> local;  // the query relative to the grid's origin
  T h;       // cell edge
  T margin;  // cell_margin(h)
  T inverse_h;  // 1 / h (row_cell)
  int32_t dim[3], cell[3], offset;

  TV_HD Rings(const GridView<T>& grid, int64_t batch, Vec3<T> q)
      : local(q - load_vec3(grid.origin + 3 * batch)), h(grid.cell_size[batch]),
        margin(cell_margin(h)), inverse_h(T(1) / h), offset(grid.cell_offset[batch]) {
    TV_UNROLL
    for (int a = 0; a < 3; ++a) dim[a] = grid.dims[3 * batch + a];
    // grid_coordinate's cells
    cell[0] = cell_of_position(local.x / h, dim[0]);
    cell[1] = cell_of_position(local.y / h, dim[1]);
    cell[2] = cell_of_position(local.z / h, dim[2]);
  }

  // Shell r's cells along axis a, clamped to the grid: [low(a, r), high(a, r)].
  TV_HD int32_t low(int a, int32_t r) const { return max_of(cell[a] - r, 0); }
  TV_HD int32_t high(int a, int32_t r) const { return min_of(cell[a] + r, dim[a] - 1); }
  // The last center_out step that reaches [low(a, r), high(a, r)]: shells far
  // wider than a thin grid cost their cells, not their width squared.
  TV_HD int32_t last_step(int a, int32_t r) const {
    return 2 * max_of(cell[a] - low(a, r), high(a, r) - cell[a]);
  }

  TV_HD T gap_z(int32_t z) const { return slab_gap(local.z, h, z, margin); }

  // The points of row (z, y) of shell r that may beat the heap's worst
  // candidate (strictly: an equally far point with a lower index would still
  // win): on a face of the shell, the row's cells within reach (contiguous
  // in sorted order); inside it, the row's two end cells.
  TV_HD RowRanges row(int32_t r, int32_t z, int32_t y, T gap_z, const int32_t* cell_start,
                      const NeighborHeap<T>& heap) const {
    RowRanges out = {{0, 0}, {0, 0}};
    const T gap_y = slab_gap(local.y, h, y, margin);
    const T gap_yz2 = gap_z * gap_z + gap_y * gap_y;
    if (heap.full() && gap_yz2 > heap.worst()) return out;
    const int32_t row_start = offset + (z * dim[1] + y) * dim[0];
    const int32_t cx = cell[0];
    if (z == cell[2] - r || z == cell[2] + r || y == cell[1] - r || y == cell[1] + r) {
      int32_t xa = low(0, r), xb = high(0, r);
      if (heap.full()) {
        const T reach = sqrt_of(heap.worst() - gap_yz2) + margin;
        xa = max_of(xa, row_cell(local.x - reach, -1));
        xb = min_of(xb, row_cell(local.x + reach, 1));
      }
      if (xa <= xb) {
        out.begin[0] = cell_start[row_start + xa];
        out.end[0] = cell_start[row_start + xb + 1];
      }
    } else {  // r >= 1: two distinct end cells
      TV_UNROLL
      for (int side = 0; side < 2; ++side) {
        const int32_t x = side == 0 ? cx - r : cx + r;
        if (x < 0 || x >= dim[0]) continue;
        const T gap_x = slab_gap(local.x, h, x, margin);
        if (heap.full() && gap_x * gap_x + gap_yz2 > heap.worst()) continue;
        out.begin[side] = cell_start[row_start + x];
        out.end[side] = cell_start[row_start + x + 1];
      }
    }
    return out;
  }

  // A bound on the cell of position x (relative to the origin, as `local`)
  // along x on the side `side` (-1: at most, 1: at least), for the row's
  // cells within reach. A product by 1 / h
  // instead of the division by h: the division is ~8 instructions on the
  // GPU, twice a row of the search, and the kNN kernel is bound by the
  // instructions it issues. The two differ by at most ~3 units in the
  // last place in float32 (2^-22 of u), so u moved outwards by 2^-20 of
  // itself bounds the quotient's cell. The search's result is unchanged: the
  // bound only prunes, and errs on the safe side.
  TV_HD int32_t row_cell(T x, int side) const {
    const T u = x * inverse_h;
    const T widened = u + T(side) * (u < T(0) ? -u : u) * (T(1) / T(1 << 20));
    return cell_of_position(widened, dim[0]);
  }

  // Whether shell r was the last one: no point outside its cube can enter
  // the heap (or the cube covers the whole grid).
  TV_HD bool exhausted(int32_t r, const NeighborHeap<T>& heap, T infinity) const {
    const T u[3] = {local.x, local.y, local.z};
    T bound = infinity;  // distance to the nearest cell outside the cube
    bool covers_grid = true;
    TV_UNROLL
    for (int a = 0; a < 3; ++a) {
      if (cell[a] - r > 0) {
        covers_grid = false;
        bound = min_of(bound, u[a] - T(cell[a] - r) * h);
      }
      if (cell[a] + r < dim[a] - 1) {
        covers_grid = false;
        bound = min_of(bound, T(cell[a] + r + 1) * h - u[a]);
      }
    }
    if (covers_grid) return true;
    bound -= margin;
    return heap.full() && bound > T(0) && heap.worst() < bound * bound;
  }
};

// Fill `heap` with the k nearest points of batch element `batch` to `query`
// (excluding the point whose original index is `excluded`, or none if -1).
// One thread per query.
template <typename T>
TV_HD void knn_search(const GridView<T>& grid, int64_t batch, Vec3<T> query, int32_t excluded,
                      NeighborHeap<T>& heap, T infinity) {
  heap.size = 0;
  const Rings<T> rings(grid, batch, query);
  for (int32_t r = 0;; ++r) {
    // Slabs and rows from the query's own outwards: the heap fills with
    // nearer candidates first, so fewer later ones replace its root.
    for (int32_t step_z = 0; step_z <= rings.last_step(2, r); ++step_z) {
      const int32_t z = center_out(rings.cell[2], step_z);
      if (z < rings.low(2, r) || z > rings.high(2, r)) continue;
      // A whole slab of rows beyond the worst candidate: skip it.
      const T gap_z = rings.gap_z(z);
      if (heap.full() && gap_z * gap_z > heap.worst()) continue;
      for (int32_t step_y = 0; step_y <= rings.last_step(1, r); ++step_y) {
        const int32_t y = center_out(rings.cell[1], step_y);
        if (y < rings.low(1, r) || y > rings.high(1, r)) continue;
        const RowRanges ranges = rings.row(r, z, y, gap_z, grid.cell_start, heap);
        TV_UNROLL
        for (int i = 0; i < 2; ++i) {
          if (ranges.begin[i] < ranges.end[i])
            offer_range(grid, ranges.begin[i], ranges.end[i], query, excluded, heap);
        }
      }
    }
    if (rings.exhausted(r, heap, infinity)) break;
  }
}

// knn_search by a group of lanes (lanes.h): the rows of each shell are
// spread over the lanes, so their cell and point loads are in flight
// together, where one thread per query waits on them one after another (a
// pass over few queries takes as long as its slowest query). The heap lives
// in memory the lanes share; lane 0 inserts the candidates the lanes found
// (passed through `offered`, one slot per lane). Same keys, same pruning
// bounds: the result equals knn_search's.
template <typename T, typename Lanes>
TV_HD void knn_search_cooperative(const GridView<T>& grid, int64_t batch, Vec3<T> query,
                                  int32_t excluded, NeighborHeap<T>& heap,
                                  StridedArray<HeapKey<T>> offered, T infinity, Lanes lanes) {
  heap.size = 0;  // every lane keeps the same count
  const Rings<T> rings(grid, batch, query);
  const int lane = lanes.index();
  for (int32_t r = 0;; ++r) {
    const int32_t z0 = rings.low(2, r), y0 = rings.low(1, r);
    const int32_t ny = rings.high(1, r) - y0 + 1;
    const int32_t rows = (rings.high(2, r) - z0 + 1) * ny;
    for (int32_t first = 0; first < rows; first += Lanes::kCount) {
      RowRanges mine = {{0, 0}, {0, 0}};
      const int32_t p = first + lane;
      if (p < rows) {
        const int32_t z = z0 + p / ny, y = y0 + p % ny;
        mine = rings.row(r, z, y, rings.gap_z(z), grid.cell_start, heap);
      }
      // Each lane walks its ranges; every step, the lanes' candidates go
      // to lane 0, in lane order.
      int32_t s = mine.begin[0], end = mine.end[0];
      bool second = false;
      for (;;) {
        if (s >= end && !second) {
          s = mine.begin[1];
          end = mine.end[1];
          second = true;
        }
        const bool has_point = s < end;
        if (!lanes.any(has_point)) break;
        HeapKey<T> item = HeapKey<T>::make(T(0), -1);
        bool candidate = false;
        if (has_point) {
          const int32_t original = grid.original_index(s);
          item = HeapKey<T>::make(squared_distance(load_vec3(grid.sorted_points + 3 * s), query), original);
          candidate = original != excluded && (!heap.full() || item < heap.key[0]);
          ++s;
        }
        const uint32_t word = lanes.ballot(candidate);
        if (word == 0u) continue;
        if (candidate) offered[lane] = item;
        lanes.sync();
        if (lane == 0) {
          NeighborHeap<T> own = heap;
          for (uint32_t bits = word; bits != 0u; bits &= bits - 1u) {
            const HeapKey<T> next = offered[lowest_bit(bits)];
            if (!own.full()) {
              own.push(next);
            } else if (next < own.key[0]) {
              own.replace_root(next);
            }
          }
        }
        lanes.sync();
        // Lane 0 pushed while the heap had room, as many as were offered.
        heap.size = min_of(heap.size + bit_count(word), heap.capacity);
      }
    }
    if (rings.exhausted(r, heap, infinity)) break;
  }
}

}  // namespace core
}  // namespace torchvor
