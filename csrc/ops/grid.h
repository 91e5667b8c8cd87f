// Builds the uniform grid of paper §2 with ATen tensor ops, so that the same
// code runs on CPU and CUDA tensors. One grid per batch element, all cells in
// one array: the kernels see it through core::GridView.
#pragma once

#include <ATen/ATen.h>

#include <algorithm>
#include <cmath>
#include <vector>

#include "../core/grid_search.h"

namespace torchvor {
namespace ops {

struct Grid {
  at::Tensor sorted_points;  // (N, 3) points ordered by cell
  at::Tensor sorted_index;   // (N,) int32: original index of each sorted point
  at::Tensor cell_start;     // (num_cells + 1,) int32
  at::Tensor origin;         // (B, 3) points' dtype
  at::Tensor cell_size;      // (B,) points' dtype
  at::Tensor dims;           // (B, 3) int32
  at::Tensor cell_offset;    // (B,) int32

  template <typename T>
  core::GridView<T> view() const {
    return {sorted_points.data_ptr<T>(),   sorted_index.data_ptr<int32_t>(),
            cell_start.data_ptr<int32_t>(), origin.data_ptr<T>(),
            cell_size.data_ptr<T>(),        dims.data_ptr<int32_t>(),
            cell_offset.data_ptr<int32_t>()};
  }
};

// Cubic cell size and cell counts for a box of the given extent holding
// `count` points at about `points_per_cell` points per cell. Flat or
// one-dimensional point sets get a single cell along their thin axes.
inline void grid_shape(const double extent[3], int64_t count, double points_per_cell,
                       double& cell_size, int32_t dims[3]) {
  const double target_cells = std::max(1.0, double(count) / points_per_cell);
  bool active[3];
  double largest = 0.0;
  for (int a = 0; a < 3; ++a) largest = std::max(largest, extent[a]);
  for (int a = 0; a < 3; ++a) active[a] = extent[a] > 0.0;
  cell_size = largest > 0.0 ? largest : 1.0;
  for (int pass = 0; pass < 3 && largest > 0.0; ++pass) {
    double volume = 1.0;
    int num_active = 0;
    for (int a = 0; a < 3; ++a) {
      if (!active[a]) continue;
      volume *= extent[a];
      ++num_active;
    }
    if (num_active == 0) break;
    cell_size = std::pow(volume / target_cells, 1.0 / num_active);
    bool changed = false;
    for (int a = 0; a < 3; ++a) {
      if (active[a] && extent[a] < cell_size) {
        active[a] = false;
        changed = true;
      }
    }
    if (!changed) break;
  }
  if (!(cell_size > 0.0) || !std::isfinite(cell_size)) cell_size = largest > 0.0 ? largest : 1.0;
  for (int a = 0; a < 3; ++a) {
    const double cells = std::ceil(extent[a] / cell_size);
    dims[a] = static_cast<int32_t>(std::min(std::max(cells, 1.0), 1048576.0));
  }
}

// Flat cell id of every point (same rounding as core::grid_coordinate).
inline at::Tensor cell_ids(const at::Tensor& points, const c10::optional<at::Tensor>& batch,
                           const Grid& grid) {
  at::Tensor origin = grid.origin, cell_size = grid.cell_size, dims = grid.dims.to(at::kLong),
             offset = grid.cell_offset.to(at::kLong);
  if (batch.has_value()) {
    origin = origin.index_select(0, *batch);
    cell_size = cell_size.index_select(0, *batch);
    dims = dims.index_select(0, *batch);
    offset = offset.index_select(0, *batch);
  }
  at::Tensor coord = ((points - origin) / cell_size.unsqueeze(-1)).floor().clamp_min(0);
  // clamp before the cast: coordinates far outside the grid must not overflow
  coord = at::minimum(coord, (dims - 1).to(coord.scalar_type())).to(at::kLong);
  at::Tensor x = coord.select(-1, 0), y = coord.select(-1, 1), z = coord.select(-1, 2);
  at::Tensor dx = dims.select(-1, 0), dy = dims.select(-1, 1);
  return offset + (z * dy + y) * dx + x;
}

// Grid over the bounding box of each batch element's points.
inline Grid build_grid(const at::Tensor& points, const c10::optional<at::Tensor>& batch,
                       int64_t num_batches, double points_per_cell) {
  const int64_t n = points.size(0);
  const auto options = points.options();
  // Per-batch bounding boxes and counts, on the points' device, then to the
  // host in one copy (every device-to-host copy waits for the device).
  // Rows of `summary`: lo (3), hi (3), count (1), in double (exact for
  // counts below 2^53).
  at::Tensor summary;
  const auto as_double = [](const at::Tensor& t) { return t.to(at::kDouble); };
  if (batch.has_value()) {
    at::Tensor index = batch->unsqueeze(1).expand({n, 3});
    at::Tensor lo = at::full({num_batches, 3}, INFINITY, options)
                        .scatter_reduce(0, index, points, "amin");
    at::Tensor hi = at::full({num_batches, 3}, -INFINITY, options)
                        .scatter_reduce(0, index, points, "amax");
    at::Tensor counts = at::bincount(*batch, {}, num_batches).unsqueeze(1);
    summary = at::cat({as_double(lo), as_double(hi), as_double(counts)}, 1).to(at::kCPU);
  } else if (n > 0) {
    at::Tensor lo = std::get<0>(points.min(0));
    at::Tensor hi = std::get<0>(points.max(0));
    const at::Tensor count = at::full({1}, double(n), lo.options().dtype(at::kDouble));
    summary = at::cat({as_double(at::stack({lo, hi})).flatten(), count}).unsqueeze(0).to(at::kCPU);
  } else {
    summary = at::zeros({1, 7}, at::kDouble);
  }
  summary = summary.contiguous();
  const double* summary_ptr = summary.data_ptr<double>();

  // Grid parameters per batch element, built on the host and copied to the
  // device in one go: origin (3), cell size (1), dims (3), first cell (1),
  // all exact in double.
  at::Tensor params_host = at::empty({num_batches, 8}, at::kDouble);
  double* params = params_host.data_ptr<double>();
  int64_t total_cells = 0;
  for (int64_t b = 0; b < num_batches; ++b) {
    const double* row = summary_ptr + 7 * b;  // lo, hi, count
    double* out = params + 8 * b;
    double extent[3], cell_size;
    int32_t dims[3];
    const int64_t count = static_cast<int64_t>(row[6]);
    for (int a = 0; a < 3; ++a) {
      extent[a] = count == 0 ? 0.0 : row[3 + a] - row[a];
      out[a] = count == 0 ? 0.0 : row[a];
    }
    grid_shape(extent, count, points_per_cell, cell_size, dims);
    out[3] = cell_size;
    for (int a = 0; a < 3; ++a) out[4 + a] = dims[a];
    out[7] = static_cast<double>(total_cells);
    total_cells += int64_t(dims[0]) * dims[1] * dims[2];
    TORCH_CHECK(total_cells < (int64_t(1) << 31), "torchvor: grid too large");
  }

  Grid grid;
  const at::Tensor params_device = params_host.to(points.device());
  grid.origin = params_device.slice(1, 0, 3).to(points.scalar_type()).contiguous();
  grid.cell_size = params_device.select(1, 3).to(points.scalar_type()).contiguous();
  grid.dims = params_device.slice(1, 4, 7).to(at::kInt).contiguous();
  grid.cell_offset = params_device.select(1, 7).to(at::kInt).contiguous();
  at::Tensor ids = cell_ids(points, batch, grid);
  auto sorted = at::sort(ids, /*stable=*/true, /*dim=*/0, /*descending=*/false);
  at::Tensor sorted_ids = std::get<0>(sorted);
  at::Tensor permutation = std::get<1>(sorted);
  grid.sorted_points = points.index_select(0, permutation).contiguous();
  grid.sorted_index = permutation.to(at::kInt);
  grid.cell_start =
      at::searchsorted(sorted_ids, at::arange(total_cells + 1, sorted_ids.options())).to(at::kInt);
  return grid;
}

// Grid density for a k-nearest-neighbour query. Small cells (about k / 16
// points) let the distance pruning of the ring search scan little more than
// the k-ball itself. Measured (benchmarks/NOTES.md): CPU 3.45 us/query at k=35
// against 5.0 with k / 4; H200 1M k=35 5.3 ms against 7.8 with k / 4.
inline double points_per_cell_for(int64_t k) {
  return std::min(32.0, std::max(2.0, double(k) / 16.0));
}

}  // namespace ops
}  // namespace torchvor
