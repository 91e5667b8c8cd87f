// Builds the uniform grid of paper §2 with ATen tensor ops, so that the same
// code runs on CPU and CUDA tensors. One grid per batch element, all cells in
// one array: the kernels see it through core::GridView.
#pragma once

#include <ATen/ATen.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <functional>
#include <vector>

#include "../core/grid_search.h"

namespace torchvor {
namespace ops {

struct Grid {
  at::Tensor sorted_points;  // (N, 3) points ordered by cell
  at::Tensor sorted_index;   // (N,) int32: original index of each sorted point, or undefined:
                             // the points are numbered in sorted order (the kernels then read no index)
  at::Tensor cell_start;     // (num_cells + 1,) int32
  at::Tensor origin;         // (B, 3) points' dtype
  at::Tensor cell_size;      // (B,) points' dtype
  at::Tensor dims;           // (B, 3) int32
  at::Tensor cell_offset;    // (B,) int32
  at::Tensor cell_bounds;    // (num_cells, 6) points' dtype, or undefined: with_cell_bounds()
  at::Tensor tie_order;      // (N,) int32: the caller's row of each sorted point where the points are
                             // numbered in sorted order, or undefined: the order in which a kNN
                             // writes points at equal distances (else by original index)

  // A copy on the CPU (the double-double pass runs there).
  Grid to_cpu() const {
    const auto cpu = [](const at::Tensor& t) { return t.defined() ? t.to(at::kCPU).contiguous() : t; };
    return {cpu(sorted_points), cpu(sorted_index), cpu(cell_start),  cpu(origin),    cpu(cell_size),
            cpu(dims),          cpu(cell_offset),  cpu(cell_bounds), cpu(tie_order)};
  }

  template <typename T>
  core::GridView<T> view() const {
    return {sorted_points.data_ptr<T>(),
            sorted_index.defined() ? sorted_index.data_ptr<int32_t>() : nullptr,
            cell_start.data_ptr<int32_t>(), origin.data_ptr<T>(),
            cell_size.data_ptr<T>(),        dims.data_ptr<int32_t>(),
            cell_offset.data_ptr<int32_t>(),
            cell_bounds.defined() ? cell_bounds.data_ptr<T>() : nullptr};
  }
};

// The bounds of the points of grid cell c (GridView::cell_bounds).
template <typename T>
struct CellBoundsFunctor {
  const T* sorted_points;     // (N, 3)
  const int32_t* cell_start;  // (num_cells + 1,)
  T* bounds;                  // (num_cells, 6)

  TV_HD void operator()(int64_t c) const {
    const T infinity = T(1) / T(0);
    T low[3] = {infinity, infinity, infinity}, high[3] = {-infinity, -infinity, -infinity};
    for (int32_t s = cell_start[c]; s < cell_start[c + 1]; ++s) {
      for (int a = 0; a < 3; ++a) {
        const T u = sorted_points[3 * s + a];
        low[a] = u < low[a] ? u : low[a];
        high[a] = u > high[a] ? u : high[a];
      }
    }
    for (int a = 0; a < 3; ++a) {
      bounds[6 * c + a] = low[a];
      bounds[6 * c + 3 + a] = high[a];
    }
  }
};

// `grid` with the bounds of each cell's points, which the vertex-ball sweep
// tests against its balls: a dense layer or slab fills a thin part of its
// grid cells, and a ball that meets such a cell can miss all its points.
template <typename Exec>
Grid with_cell_bounds(const Grid& grid) {
  Grid out = grid;
  const int64_t cells = grid.cell_start.size(0) - 1;
  out.cell_bounds = at::empty({cells, 6}, grid.sorted_points.options());
  AT_DISPATCH_FLOATING_TYPES(grid.sorted_points.scalar_type(), "torchvor::cell_bounds", [&] {
    Exec::for_each(cells, CellBoundsFunctor<scalar_t>{grid.sorted_points.data_ptr<scalar_t>(),
                                                      grid.cell_start.data_ptr<int32_t>(),
                                                      out.cell_bounds.data_ptr<scalar_t>()});
  });
  return out;
}

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

// Flat cell id (int32) of every point, computed by core::grid_coordinate:
// the assignment the kNN search assumes, on either backend, in one pass
// (the tensor-op version took a dozen kernel launches on the GPU).
template <typename T>
struct CellIdFunctor {
  const T* points;          // (N, 3)
  const int64_t* batch;     // (N,) or nullptr
  const T* origin;          // (B, 3)
  const T* cell_size;       // (B,)
  const int32_t* dims;      // (B, 3)
  const int32_t* cell_offset;  // (B,)
  int32_t* ids;             // (N,)

  TV_HD void operator()(int64_t i) const {
    const int64_t b = batch ? batch[i] : 0;
    const T h = cell_size[b];
    const int32_t dx = dims[3 * b], dy = dims[3 * b + 1], dz = dims[3 * b + 2];
    const int32_t x = core::grid_coordinate(points[3 * i], origin[3 * b], h, dx);
    const int32_t y = core::grid_coordinate(points[3 * i + 1], origin[3 * b + 1], h, dy);
    const int32_t z = core::grid_coordinate(points[3 * i + 2], origin[3 * b + 2], h, dz);
    ids[i] = cell_offset[b] + (z * dy + y) * dx + x;
  }
};

// The cell id (N,) int32 of every point (CellIdFunctor).
template <typename Exec>
at::Tensor cell_ids(const at::Tensor& points, const c10::optional<at::Tensor>& batch, const Grid& grid) {
  at::Tensor ids = at::empty({points.size(0)}, points.options().dtype(at::kInt));
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "torchvor::cell_ids", [&] {
    const CellIdFunctor<scalar_t> functor{
        points.data_ptr<scalar_t>(), batch.has_value() ? batch->data_ptr<int64_t>() : nullptr,
        grid.origin.data_ptr<scalar_t>(), grid.cell_size.data_ptr<scalar_t>(),
        grid.dims.data_ptr<int32_t>(), grid.cell_offset.data_ptr<int32_t>(), ids.data_ptr<int32_t>()};
    Exec::for_each(points.size(0), functor);
  });
  return ids;
}

// The points in cell order and where each cell's run of them ends, in one
// pass over the sorted order:
// - out[i] = points[index[i]], rows of 3 coordinates (a row a thread, its
//   index loaded once, where index_select loads it for each element);
// - ends[c + 1] = one past the last sorted point of cell c, for every cell
//   that holds points (the others keep their 0), written by the last point
//   of each run of equal ids: one plain store a cell. Their running maximum
//   is the cells' starts, as an empty cell starts where the last cell before
//   it with points ends.
// This replaces counting each cell's points by atomic adds, and a kernel of
// its own for the ends: the gather, bound by its scattered reads of the
// points, absorbs the pass over the sorted ids.
template <typename T>
struct GatherByCellFunctor {
  const T* points;            // (N, 3)
  const int32_t* index;       // (N,) the sort's permutation
  const int32_t* sorted_ids;  // (N,) cell ids in increasing order
  int64_t n;
  T* out;                     // (N, 3)
  int32_t* ends;              // (num_cells + 1,), zeroed

  TV_HD void operator()(int64_t i) const {
    const int64_t from = 3 * int64_t(index[i]);
    out[3 * i] = points[from];
    out[3 * i + 1] = points[from + 1];
    out[3 * i + 2] = points[from + 2];
    const int32_t id = sorted_ids[i];
    if (i + 1 == n || sorted_ids[i + 1] != id) ends[id + 1] = static_cast<int32_t>(i + 1);
  }
};

// The bits a cell id of a grid of `num_cells` cells uses (what a radix sort
// by cell must look at).
inline int cell_id_bits(int64_t num_cells) {
  int bits = 1;
  while ((int64_t(1) << bits) < num_cells) ++bits;
  return bits;
}

// Per batch element, on the host: the points' bounding box and count, rows
// (lo x, y, z, hi x, y, z, count) in double, read in one device-to-host copy
// (each copy waits for the device). The values of `extra` (tensors on the
// points' device: value checks, the box) travel in the same copy, flattened
// in order into `extra_out`; without a batch they travel in the points' dtype,
// so they must be exact in it (conditions, coordinates).
//
// `meanwhile`, where given, is launched after the copy and before the host
// waits for it: device work that needs no bounds (voronoi_forward's positions
// and statuses) then runs while the host takes the values in, instead of
// before the copy, where the host waited for it too.
//
// A NaN coordinate makes its element's bounds NaN (aminmax and scatter_reduce
// propagate it on the CPU; a CUDA scatter_reduce need not: callers with a
// batch check finiteness separately).
template <typename Exec>
at::Tensor point_bounds(const at::Tensor& points, const c10::optional<at::Tensor>& batch, int64_t num_batches,
                        const std::vector<at::Tensor>& extra = {}, std::vector<double>* extra_out = nullptr,
                        const std::function<void()>& meanwhile = {}) {
  const int64_t n = points.size(0);
  const auto options = points.options();
  // The values on the device, in one tensor: with a batch, the rows and the
  // extra values in double; without one, (lo, hi) and the extra values in
  // the points' dtype (no conversion kernels on the hot path of every call
  // and every Lloyd iteration), the count inserted on the host.
  at::Tensor device_values;
  if (batch.has_value()) {
    const auto as_double = [](const at::Tensor& t) { return t.to(at::kDouble).flatten(); };
    at::Tensor index = batch->unsqueeze(1).expand({n, 3});
    at::Tensor lo = at::full({num_batches, 3}, INFINITY, options).scatter_reduce(0, index, points, "amin");
    at::Tensor hi = at::full({num_batches, 3}, -INFINITY, options).scatter_reduce(0, index, points, "amax");
    at::Tensor counts = at::bincount(*batch, {}, num_batches).unsqueeze(1);
    std::vector<at::Tensor> parts = {at::cat({lo.to(at::kDouble), hi.to(at::kDouble), counts.to(at::kDouble)}, 1).flatten()};
    for (const at::Tensor& e : extra) parts.push_back(as_double(e));
    device_values = at::cat(parts);
  } else {
    std::vector<at::Tensor> parts;
    if (n > 0) {
      const auto minmax = at::aminmax(points, 0);
      parts = {std::get<0>(minmax), std::get<1>(minmax)};
    } else {
      parts = {at::zeros({6}, options)};
    }
    for (const at::Tensor& e : extra) parts.push_back(e.flatten());
    device_values = at::cat(parts).to(points.scalar_type());
  }
  const typename Exec::HostRead reading(device_values);
  if (meanwhile) meanwhile();
  const at::Tensor read = reading.wait().contiguous();
  // The rows and then the extra values, in double (a loop on the host, cheaper
  // than tensor ops for a few values).
  const bool count_on_host = !batch.has_value();
  const at::Tensor host = at::empty({read.numel() + (count_on_host ? 1 : 0)}, at::TensorOptions(at::kDouble));
  double* values = host.data_ptr<double>();
  AT_DISPATCH_FLOATING_TYPES(read.scalar_type(), "torchvor::point_bounds", [&] {
    const scalar_t* from = read.data_ptr<scalar_t>();
    for (int64_t i = 0; i < read.numel(); ++i) values[i + (count_on_host && i >= 6 ? 1 : 0)] = double(from[i]);
  });
  if (count_on_host) values[6] = double(n);
  if (extra_out != nullptr) extra_out->assign(values + 7 * num_batches, values + host.numel());
  return host.slice(0, 0, 7 * num_batches).view({num_batches, 7});
}

// Grid over the bounding box of each batch element's points; `bounds` is
// point_bounds() of them (read here when not given). `identity`, where the
// caller has it, is 0, 1, ..., N - 1 as int32 (the sort's indices: one
// kernel less).
template <typename Exec>
Grid build_grid(const at::Tensor& points, const c10::optional<at::Tensor>& batch,
                int64_t num_batches, double points_per_cell, at::Tensor bounds = {},
                const at::Tensor& identity = {}, at::Tensor* sorted_ids_out = nullptr) {
  if (!bounds.defined()) bounds = point_bounds<Exec>(points, batch, num_batches);
  const double* bounds_ptr = bounds.data_ptr<double>();

  // Grid parameters per batch element, built on the host and sent to the
  // device in one copy of one byte buffer, viewed as origin (B, 3) and cell
  // size (B,) in the points' dtype, dims (B, 3) and first cell id (B,) int32.
  const int64_t real_size = points.element_size();
  const auto aligned = [](int64_t bytes) { return (bytes + 7) / 8 * 8; };
  const int64_t origin_at = 0;
  const int64_t size_at = origin_at + aligned(3 * num_batches * real_size);
  const int64_t dims_at = size_at + aligned(num_batches * real_size);
  const int64_t offset_at = dims_at + aligned(3 * num_batches * 4);
  const int64_t total_bytes = offset_at + aligned(num_batches * 4);
  // Pinned when the grid lives on a GPU: the copy below then does not wait
  // for the device (the host allocator keeps the buffer until it is done).
  at::Tensor params_host = at::empty({total_bytes}, at::TensorOptions(at::kByte).pinned_memory(points.is_cuda()));
  unsigned char* params = params_host.data_ptr<unsigned char>();
  int64_t total_cells = 0;
  for (int64_t b = 0; b < num_batches; ++b) {
    const double* row = bounds_ptr + 7 * b;  // lo, hi, count
    double extent[3], origin[3], cell_size;
    int32_t dims[3];
    const int64_t count = static_cast<int64_t>(row[6]);
    for (int a = 0; a < 3; ++a) {
      extent[a] = count == 0 ? 0.0 : row[3 + a] - row[a];
      origin[a] = count == 0 ? 0.0 : row[a];
    }
    grid_shape(extent, count, points_per_cell, cell_size, dims);
    AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "torchvor::build_grid", [&] {
      scalar_t* origin_out = reinterpret_cast<scalar_t*>(params + origin_at) + 3 * b;
      for (int a = 0; a < 3; ++a) origin_out[a] = static_cast<scalar_t>(origin[a]);
      reinterpret_cast<scalar_t*>(params + size_at)[b] = static_cast<scalar_t>(cell_size);
    });
    for (int a = 0; a < 3; ++a) reinterpret_cast<int32_t*>(params + dims_at)[3 * b + a] = dims[a];
    reinterpret_cast<int32_t*>(params + offset_at)[b] = static_cast<int32_t>(total_cells);
    total_cells += int64_t(dims[0]) * dims[1] * dims[2];
    TORCH_CHECK(total_cells < (int64_t(1) << 31), "torchvor: grid too large");
  }

  Grid grid;
  const at::Tensor params_device = params_host.to(points.device(), /*non_blocking=*/true);
  const auto region = [&](int64_t at, int64_t count, at::ScalarType type) {
    return params_device.slice(0, at, at + count * at::elementSize(type)).view(type);
  };
  grid.origin = region(origin_at, 3 * num_batches, points.scalar_type()).view({num_batches, 3});
  grid.cell_size = region(size_at, num_batches, points.scalar_type());
  grid.dims = region(dims_at, 3 * num_batches, at::kInt).view({num_batches, 3});
  grid.cell_offset = region(offset_at, num_batches, at::kInt);
  // A stable sort (exact duplicates keep their order) over only the bits
  // the cell ids use (Exec::stable_order), then the points in that order and
  // the cells' starts from the sorted ids (GatherByCellFunctor).
  const at::Tensor ids = cell_ids<Exec>(points, batch, grid);
  at::Tensor sorted_ids;
  const at::Tensor permutation = Exec::stable_order(ids, cell_id_bits(total_cells), identity, &sorted_ids);
  const int64_t n = points.size(0);
  grid.sorted_points = at::empty({n, 3}, points.options());
  const at::Tensor ends = at::zeros({total_cells + 1}, sorted_ids.options());
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "torchvor::gather_by_cell", [&] {
    Exec::for_each(n, GatherByCellFunctor<scalar_t>{points.data_ptr<scalar_t>(), permutation.data_ptr<int32_t>(),
                                                    sorted_ids.data_ptr<int32_t>(), n,
                                                    grid.sorted_points.data_ptr<scalar_t>(), ends.data_ptr<int32_t>()});
  });
  grid.sorted_index = permutation;
  grid.cell_start = Exec::running_max(ends);  // (num_cells + 1,), N last
  if (sorted_ids_out != nullptr) *sorted_ids_out = sorted_ids;
  return grid;
}

// Whether each sorted point is an exact copy of a point before it in its grid
// cell (a lower row: the sorts are stable), looking back over at most
// kLookBack points of the cell. Once copies are grouped (CopyKeyFunctor),
// each follows another; a copy not found so is found by its cell, at
// distance 0 (DUPLICATE all the same).
template <typename T>
struct CopyFlagFunctor {
  static constexpr int64_t kLookBack = 32;
  const T* sorted_points;     // (N, 3)
  const int32_t* sorted_ids;  // (N,)
  bool* is_copy;              // (N,)

  TV_HD void operator()(int64_t i) const {
    const int32_t id = sorted_ids[i];
    const T x = sorted_points[3 * i], y = sorted_points[3 * i + 1], z = sorted_points[3 * i + 2];
    bool copy = false;
    for (int64_t q = i - 1; q >= 0 && q >= i - kLookBack && sorted_ids[q] == id && !copy; --q) {
      copy = sorted_points[3 * q] == x && sorted_points[3 * q + 1] == y && sorted_points[3 * q + 2] == z;
    }
    is_copy[i] = copy;
  }
};

// A sort key that groups equal points within their grid cell: the cell id
// above a 32-bit hash of the coordinates' bits (-0 counted as +0, which
// compares equal to it).
template <typename T>
struct CopyKeyFunctor {
  const T* sorted_points;     // (N, 3)
  const int32_t* sorted_ids;  // (N,)
  int64_t* keys;              // (N,)

  TV_HD void operator()(int64_t i) const {
    uint64_t hash = 0x9E3779B97F4A7C15ull;
    for (int a = 0; a < 3; ++a) {
      const T value = sorted_points[3 * i + a] + T(0);
      uint64_t bits = 0;
      memcpy(&bits, &value, sizeof(T));
      hash = (hash ^ bits) * 0xFF51AFD7ED558CCDull;
      hash ^= hash >> 29;
    }
    keys[i] = (int64_t(sorted_ids[i]) << 32) | int64_t(hash & 0xFFFFFFFFull);
  }
};

// Sets the exact copies aside: the grid then holds the other points, first
// in its order, and the copies follow them, outside every grid cell, so that
// no neighbour search returns one. A pass over the grid's order looks for
// copies (CopyFlagFunctor); only if it finds one are equal points grouped
// (a stable sort by CopyKeyFunctor's key, which keeps each cell's points
// together) and looked for again. Returns the number of points kept (one
// host read, two more where there are copies); sorted_index follows.
template <typename Exec>
int64_t set_copies_aside(Grid& grid, at::Tensor sorted_ids) {
  const int64_t n = grid.sorted_points.size(0);
  const at::Tensor is_copy = at::empty({n}, sorted_ids.options().dtype(at::kBool));
  const auto flag_copies = [&] {
    AT_DISPATCH_FLOATING_TYPES(grid.sorted_points.scalar_type(), "torchvor::copy_flags", [&] {
      Exec::for_each(n, CopyFlagFunctor<scalar_t>{grid.sorted_points.data_ptr<scalar_t>(),
                                                  sorted_ids.data_ptr<int32_t>(), is_copy.data_ptr<bool>()});
    });
    return is_copy.sum().item<int64_t>();
  };
  if (flag_copies() == 0) return n;
  const at::Tensor keys = at::empty({n}, sorted_ids.options().dtype(at::kLong));
  AT_DISPATCH_FLOATING_TYPES(grid.sorted_points.scalar_type(), "torchvor::copy_keys", [&] {
    Exec::for_each(n, CopyKeyFunctor<scalar_t>{grid.sorted_points.data_ptr<scalar_t>(),
                                               sorted_ids.data_ptr<int32_t>(), keys.data_ptr<int64_t>()});
  });
  const at::Tensor grouped = std::get<1>(at::sort(keys, /*stable=*/true, /*dim=*/0, /*descending=*/false));
  grid.sorted_points = grid.sorted_points.index_select(0, grouped);
  sorted_ids = sorted_ids.index_select(0, grouped);
  const int64_t copies = flag_copies();
  const at::Tensor kept = at::logical_not(is_copy);
  const at::Tensor order = at::cat({kept.nonzero().flatten(), is_copy.nonzero().flatten()});
  grid.sorted_points = grid.sorted_points.index_select(0, order);
  grid.sorted_index = grid.sorted_index.index_select(0, grouped.index_select(0, order));
  // A cell's new start: the points kept before its old start.
  const at::Tensor kept_before = at::cat({at::zeros({1}, kept.options().dtype(at::kInt)),
                                          kept.cumsum(0, at::kInt)});
  grid.cell_start = kept_before.index_select(0, grid.cell_start.to(at::kLong)).contiguous();
  return n - copies;
}

// Grid density for a k-nearest-neighbour query, in points a grid cell, times
// `scale` (Options::points_per_cell_scale). Small cells (about k / 16 points)
// let the distance pruning of the ring search scan little more than the
// k-ball itself; below 1.5 points a cell the clip gives back what the kNN
// gains (docs/design.md).
// The order a neighbour search visits its queries in: grid order, so that
// neighbouring queries read the same cells. When the queries are the grid's
// own points, its sort already holds that order (`queries_are_points`).
template <typename Exec>
at::Tensor query_order(const Grid& grid, const at::Tensor& queries, const c10::optional<at::Tensor>& queries_batch,
                       bool queries_are_points) {
  if (queries_are_points) return grid.sorted_index;
  return Exec::stable_order(cell_ids<Exec>(queries, queries_batch, grid), cell_id_bits(grid.cell_start.size(0) - 1));
}

inline double points_per_cell_for(int64_t k, double scale) {
  return scale * std::min(32.0, std::max(1.5, double(k) / 16.0));
}

}  // namespace ops
}  // namespace torchvor
