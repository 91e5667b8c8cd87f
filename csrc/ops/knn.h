// torchvor::knn, shared by the CPU and CUDA backends. `Exec` runs a functor
// over an index range: cpu/exec.h (at::parallel_for) or cuda/exec.cuh (a
// kernel launch); everything else here is backend-agnostic.
#pragma once

#include <ATen/ATen.h>

#include <tuple>
#include <type_traits>

#include "../core/device_count.h"
#include "../core/grid_search.h"
#include "checks.h"
#include "grid.h"
#include "options.h"

namespace torchvor {
namespace ops {

// Query t of `order` -> its k nearest points, written to row `row(t)` of
// (dist2, index). The heap lives in a k-slot scratch array that the executor
// provides: a contiguous array per CPU thread, shared memory interleaved
// across a block's threads on the GPU (one thread per query), or shared
// memory of the lanes that search one query together.
template <typename T, typename index_t>
struct KnnFunctor {
  core::GridView<T> grid;
  const T* queries;              // (M, 3): query order[t] at row order[t], or at row t if queries_in_order
  const int64_t* query_batch;    // (M,) or nullptr
  const int32_t* order;          // processing order: query id of step t
  T* dist2;                      // (rows, k), or nullptr when only indices are wanted
  index_t* index;                // (rows, k): int64 for the public op, int32 inside Voronoi
  const int32_t* tie_order;      // (N,) by sorted point, or nullptr: Grid::tie_order
  int32_t k;
  bool queries_in_order;         // queries are stored in processing order (sequential reads)
  bool exclude_self;             // queries are the points: skip point q for query q
  bool row_by_query;             // row = query id (else row = t, chunk-local)
  // Element (row, e) at row * k + e (kRows, kStreamedRows: the host writes
  // each row by non-temporal stores, stream_stores.h) or row + e * rows.
  enum class Layout : uint8_t { kRows, kStreamedRows, kColumns } layout;
  int64_t rows;

  static int64_t scratch_bytes(int64_t k) { return core::ScratchArena::bytes<core::HeapKey<T>>(k); }
  // The heap and one offered candidate per lane.
  template <typename Lanes>
  static int64_t cooperative_scratch_bytes(int64_t k) {
    return scratch_bytes(k) + core::ScratchArena::bytes<core::HeapKey<T>>(Lanes::kCount);
  }

  // One thread searches query t.
  TV_HD void operator()(int64_t t, core::ScratchArena scratch) const {
    const int32_t q = order[t];
    const T inf = T(1) / T(0);
    core::NeighborHeap<T> heap{scratch.take<core::HeapKey<T>>(k), k, 0};
    core::knn_search(grid, batch_of(q), query(t, q), exclude_self ? q : -1, heap, inf);
    heap.write_sorted(dist2 ? dist2 + row(t, q) : nullptr, index + row(t, q), column_stride(), inf, tie_order,
                      layout == Layout::kStreamedRows);
  }

  // A group of lanes searches query t together; `scratch` is theirs.
  template <typename Lanes>
  TV_HD void operator()(int64_t t, Lanes lanes, core::ScratchArena scratch) const {
    const int32_t q = order[t];
    const T inf = T(1) / T(0);
    core::NeighborHeap<T> heap{scratch.take<core::HeapKey<T>>(k), k, 0};
    const core::StridedArray<core::HeapKey<T>> offered = scratch.take<core::HeapKey<T>>(Lanes::kCount);
    core::knn_search_cooperative(grid, batch_of(q), query(t, q), exclude_self ? q : -1, heap, offered, inf,
                                 lanes);
    heap.write_ranked(dist2 ? dist2 + row(t, q) : nullptr, index + row(t, q), column_stride(), inf, lanes,
                      tie_order);
  }

  TV_HD int64_t batch_of(int32_t q) const { return query_batch ? query_batch[q] : 0; }
  TV_HD core::Vec3<T> query(int64_t t, int32_t q) const {
    return core::load_vec3(queries + 3 * (queries_in_order ? t : int64_t(q)));
  }
  TV_HD int64_t row(int64_t t, int32_t q) const {
    return (row_by_query ? q : t) * (layout == Layout::kColumns ? 1 : k);
  }
  TV_HD int64_t column_stride() const { return layout == Layout::kColumns ? rows : 1; }
};
// Past 128 bytes of kernel parameter nvcc reads a functor's fields at each
// use instead of once at the kernel's entry (clip_pass.h's
// VertexBallsGridMember).
static_assert(sizeof(KnnFunctor<double, int64_t>) <= 128, "the kNN functor must stay within 128 bytes");

// Launches `launched` (a KnnFunctor, or one wrapped in UpToDeviceCount)
// over `count` queries: a group of lanes per query or a thread per query
// (Exec's choice by the count, unless `forced`).
template <typename Exec, typename Functor, typename Launched>
void launch_knn(int64_t count, int64_t k, Implementation forced, const Launched& launched) {
  const int64_t cooperative_bytes = Functor::template cooperative_scratch_bytes<typename Exec::Lanes>(k);
  if (Exec::fits_cooperative_scratch(cooperative_bytes) &&
      use_cooperative(forced, Exec::cooperative_queries(count))) {
    Exec::for_each_cooperative_with_scratch(count, cooperative_bytes, launched);
  } else {
    Exec::for_each_with_scratch(count, Functor::scratch_bytes(k), launched);
  }
}

// Runs the search for `count` queries. `dist2` may be undefined when only
// indices are wanted. Results are (rows, k) row-major, or (k, rows)
// column-major when `column_major` (coalesced on GPUs). `forced` overrides
// the backend's choice of implementation. With kUpToDeviceCount, only the
// queries that `live` says are valid run (the speculative retry pass of
// recovery.h; its own kernels).
template <typename Exec, typename T, typename index_t, bool kUpToDeviceCount = false>
void run_knn(const Grid& grid, const T* queries, bool queries_in_order,
             const int64_t* query_batch, const int32_t* order, int64_t count, int64_t k,
             bool exclude_self, bool row_by_query, bool column_major, bool stream_rows, Implementation forced,
             at::Tensor& dist2, at::Tensor& index, const core::DeviceCount& live = {}) {
  using Functor = KnnFunctor<T, index_t>;
  const Functor functor{grid.view<T>(), queries, query_batch, order,
                        dist2.defined() ? dist2.data_ptr<T>() : nullptr,
                        index.data_ptr<index_t>(),
                        grid.tie_order.defined() ? grid.tie_order.data_ptr<int32_t>() : nullptr,
                        static_cast<int32_t>(k), queries_in_order, exclude_self, row_by_query,
                        column_major  ? Functor::Layout::kColumns
                        : stream_rows ? Functor::Layout::kStreamedRows
                                      : Functor::Layout::kRows,
                        index.numel() / k};
  if constexpr (kUpToDeviceCount) {
    launch_knn<Exec, Functor>(count, k, forced, core::up_to_device_count(functor, live));
  } else {
    launch_knn<Exec, Functor>(count, k, forced, functor);
  }
}

template <typename Exec>
std::tuple<at::Tensor, at::Tensor> knn_forward(const at::Tensor& points_in,
                                               const at::Tensor& queries_in, int64_t k,
                                               const c10::optional<at::Tensor>& points_batch_in,
                                               const c10::optional<at::Tensor>& queries_batch_in,
                                               bool exclude_self) {
  const Options options = Options::from_environment();
  const auto contiguous = [](const c10::optional<at::Tensor>& t) {
    return t.has_value() ? c10::optional<at::Tensor>(t->contiguous()) : c10::nullopt;
  };
  const c10::optional<at::Tensor> points_batch = contiguous(points_batch_in);
  const c10::optional<at::Tensor> queries_batch = contiguous(queries_batch_in);
  const int64_t num_batches =
      check_knn_inputs(points_in, queries_in, k, points_batch, queries_batch, exclude_self);
  const int64_t m = queries_in.size(0);
  at::Tensor dist2 = Exec::empty({m, k}, queries_in.options());
  at::Tensor index = Exec::empty({m, k}, queries_in.options().dtype(at::kLong));
  const at::Tensor points = points_in.contiguous();
  const at::Tensor queries = queries_in.contiguous();
  const ValueChecks values = knn_value_checks(points, queries);
  if (m == 0) {
    values.run();
    return {dist2, index};
  }
  // The value checks travel with the grid's bounds: one device sync.
  std::vector<double> holds;
  const at::Tensor bounds = point_bounds<Exec>(points, points_batch, num_batches, values.conditions(), &holds);
  values.verify(holds.data());
  const Grid grid = build_grid<Exec>(points, points_batch, num_batches,
                                     points_per_cell_for(k, options.points_per_cell_scale), bounds);
  // Visit queries in grid order: neighbouring queries read the same cells.
  // When the queries are the points, the grid's sorted copy holds them in
  // that order already (sequential reads).
  const bool queries_are_points = exclude_self && !points_batch.has_value();
  const at::Tensor order = query_order<Exec>(grid, queries, queries_batch, queries_are_points);
  const at::Tensor ordered_queries = queries_are_points ? grid.sorted_points : queries;
  // Rows land in caller order, scattered over the result: past the caches'
  // size, non-temporal stores skip reading in each line they fill.
  const bool stream_rows = (dist2.nbytes() + index.nbytes()) >= size_t(options.stream_rows_bytes);
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "torchvor::knn", [&] {
    run_knn<Exec, scalar_t, int64_t>(grid, ordered_queries.data_ptr<scalar_t>(),
                            queries_are_points,
                            queries_batch.has_value() ? queries_batch->data_ptr<int64_t>() : nullptr,
                            order.data_ptr<int32_t>(), m, k, exclude_self, /*row_by_query=*/true,
                            /*column_major=*/false, stream_rows, options.knn, dist2, index);
  });
  return {dist2, index};
}

}  // namespace ops
}  // namespace torchvor
