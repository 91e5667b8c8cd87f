// torchvor::radius, shared by the CPU and CUDA backends: every point within
// distance r of each query, found on the grid in two passes (count, then fill
// from the counts' offsets), so that memory is the output's and no more.
#pragma once

#include <ATen/ATen.h>

#include <cmath>
#include <tuple>
#include <vector>

#include "../core/grid_search.h"
#include "checks.h"
#include "grid.h"

namespace torchvor {
namespace ops {

// Orders a query's m found points by (squared distance, index), in place
// (the keys are distinct, so the order is total and no stability is
// needed). Host: one kNN key a point (the indices are below 2^31 here),
// ranked by the AVX2 rank count up to its size, else std::sort, without the
// heap sort's mispredicted branches. Device: a heap sort, O(m log m) for any
// m and no extra memory.
template <typename T>
TV_HD void sort_by_distance(T* dist2, int64_t* index, int64_t m) {
#if !defined(__CUDA_ARCH__)
  using Key = core::HeapKey<T>;
  constexpr int64_t kOnStack = 128;
  Key on_stack[kOnStack];
  std::vector<Key> on_heap;
  Key* key = on_stack;
  if (m > kOnStack) {
    on_heap.resize(static_cast<size_t>(m));
    key = on_heap.data();
  }
  for (int64_t i = 0; i < m; ++i) key[i] = Key::make(dist2[i], static_cast<int32_t>(index[i]));
#if defined(TORCHVOR_HAS_KEY_RANKS)
  if (m <= core::kMaxRankedKeys && core::cpu_has_avx2()) {
    int32_t rank[core::kMaxRankedKeys];
    core::heap_key_ranks(key, static_cast<int32_t>(m), rank);
    for (int64_t i = 0; i < m; ++i) {
      dist2[rank[i]] = key[i].dist2();
      index[rank[i]] = key[i].index();
    }
    return;
  }
#endif
  std::sort(key, key + m);
  for (int64_t i = 0; i < m; ++i) {
    dist2[i] = key[i].dist2();
    index[i] = key[i].index();
  }
#else
  const auto less = [&](int64_t a, int64_t b) {
    return dist2[a] < dist2[b] || (dist2[a] == dist2[b] && index[a] < index[b]);
  };
  const auto swap = [&](int64_t a, int64_t b) {
    const T d = dist2[a];
    dist2[a] = dist2[b];
    dist2[b] = d;
    const int64_t i = index[a];
    index[a] = index[b];
    index[b] = i;
  };
  const auto sift_down = [&](int64_t root, int64_t end) {  // a max-heap on [0, end)
    for (int64_t child = 2 * root + 1; child < end; root = child, child = 2 * root + 1) {
      if (child + 1 < end && less(child, child + 1)) ++child;
      if (!less(root, child)) return;
      swap(root, child);
    }
  };
  for (int64_t start = m / 2 - 1; start >= 0; --start) sift_down(start, m);
  for (int64_t end = m - 1; end > 0; --end) {
    swap(0, end);
    sift_down(0, end);
  }
#endif
}

// Query q's points within r (|p - q|^2 <= r^2, q itself left out when
// `exclude_self`), visited row by row of the grid cells that the query's
// cube of half side r meets: counted (counts, the count pass) or written
// from offsets[q] on and sorted by distance (the fill pass).
template <typename T>
struct RadiusFunctor {
  core::GridView<T> grid;
  const T* queries;             // (M, 3)
  const int64_t* query_batch;   // (M,) or nullptr
  const int32_t* order;         // step t searches query order[t]: grid order, nearby queries read the same cells
  T r, r2;
  bool exclude_self;
  int64_t* counts;              // count pass: (M,); nullptr in the fill pass
  const int64_t* offsets;       // fill pass: (M,) each query's first output
  int64_t* index;               // fill pass: (E,) the points' indices
  T* dist2;                     // fill pass: (E,) their squared distances

  TV_HD void operator()(int64_t t) const {
    const int64_t q = order[t];
    const int64_t b = query_batch ? query_batch[q] : 0;
    const core::Vec3<T> x = core::load_vec3(queries + 3 * q);
    const core::Vec3<T> local = x - core::load_vec3(grid.origin + 3 * b);
    const T h = grid.cell_size[b];
    // Points are assigned to cells by a rounded division: a margin keeps a
    // point at about distance r inside the cells visited.
    const T reach = r + core::cell_margin(h);
    const int32_t dim[3] = {grid.dims[3 * b], grid.dims[3 * b + 1], grid.dims[3 * b + 2]};
    const T u[3] = {local.x, local.y, local.z};
    int32_t low[3], high[3];
    for (int a = 0; a < 3; ++a) {
      low[a] = core::cell_of_position((u[a] - reach) / h, dim[a]);
      high[a] = core::cell_of_position((u[a] + reach) / h, dim[a]);
    }
    const int32_t first_cell = grid.cell_offset[b];
    int64_t found = 0;
    int64_t* out_index = counts ? nullptr : index + offsets[q];
    T* out_dist2 = counts ? nullptr : dist2 + offsets[q];
    for (int32_t z = low[2]; z <= high[2]; ++z) {
      for (int32_t y = low[1]; y <= high[1]; ++y) {
        // A row of cells along x is one range of the sorted points.
        const int32_t row = first_cell + (z * dim[1] + y) * dim[0];
        const int32_t from = grid.cell_start[row + low[0]], to = grid.cell_start[row + high[0] + 1];
        for (int32_t s = from; s < to; ++s) {
          const T d2 = core::squared_norm(core::load_vec3(grid.sorted_points + 3 * int64_t(s)) - x);
          if (!(d2 <= r2)) continue;
          const int32_t p = grid.original_index(s);
          if (exclude_self && p == q) continue;
          if (!counts) {
            out_index[found] = p;
            out_dist2[found] = d2;
          }
          ++found;
        }
      }
    }
    if (counts) {
      counts[q] = found;
    } else {
      sort_by_distance(out_dist2, out_index, found);
    }
  }
};

// Every point within r of each query: (index (E,) int64, row (E,) int64 the
// query, dist2 (E,)), sorted by row (each query's points are written from its
// offset on), then squared distance, then index.
// Points and queries of different batch elements never pair.
template <typename Exec>
std::tuple<at::Tensor, at::Tensor, at::Tensor> radius_forward(const at::Tensor& points_in,
                                                              const at::Tensor& queries_in, double r,
                                                              const c10::optional<at::Tensor>& points_batch_in,
                                                              const c10::optional<at::Tensor>& queries_batch_in,
                                                              bool exclude_self) {
  const auto contiguous = [](const c10::optional<at::Tensor>& t) {
    return t.has_value() ? c10::optional<at::Tensor>(t->contiguous()) : c10::nullopt;
  };
  const c10::optional<at::Tensor> points_batch = contiguous(points_batch_in);
  const c10::optional<at::Tensor> queries_batch = contiguous(queries_batch_in);
  const int64_t num_batches =
      check_knn_inputs(points_in, queries_in, 1, points_batch, queries_batch, exclude_self);
  TORCH_CHECK_VALUE(std::isfinite(r) && r >= 0.0, "torchvor: r must be finite and non-negative, got ", r);
  const int64_t m = queries_in.size(0), n = points_in.size(0);
  TORCH_CHECK_VALUE(n < (int64_t(1) << 31), "torchvor: radius takes fewer than 2^31 points, got ", n);
  const at::Tensor points = points_in.contiguous();
  const at::Tensor queries = queries_in.contiguous();
  const ValueChecks values = knn_value_checks(points, queries);
  const auto long_options = queries.options().dtype(at::kLong);
  if (m == 0 || n == 0) {
    values.run();
    return {at::empty({0}, long_options), at::empty({0}, long_options), at::empty({0}, queries.options())};
  }
  std::vector<double> holds;
  const at::Tensor bounds = point_bounds<Exec>(points, points_batch, num_batches, values.conditions(), &holds);
  values.verify(holds.data());
  // A few points a cell: a ball much wider than a cell visits about twice
  // as many points as it holds, one much narrower a few cells.
  const Grid grid = build_grid<Exec>(points, points_batch, num_batches, /*points_per_cell=*/4.0, bounds);
  const at::Tensor order = query_order<Exec>(grid, queries, queries_batch, exclude_self && !points_batch.has_value());
  at::Tensor counts = at::zeros({m}, long_options);
  at::Tensor index, row, dist2;
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "torchvor::radius", [&] {
    RadiusFunctor<scalar_t> functor{grid.view<scalar_t>(),
                                    queries.data_ptr<scalar_t>(),
                                    queries_batch.has_value() ? queries_batch->data_ptr<int64_t>() : nullptr,
                                    order.data_ptr<int32_t>(),
                                    static_cast<scalar_t>(r),
                                    static_cast<scalar_t>(r) * static_cast<scalar_t>(r),
                                    exclude_self,
                                    counts.data_ptr<int64_t>(),
                                    nullptr,
                                    nullptr,
                                    nullptr};
    Exec::for_each(m, functor);
    const at::Tensor ends = at::cumsum(counts, 0);
    const int64_t total = ends[m - 1].item<int64_t>();  // the output's size: the one host read
    const at::Tensor offsets = ends - counts;
    index = at::empty({total}, long_options);
    dist2 = at::empty({total}, queries.options());
    if (total > 0) {
      functor.counts = nullptr;
      functor.offsets = offsets.data_ptr<int64_t>();
      functor.index = index.data_ptr<int64_t>();
      functor.dist2 = dist2.data_ptr<scalar_t>();
      Exec::for_each(m, functor);
    }
    row = at::arange(m, long_options).repeat_interleave(counts, /*dim=*/0, /*output_size=*/total);
  });
  return {index, row, dist2};
}

}  // namespace ops
}  // namespace torchvor
