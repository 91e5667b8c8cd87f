// torchvor::knn, shared by the CPU and CUDA backends. `Exec` runs a functor
// over an index range: cpu/exec.h (at::parallel_for) or cuda/exec.cuh (a
// kernel launch); everything else here is backend-agnostic.
#pragma once

#include <ATen/ATen.h>

#include <tuple>

#include "../core/grid_search.h"
#include "checks.h"
#include "grid.h"

namespace torchvor {
namespace ops {

// Query t of `order` -> its k nearest points, written to heap row `row(t)`.
template <typename T>
struct KnnFunctor {
  core::GridView<T> grid;
  const T* queries;              // (M, 3)
  const int64_t* query_batch;    // (M,) or nullptr
  const int32_t* order;          // processing order: query id of step t
  T* dist2;                      // heap storage, (rows, k)
  int32_t* index;                // heap storage, (rows, k)
  int32_t k;
  bool exclude_self;             // queries are the points: skip point q for query q
  bool row_by_query;             // row = query id (else row = t, chunk-local)

  TV_HD void operator()(int64_t t) const {
    const int32_t q = order[t];
    const int64_t row = row_by_query ? q : t;
    core::NeighborHeap<T> heap{dist2 + row * k, index + row * k, 1, k, 0};
    const int64_t b = query_batch ? query_batch[q] : 0;
    const T inf = T(1) / T(0);
    core::knn_search(grid, b, core::load_vec3(queries + 3 * int64_t(q)), exclude_self ? q : -1,
                     heap, inf);
  }
};

template <typename Exec>
std::tuple<at::Tensor, at::Tensor> knn_forward(const at::Tensor& points_in,
                                               const at::Tensor& queries_in, int64_t k,
                                               const c10::optional<at::Tensor>& points_batch,
                                               const c10::optional<at::Tensor>& queries_batch,
                                               bool exclude_self) {
  check_points(points_in, "points");
  check_points(queries_in, "queries");
  check_same_device(points_in, "points", queries_in, "queries");
  TORCH_CHECK_TYPE(points_in.scalar_type() == queries_in.scalar_type(),
                   "torchvor: queries must have the dtype of points (", points_in.scalar_type(),
                   "), got ", queries_in.scalar_type());
  TORCH_CHECK_VALUE(k >= 1, "torchvor: k must be at least 1, got ", k);
  TORCH_CHECK_VALUE(k < (int64_t(1) << 31), "torchvor: k is too large: ", k);
  TORCH_CHECK_VALUE(points_batch.has_value() == queries_batch.has_value(),
                    "torchvor: give both batch and query_batch, or neither");
  const int64_t n = points_in.size(0), m = queries_in.size(0);
  if (exclude_self) {
    TORCH_CHECK_VALUE(n == m, "torchvor: exclude_self needs queries to be the points");
  }
  const int64_t points_batches = check_batch(points_batch, n, points_in, "batch");
  const int64_t query_batches = check_batch(queries_batch, m, points_in, "query_batch");
  check_finite(points_in, "points");
  check_finite(queries_in, "queries");

  at::Tensor dist2 = at::empty({m, k}, queries_in.options());
  at::Tensor index32 = at::empty({m, k}, queries_in.options().dtype(at::kInt));
  if (m == 0) return {dist2, index32.to(at::kLong)};
  const at::Tensor points = points_in.contiguous();
  const at::Tensor queries = queries_in.contiguous();
  const int64_t num_batches = std::max(points_batches, query_batches);
  const Grid grid = build_grid(points, points_batch, num_batches, points_per_cell_for(k));
  // Visit queries in grid order: neighbouring queries read the same cells.
  const at::Tensor order = exclude_self && !points_batch.has_value()
                               ? grid.sorted_index
                               : cell_ids(queries, queries_batch, grid).argsort().to(at::kInt);
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "torchvor::knn", [&] {
    KnnFunctor<scalar_t> functor{grid.view<scalar_t>(),
                                 queries.data_ptr<scalar_t>(),
                                 queries_batch.has_value() ? queries_batch->data_ptr<int64_t>() : nullptr,
                                 order.data_ptr<int32_t>(),
                                 dist2.data_ptr<scalar_t>(),
                                 index32.data_ptr<int32_t>(),
                                 static_cast<int32_t>(k),
                                 exclude_self,
                                 /*row_by_query=*/true};
    Exec::for_each(m, functor);
  });
  return {dist2, index32.to(at::kLong)};
}

}  // namespace ops
}  // namespace torchvor
