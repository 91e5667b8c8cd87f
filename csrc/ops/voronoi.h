// torchvor::voronoi_cells, shared by the CPU and CUDA backends.
//
// Cells are computed chunk by chunk (kNN into a bounded buffer, then clipping),
// so no N x k neighbour array ever exists. Failed cells are retried with what
// their status asks for: more neighbours, larger arrays, or more precision
// (float64, then double-double on the CPU, where an inconsistent clip may also
// widen its predicate band; ill-conditioned integrals ask for precision too).
// A cell that fails every pass keeps its status and NaN outputs.
#pragma once

#include <ATen/ATen.h>

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdlib>
#include <cstring>
#include <functional>
#include <limits>
#include <tuple>
#include <type_traits>
#include <vector>

#include "../core/voronoi_cell.h"
#include "../cpu/exec.h"
#include "checks.h"
#include "grid.h"
#include "knn.h"

namespace torchvor {
namespace ops {

// One cell's outputs, by grid position, as one record: the gather to the
// caller's rows at the end (ToRowsFunctor) then reads one or two 32-byte
// sectors a cell (a record is 32 bytes in float32, 48 in float64), where
// five arrays cost five or six. At 10M points the outputs outgrow the L2
// cache and that gather was 1.8 ms of a 51 ms call (H100, benchmarks/NOTES.md).
template <typename io_t>
struct alignas(16) CellRecord {
  io_t volume;
  io_t centroid[3];
  io_t second_moment;
  int32_t num_neighbors;
  int8_t status;
};

// The outputs by grid position (the numbering the passes work in): one
// CellRecord<io_t> a position, in a byte tensor, and the caller's row of
// each position. The statuses are also kept apart, a byte a cell: the scan
// after a pass reads them there (a record is a 32-byte sector; the scan of
// the records took 169 us of a 10M call on an H100). The records keep theirs
// too: the gather to the caller's rows (ToRowsFunctor) then reads one sector
// a cell, where a status from the byte array would cost a second scattered
// one.
struct PositionOutputs {
  at::Tensor records;          // (N, sizeof(CellRecord<io_t>)) uint8
  at::Tensor status;           // (N,) int8, the records' statuses again
  at::Tensor row_of_position;  // (N,) int32
  at::Tensor position_of_row;  // (N,) int32, its inverse: the first pass's status read computes it

  template <typename io_t>
  CellRecord<io_t>* data() const {
    return reinterpret_cast<CellRecord<io_t>*>(records.data_ptr<uint8_t>());
  }
  // (N,) int32 view of the records' neighbour counts.
  template <typename io_t>
  at::Tensor num_neighbors() const {
    return records.view(at::kInt).select(1, offsetof(CellRecord<io_t>, num_neighbors) / sizeof(int32_t));
  }
};

template <typename io_t>
at::Tensor empty_records(int64_t n, const at::TensorOptions& options) {
  return at::empty({n, int64_t(sizeof(CellRecord<io_t>))}, options.dtype(at::kByte));
}

// The grid that the vertex-ball passes sweep, held only by their functors
// (an empty base of the others). As a member of every clip functor it made
// the kernel parameter 136 bytes instead of 80. Past 128 bytes nvcc reads a
// functor's fields at each use instead of once at the kernel's entry (the
// neighbour stride was recomputed at every read), and the 1M blue-noise
// clip kernel took 1.6% longer (H100, benchmarks/NOTES.md). The static_assert
// below the functor keeps the hot ones within 128 bytes.
template <typename io_t, bool kVertexBalls>
struct VertexBallsGridMember {
  core::GridView<io_t> grid;  // the points by position
};
template <typename io_t>
struct VertexBallsGridMember<io_t, false> {};

// The planes a cell of a vertex-ball pass may hold: those passes run at the
// largest tier only, whatever the cells asked for before. Their cells are
// few (5282 of 1M points in a box 3x wide, the most measured), and a
// kernel per tier and precision would be three times as many vertex-ball
// kernels to compile.
constexpr int kVertexBallPlanes = 160;

// Clip cell `cells[t]` by its neighbours (row t of `neighbors`); with
// kVertexBalls, a cell whose neighbours run out before the radius of
// security is finished on the grid (core::finish_by_vertex_balls). With
// kCompactTriangles, a thread cell keeps its triangles in 12 bytes
// (core::CompactTriangles: float32, at most 32 planes).
template <typename io_t, typename T, int MAX_PLANES, bool kVertexBalls = false, bool kCompactTriangles = false>
struct ClipFunctor : VertexBallsGridMember<io_t, kVertexBalls> {
  static constexpr int kMaxTriangles = 2 * MAX_PLANES;
  using Arrays = core::CooperativeCellArrays<T, MAX_PLANES, kMaxTriangles>;

  const io_t* points;          // (N, 3)
  const io_t* box;             // (B, 2, 3)
  const int64_t* batch;        // (N,) or nullptr
  const int32_t* cells;        // (chunk,) cell (= point) ids
  const int32_t* neighbors;    // (chunk, k) row-major, or (k, chunk) if neighbors_column_major
  int32_t k;
  bool neighbors_column_major;
  int32_t chunk;               // cells in this chunk (the column stride)
  T tolerance;
  int band_widenings;          // > 0 only in the last-resort pass
  bool tetrahedron_start;      // core::compute_cell: from a tetrahedron where one fits (false: the box)
  bool rows_by_step;           // write record t (chunk-local outputs) instead of record cells[t]
  CellRecord<io_t>* records;   // (N,) by position
  int8_t* status;              // (N,) by position: the records' statuses again

  // One thread computes cell t.
  TV_HD void operator()(int64_t t) const {
    core::ConvexCell<T, MAX_PLANES, kMaxTriangles, kCompactTriangles> cell;
    write(t, compute(cell, t));
  }

  // A group of lanes computes cell t together, its arrays in `arrays`.
  template <typename Lanes>
  TV_HD void operator()(int64_t t, Lanes lanes, Arrays& arrays) const {
    core::CooperativeCell<T, MAX_PLANES, kMaxTriangles, Lanes> cell(arrays, lanes);
    const core::CellIntegrals<T> out = compute(cell, t);
    if (lanes.index() == 0) write(t, out);
  }

  template <typename Cell>
  TV_HD core::CellIntegrals<T> compute(Cell& cell, int64_t t) const {
    const int32_t cell_id = cells[t];
    const int64_t b = batch ? batch[cell_id] : 0;
    const int32_t* row = neighbors + (neighbors_column_major ? t : t * int64_t(k));
    const int64_t stride = neighbors_column_major ? int64_t(chunk) : int64_t(1);
    if constexpr (kVertexBalls) {
      const core::VertexBallGrid<io_t> vertex_balls{this->grid, b};
      return core::compute_cell(cell, points, cell_id, row, stride, k, box + 6 * b, tolerance,
                                band_widenings, tetrahedron_start, &vertex_balls);
    } else {
      return core::compute_cell(cell, points, cell_id, row, stride, k, box + 6 * b, tolerance,
                                band_widenings, tetrahedron_start);
    }
  }

  TV_HD void write(int64_t t, const core::CellIntegrals<T>& out) const {
    const int64_t i = rows_by_step ? t : cells[t];
    records[i] = {static_cast<io_t>(out.volume),
                  {static_cast<io_t>(out.centroid.x), static_cast<io_t>(out.centroid.y),
                   static_cast<io_t>(out.centroid.z)},
                  static_cast<io_t>(out.second_moment), out.neighbors, out.status};
    status[i] = out.status;
  }
};
static_assert(sizeof(ClipFunctor<float, float, 32>) <= 128 && sizeof(ClipFunctor<double, double, 32>) <= 128,
              "clip functors beyond 128 bytes get slower kernels (VertexBallsGridMember)");

// After a pass, in one kernel: which status codes its cells got (bit
// code - kNotComputed of words[0]) and the list of the cells that failed
// (words[1] of them); the host reads the two words in one copy.
// Each thread scans kItems cells, `stride` apart (a warp's reads stay
// coalesced), and ORs what it saw into words[0] once: with a thread per
// cell, the read of that one word by every warp (set_bits) queued at one
// L2 slice, and the scan of 10M cells took 115 us (H100) for 50 MB of reads;
// 26 us now (the first pass's scan reads no cell list: every position).
// With `live_count`, the pass's list is the speculative retry's (its valid
// entries counted on the device, core::DeviceCount; num_cells is its
// capacity).
struct StatusScanFunctor {
  static constexpr int64_t kItems = 16;
  const int8_t* status;   // (N,) by position
  const int32_t* cells;   // the pass's positions, or nullptr: positions 0, 1, ..., num_cells - 1
  int64_t num_cells;
  int64_t stride;         // the threads of the scan: threads(num_cells)
  int32_t* failed_cells;  // (num_cells,) the failed ones (not SUCCESS or DUPLICATE), in no set order
  int32_t* words;         // two words, zeroed
  const int32_t* live_count = nullptr;

  static int64_t threads(int64_t num_cells) { return (num_cells + kItems - 1) / kItems; }

  TV_HD void operator()(int64_t t) const {
    int32_t seen = 0;
    const int64_t scanned = live_count ? core::DeviceCount{live_count, num_cells}.live() : num_cells;
    for (int64_t i = t; i < scanned; i += stride) {
      const int32_t cell = cells ? cells[i] : static_cast<int32_t>(i);
      const int8_t code = status[cell];
      seen |= int32_t(1) << (code - core::kNotComputed);
      core::append_if(code != core::kSuccess && code != core::kDuplicate, cell, failed_cells, words + 1);
    }
    core::set_bits(words, seen);
  }
};

// How hard a pass tries: neighbours per cell, array tier, precision.
enum class Precision { kInput, kFloat64, kDoubleDouble };

struct PassSettings {
  int64_t k;
  int tier;            // 0, 1, 2: at most 32, 64, 160 planes
  Precision precision;
  bool vertex_balls = false;  // cells whose k neighbours run out are finished on the grid

  bool operator==(const PassSettings& o) const {
    return k == o.k && tier == o.tier && precision == o.precision && vertex_balls == o.vertex_balls;
  }
};

// The record of a cell that no pass wrote: "not computed" (NaN, status -1,
// 0 neighbours). Only the status bytes start so (poisoned_outputs); a pass
// writes the record of each of its cells, and after the passes the records
// of the cells still not computed are set to this (PoisonUnwrittenFunctor).
// Poisoning every record up front was a 198 us kernel: 10M blue noise took
// 38.73 ms with it, 38.41 without (H100, benchmarks/NOTES.md).
template <typename io_t>
TV_HD CellRecord<io_t> not_computed_record() {
  const io_t zero = io_t(0);
  const io_t nan = zero / zero;
  return {nan, {nan, nan, nan}, nan, 0, core::kNotComputed};
}

// The cells of `cells` whose status is still "not computed" get the record
// that says so.
template <typename io_t>
struct PoisonUnwrittenFunctor {
  const int32_t* cells;
  const int8_t* status;        // (N,) by position
  CellRecord<io_t>* records;   // (N,) by position

  TV_HD void operator()(int64_t i) const {
    const int32_t position = cells[i];
    if (status[position] == core::kNotComputed) records[position] = not_computed_record<io_t>();
  }
};

// position_of_row[row_of_position[p]] = p for the rows in [first_row,
// end_row): the inverse of the grid order, over every position once per
// range of rows. The writes scatter, and a range that the GPU's L2 cache
// holds (Exec::cached_scatter_bytes) lets each sector fill there before it
// goes to memory: in one range at 10M points (40 MB, about the H100's L2),
// the kernel took 291 us for 40 MB of reads and 40 MB of writes; in two of
// 25 MB, 152 + 87 us (10M blue noise, H100: 35.37 -> 35.32 ms a call).
struct InvertOrderFunctor {
  const int32_t* row_of_position;
  int32_t* position_of_row;
  int32_t first_row;
  int32_t end_row;

  TV_HD void operator()(int64_t p) const {
    const int32_t row = row_of_position[p];
    if (row >= first_row && row < end_row) position_of_row[row] = static_cast<int32_t>(p);
  }
};

// The inverse of the grid order (N,) int32 from `row_of_position`, in
// ranges of rows that fit the cache (InvertOrderFunctor). Only the GPU
// splits 10M points or more; TORCHVOR_TEST_SCATTER_BYTES (tests only) sets
// the bytes a range writes, so that small inputs take several ranges too.
template <typename Exec>
at::Tensor invert_order(const at::Tensor& row_of_position) {
  const int64_t n = row_of_position.size(0);
  const at::Tensor position_of_row = Exec::empty({n}, row_of_position.options());
  const char* test_bytes = std::getenv("TORCHVOR_TEST_SCATTER_BYTES");
  const int64_t test_range = test_bytes != nullptr ? std::atoll(test_bytes) : 0;
  const int64_t range_bytes = test_range > 0 ? test_range : Exec::cached_scatter_bytes();
  const int64_t rows_per_range = std::max<int64_t>(1, range_bytes / int64_t(sizeof(int32_t)));
  for (int64_t first = 0; first < n; first += rows_per_range) {
    Exec::for_each(n, InvertOrderFunctor{row_of_position.data_ptr<int32_t>(), position_of_row.data_ptr<int32_t>(),
                                         static_cast<int32_t>(first),
                                         static_cast<int32_t>(std::min(n, first + rows_per_range))});
  }
  return position_of_row;
}

// The caller's row `row` of the five outputs from the record at its grid
// position, in one kernel. It gathers (scattered reads, rows written in
// order) rather than scatters, whose partial-sector writes were slow once
// the outputs outgrew the L2 cache: kernel time at 10M blue noise, H100,
// 4.26-4.36 ms scattering five arrays against 1.79-1.84 gathering them, plus
// 0.29 for InvertOrderFunctor, which scatters a single int32 array
// (ab_compare.sh). Writing the caller's rows from the clip kernel itself
// slowed it (scattered stores: clip kernel 7.81 -> 8.45 ms at 1M blue, H100).
// Without `position_of_row`, row p is position p (outputs in grid order).
template <typename io_t>
struct ToRowsFunctor {
  const int32_t* position_of_row;  // (N,), or nullptr: the identity
  const CellRecord<io_t>* records;
  io_t* volume;         // (N,)
  io_t* centroid;       // (N, 3)
  io_t* second_moment;  // (N,)
  int8_t* status;       // (N,)
  int32_t* num_neighbors;  // (N,)

  TV_HD void operator()(int64_t row) const {
    const CellRecord<io_t> record = records[position_of_row ? position_of_row[row] : row];
    volume[row] = record.volume;
    centroid[3 * row] = record.centroid[0];
    centroid[3 * row + 1] = record.centroid[1];
    centroid[3 * row + 2] = record.centroid[2];
    second_moment[row] = record.second_moment;
    status[row] = record.status;
    num_neighbors[row] = record.num_neighbors;
  }
};

using CallerOutputs = std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor>;

// What the ops return: the five outputs (volume, centroid, second_moment,
// status, num_neighbors), in the caller's rows, or (grid_order) by grid
// position with `order`, (N,) int64, the caller's row of each position.
struct VoronoiOutputs {
  CallerOutputs cells;
  at::Tensor order;          // undefined unless grid_order
  int64_t first_pass_k = 0;  // the caller's k or the pilot's, capped by the largest cloud; 0: no pass ran
};

// Work that a call launches on its outputs before the op returns
// (torchvor::lloyd_step's move and sums, which the host then reads).
// voronoi_passes launches it before the first status read, the last one of
// most calls, so that the device runs it while the host waits for that read;
// and once more after the passes if a later pass or the poison of unwritten
// cells changed the outputs since (that launch's results replace the
// first's). Launched after the read, from Python, that work cost a Lloyd
// step 0.2-0.4 ms of idle device (the launches and a second read): one step
// at 1M blue noise took 4.56-4.58 ms that way, 4.14-4.17 this way (H100,
// benchmarks/NOTES.md).
using LaunchOnOutputs = std::function<void(const VoronoiOutputs&)>;

// The five outputs from the records by position: in the caller's rows, or
// in grid order with the order (torchvor::voronoi_cells_grid_order, which
// saves the inverse order and the scattered gather: Lloyd keeps its points
// in grid order, and then the next call's grid order is nearly the identity).
template <typename Exec, typename io_t>
VoronoiOutputs finish_outputs(const PositionOutputs& in, const at::TensorOptions& options, bool grid_order) {
  const int64_t n = in.records.size(0);
  const at::Tensor volume = Exec::empty({n}, options);
  const at::Tensor centroid = Exec::empty({n, 3}, options);
  const at::Tensor second_moment = Exec::empty({n}, options);
  const at::Tensor status = Exec::empty({n}, options.dtype(at::kChar));
  const at::Tensor num_neighbors = Exec::empty({n}, options.dtype(at::kInt));
  VoronoiOutputs out;
  if (grid_order) {
    out.order = n > 0 ? in.row_of_position.to(at::kLong) : Exec::empty({0}, options.dtype(at::kLong));
  }
  if (n > 0) {
    at::Tensor position_of_row;
    if (!grid_order) {
      TORCH_CHECK(in.position_of_row.defined(), "torchvor: internal error: the inverse order was not computed");
      position_of_row = in.position_of_row;
    }
    Exec::for_each(n, ToRowsFunctor<io_t>{grid_order ? nullptr : position_of_row.data_ptr<int32_t>(),
                                          in.data<io_t>(), volume.data_ptr<io_t>(), centroid.data_ptr<io_t>(),
                                          second_moment.data_ptr<io_t>(), status.data_ptr<int8_t>(),
                                          num_neighbors.data_ptr<int32_t>()});
  }
  out.cells = {volume, centroid, second_moment, status, num_neighbors};
  return out;
}

// The outputs by position, every status "not computed" (`status`, from
// not_computed_statuses); the records are written by the passes (and by
// PoisonUnwrittenFunctor for the cells that none wrote).
template <typename io_t>
PositionOutputs poisoned_outputs(const at::Tensor& status, const at::TensorOptions& options) {
  PositionOutputs out;
  out.records = empty_records<io_t>(status.size(0), options);
  out.status = status;
  return out;
}

inline at::Tensor not_computed_statuses(int64_t n, const at::TensorOptions& options) {
  return at::full({n}, int(core::kNotComputed), options.dtype(at::kChar));
}

// Whether cells start from a tetrahedron of their first neighbours where
// one fits (core::start_tetrahedron), as by default, or always from the box:
// TORCHVOR_CELL_START=box (the tests compare the two; benchmarks time them).
inline bool tetrahedron_start() {
  const char* forced = std::getenv("TORCHVOR_CELL_START");
  return !(forced != nullptr && std::strcmp(forced, "box") == 0);
}

// Whether float32 thread cells of at most 32 planes keep their triangles in
// 12 bytes (core::CompactTriangles), as by default, or in 16:
// TORCHVOR_THREAD_TRIANGLES=full (the tests compare the two; benchmarks time them).
inline bool compact_triangles() {
  const char* forced = std::getenv("TORCHVOR_THREAD_TRIANGLES");
  return !(forced != nullptr && std::strcmp(forced, "full") == 0);
}

// Clips a chunk of cells. With `vertex_balls` (the grid of `points` by
// position), cells whose neighbours run out before the radius of security
// are finished on it (ClipFunctor's kVertexBalls).
// With kUpToDeviceCount, only the cells that `live` says are valid run (the
// speculative retry pass; kernels of their own).
template <typename Exec, typename io_t, typename T, int MAX_PLANES, bool kVertexBalls,
          bool kUpToDeviceCount = false>
void clip_chunk(const at::Tensor& points, const at::Tensor& box,
                const c10::optional<at::Tensor>& batch, const at::Tensor& cells,
                const at::Tensor& neighbors, bool column_major, int band_widenings,
                bool rows_by_step, const Grid* vertex_balls, c10::optional<double> neighbor_spread,
                PositionOutputs& out, const core::DeviceCount& live = {}) {
  static_assert(!kVertexBalls || MAX_PLANES == kVertexBallPlanes, "vertex-ball passes run at the largest tier");
  constexpr bool kCompactPossible = std::is_same<T, float>::value && MAX_PLANES <= 32;
  // The functor with or without compact triangles (std::true_type or std::false_type).
  const auto functor = [&](auto compact) {
    ClipFunctor<io_t, T, MAX_PLANES, kVertexBalls, decltype(compact)::value> clip{
        {},
        points.data_ptr<io_t>(),        box.data_ptr<io_t>(),
        batch.has_value() ? batch->data_ptr<int64_t>() : nullptr,
        cells.data_ptr<int32_t>(),      neighbors.data_ptr<int32_t>(),
        static_cast<int32_t>(neighbors.size(1)), column_major, static_cast<int32_t>(cells.size(0)),
        T(core::ClipTolerance<T>::value),
        band_widenings,                 tetrahedron_start(),
        rows_by_step,                   out.data<io_t>(),
        out.status.data_ptr<int8_t>()};
    if constexpr (kVertexBalls) clip.grid = vertex_balls->view<io_t>();
    if constexpr (kUpToDeviceCount) {
      return core::up_to_device_count(clip, live);
    } else {
      return clip;
    }
  };
  // One thread per cell (ConvexCell) or a group of lanes per cell
  // (CooperativeCell): the backend chooses by the pass's size, k and the
  // pilot's neighbour spread, and TORCHVOR_CELLS=thread|cooperative
  // overrides it (use_cooperative). Cells finished on the grid vary the most
  // (their sweeps' lengths): the backend's choice for the widest spread,
  // warps on the GPU (each sweeps its cell's rows and points together,
  // where a thread's cell waited on its own loads: vertex_balls.h).
  // Float32 thread cells of the first tier keep their triangles in 12 bytes
  // (compact_triangles).
  // Double-double's products must round separately (Dekker's split); it
  // runs on the CPU only, one thread per cell.
  if constexpr (std::is_same<T, core::DoubleDouble>::value) {
    Exec::for_each(cells.size(0), functor(std::false_type()));
  } else {
    const c10::optional<double> spread =
        kVertexBalls ? c10::optional<double>(std::numeric_limits<double>::infinity()) : neighbor_spread;
    if (use_cooperative("TORCHVOR_CELLS", Exec::cooperative_cells(cells.size(0), neighbors.size(1), spread))) {
      Exec::template for_each_cooperative<typename ClipFunctor<io_t, T, MAX_PLANES>::Arrays>(cells.size(0),
                                                                                          functor(std::false_type()));
    } else {
      if constexpr (kCompactPossible) {
        if (compact_triangles()) {
          Exec::for_each_cell(cells.size(0), neighbors.size(1), functor(std::true_type()));
          return;
        }
      }
      Exec::for_each_cell(cells.size(0), neighbors.size(1), functor(std::false_type()));
    }
  }
}

template <typename Exec, typename io_t, typename T>
void clip_chunk_tier(const at::Tensor& points, const at::Tensor& box,
                     const c10::optional<at::Tensor>& batch, const at::Tensor& cells,
                     const at::Tensor& neighbors, int tier, const Grid* vertex_balls,
                     c10::optional<double> neighbor_spread, PositionOutputs& out) {
  constexpr bool column_major = Exec::kColumnMajorNeighbors;
  if (vertex_balls != nullptr) {
    TORCH_CHECK(tier == 2, "torchvor: internal error: a vertex-ball pass below the largest tier");
    clip_chunk<Exec, io_t, T, kVertexBallPlanes, true>(points, box, batch, cells, neighbors, column_major, 0, false,
                                                        vertex_balls, neighbor_spread, out);
    return;
  }
  switch (tier) {
    case 0: clip_chunk<Exec, io_t, T, 32, false>(points, box, batch, cells, neighbors, column_major, 0, false, nullptr, neighbor_spread, out); break;
    case 1: clip_chunk<Exec, io_t, T, 64, false>(points, box, batch, cells, neighbors, column_major, 0, false, nullptr, neighbor_spread, out); break;
    default: clip_chunk<Exec, io_t, T, 160, false>(points, box, batch, cells, neighbors, column_major, 0, false, nullptr, neighbor_spread, out); break;
  }
}

// The speculative retry pass's clip (voronoi_passes): the first tier, in
// the points' precision, on the cells of `cells` that `live` says are valid.
template <typename Exec, typename io_t>
void clip_chunk_up_to_device_count(const at::Tensor& points, const at::Tensor& box,
                                   const c10::optional<at::Tensor>& batch, const at::Tensor& cells,
                                   const at::Tensor& neighbors, c10::optional<double> neighbor_spread,
                                   const core::DeviceCount& live, PositionOutputs& out) {
  clip_chunk<Exec, io_t, io_t, 32, false, true>(points, box, batch, cells, neighbors, Exec::kColumnMajorNeighbors,
                                                0, false, nullptr, neighbor_spread, out, live);
}

// The last resort, on the CPU whatever the device (as the paper's fallback):
// double-double arithmetic, and an inconsistent clip may widen its predicate
// band up to 6 times tenfold. Only a handful of cells ever get here.
template <typename io_t>
void clip_chunk_double_double(const at::Tensor& points, const at::Tensor& box,
                              const c10::optional<at::Tensor>& batch, const at::Tensor& cells,
                              const at::Tensor& neighbors, bool column_major, const Grid* vertex_balls,
                              PositionOutputs& out) {
  const int64_t m = cells.size(0);
  const auto cpu = [](const at::Tensor& t) { return t.to(at::kCPU).contiguous(); };
  const c10::optional<at::Tensor> batch_cpu =
      batch.has_value() ? c10::optional<at::Tensor>(cpu(*batch)) : c10::nullopt;
  const Grid vertex_balls_cpu = vertex_balls != nullptr ? vertex_balls->to_cpu() : Grid{};
  PositionOutputs part;
  part.records = empty_records<io_t>(m, points.options().device(at::kCPU));
  part.status = at::empty({m}, points.options().device(at::kCPU).dtype(at::kChar));
  const auto clip = [&](auto finish_by_vertex_balls) {
    clip_chunk<cpu::CpuExec, io_t, core::DoubleDouble, 160, decltype(finish_by_vertex_balls)::value>(
        cpu(points), cpu(box), batch_cpu, cpu(cells), cpu(neighbors), column_major,
        /*band_widenings=*/6, /*rows_by_step=*/true, vertex_balls != nullptr ? &vertex_balls_cpu : nullptr,
        /*neighbor_spread=*/c10::nullopt, part);
  };
  if (vertex_balls != nullptr) {
    clip(std::true_type{});
  } else {
    clip(std::false_type{});
  }
  const at::Tensor rows = cells.to(at::kLong);
  out.records.index_copy_(0, rows, part.records.to(out.records.device()));
  out.status.index_copy_(0, rows, part.status.to(out.status.device()));
}

// One pass over `cells` (int32 point ids), in chunks of bounded memory.
template <typename Exec, typename io_t>
void run_pass(const at::Tensor& points, const at::Tensor& box,
              const c10::optional<at::Tensor>& batch, const Grid& grid, const at::Tensor& cells,
              const PassSettings& pass, c10::optional<double> neighbor_spread, int64_t memory_budget,
              PositionOutputs& out) {
  TORCH_CHECK(cells.is_contiguous(), "torchvor: internal error: cell list not contiguous");
  // The budget holds the chunk's neighbour ids. Chunks of equal size: a
  // small last chunk would leave most of the GPU idle while its few cells
  // run, and every chunk ends in such a tail, so fewer chunks are better.
  const int64_t bytes_per_cell = pass.k * int64_t(sizeof(int32_t));
  const int64_t largest_chunk = std::max<int64_t>(1024, memory_budget / bytes_per_cell);
  const int64_t chunks = std::max<int64_t>(1, (cells.size(0) + largest_chunk - 1) / largest_chunk);
  const int64_t chunk = (cells.size(0) + chunks - 1) / chunks;
  for (int64_t begin = 0; begin < cells.size(0); begin += chunk) {
    const at::Tensor part = cells.slice(0, begin, std::min(cells.size(0), begin + chunk));
    const int64_t m = part.size(0);
    at::Tensor no_distances;  // the clipper recomputes distances from coordinates
    // m * k neighbour ids, laid out as Exec prefers (see kColumnMajorNeighbors)
    at::Tensor neighbors = at::empty({m, pass.k}, points.options().dtype(at::kInt));
    run_knn<Exec, io_t, int32_t>(grid.view<io_t>(), points.data_ptr<io_t>(), /*queries_in_order=*/false,
                        batch.has_value() ? batch->data_ptr<int64_t>() : nullptr,
                        part.data_ptr<int32_t>(), m, pass.k, /*exclude_self=*/true,
                        /*row_by_query=*/false, Exec::kColumnMajorNeighbors, no_distances, neighbors);
    const Grid* vertex_balls = pass.vertex_balls ? &grid : nullptr;
    // Float32 points are clipped in float32 or float64; float64 points only
    // in float64 (`if constexpr`: no float32 cells of float64 points are
    // compiled, which nothing would run).
    const auto clip_in_float64 = [&] {
      clip_chunk_tier<Exec, io_t, double>(points, box, batch, part, neighbors, pass.tier, vertex_balls,
                                          neighbor_spread, out);
    };
    if (pass.precision == Precision::kDoubleDouble) {
      clip_chunk_double_double<io_t>(points, box, batch, part, neighbors,
                                     Exec::kColumnMajorNeighbors, vertex_balls, out);
    } else if constexpr (std::is_same<io_t, double>::value) {
      clip_in_float64();
    } else if (pass.precision == Precision::kFloat64) {
      clip_in_float64();
    } else {
      clip_chunk_tier<Exec, io_t, float>(points, box, batch, part, neighbors, pass.tier, vertex_balls,
                                         neighbor_spread, out);
    }
  }
}

// What a pilot measures: about 1000 cells spread over the grid order,
// computed with k = 64 (a larger pilot k costs latency: on an H200 the
// pilot at k = 96 took ~1 ms of a 12 ms call), and the neighbours they
// needed:
// - `k`, their 98th percentile (pilot_quantile) plus 2, the first pass's k
//   when the caller gives none: blue noise ~19, perturbed grids ~50, white
//   noise 66 (its 98th percentile, ~77, is past the pilot's 64). Most cells
//   then succeed in one pass and the rest retry.
// - `neighbor_spread`, their standard deviation over their mean (each capped
//   at the pilot's k, as a cell that fails there reports it): how unequal
//   the cells' work is, by which the backend chooses a thread or a warp per
//   cell (Exec::cooperative_cells).
struct Pilot {
  int64_t k;
  double neighbor_spread;
};

// The share of the pilot's cells that the first pass's k covers, or
// TORCHVOR_PILOT_QUANTILE in (0, 1] (benchmarks). 0.98 rather than 0.9:
// fewer retries beat a smaller first pass on every kind measured. Voronoi
// with the default k, quantile 0.9 / 0.98 (H100, 904498b, ab_env.py
// --pilot, 7 rounds): 10M perturbed grid 145.4 / 141.9 ms, white noise
// 215.4 / 209.9, blue noise 38.9 / 38.8; 1M 15.9 / 15.4, 23.3 / 22.6, 4.77
// / 4.60 (0.95 in between, 0.8 worse everywhere). 2 CPU cores, 100K:
// 398.8 / 389.5, 496.9 / 489.7, 247.9 / 245.0 ms.
inline double pilot_quantile() {
  constexpr double kDefault = 0.98;
  const char* chosen = std::getenv("TORCHVOR_PILOT_QUANTILE");
  const double quantile = chosen != nullptr ? std::atof(chosen) : kDefault;
  return (quantile > 0.0 && quantile <= 1.0) ? quantile : kDefault;
}

// The most neighbours a retry asks for; a cell that needs more is finished
// on the grid, by the empty balls of its vertices, from a list of this many
// (core::finish_by_vertex_balls): a cell that reaches into empty space would
// ask for up to the whole cloud. 256, not 128: 128 is 9-16% faster on two
// inputs but 75% slower on a third, the same on white noise (H100, 1M points,
// a warp sweeping each cell, 256 / 128: 200 clusters of 0.05 38.7 / 67.8 ms,
// 20 clusters of 0.02 117.5 / 107.4, white noise in a box 3x wide 81.3 /
// 68.3, white noise 22.6 / 22.4; 64 was slower on all four;
// benchmarks/NOTES.md).
// TORCHVOR_VERTEX_BALLS_K (an integer >= 1) overrides it (tests, benchmarks).
inline int64_t vertex_balls_k() {
  constexpr int64_t kDefault = 256;
  const char* chosen = std::getenv("TORCHVOR_VERTEX_BALLS_K");
  if (chosen == nullptr) return kDefault;
  char* end = nullptr;
  const long long value = std::strtoll(chosen, &end, 10);
  return (end != chosen && *end == '\0' && value >= 1) ? static_cast<int64_t>(value) : kDefault;
}

// Counts the sample's cells by the neighbours they needed: bin c holds the
// cells that needed c (the last bin also those that needed more).
template <typename io_t>
struct NeededHistogramFunctor {
  const int32_t* cells;              // the pilot's positions
  const CellRecord<io_t>* records;   // (N,) by position
  int32_t* bins;                     // (num_bins,), zeroed
  int32_t num_bins;

  TV_HD void operator()(int64_t i) const {
    const int32_t needed = records[cells[i]].num_neighbors;
    core::atomic_increment(bins + core::min_of(core::max_of(needed, int32_t(0)), num_bins - 1));
  }
};

// The pilot's statistics from that histogram (on the host): the quantile
// with linear interpolation between order statistics (as torch.quantile's
// default), the mean and the standard deviation (n - 1 in the denominator;
// NaN for one cell).
inline void needed_statistics(const int32_t* bins, int num_bins, double quantile, double& at_quantile,
                              double& mean, double& deviation) {
  int64_t count = 0;
  double sum = 0.0;
  for (int c = 0; c < num_bins; ++c) {
    count += bins[c];
    sum += double(c) * bins[c];
  }
  mean = sum / double(count);
  double squares = 0.0;
  for (int c = 0; c < num_bins; ++c) squares += bins[c] * (double(c) - mean) * (double(c) - mean);
  deviation = count > 1 ? std::sqrt(squares / double(count - 1)) : std::numeric_limits<double>::quiet_NaN();
  // The value of order statistic r (0-based) of the sorted sample.
  const auto order_statistic = [&](int64_t r) {
    int64_t seen = 0;
    for (int c = 0; c < num_bins; ++c) {
      seen += bins[c];
      if (r < seen) return double(c);
    }
    return double(num_bins - 1);
  };
  // In float, step by step as torch.quantile computes it for the float
  // tensor it was given before (the same first-pass k on every input), and
  // its lerp from the nearer end.
  const float rank = float(quantile) * float(count - 1);
  const int64_t below = static_cast<int64_t>(rank);
  const float low = static_cast<float>(order_statistic(below));
  const float high = static_cast<float>(order_statistic(std::min(below + 1, count - 1)));
  const float weight = rank - float(below);
  at_quantile = weight < 0.5f ? low + weight * (high - low) : high - (high - low) * (1.0f - weight);
}

template <typename Exec, typename io_t, typename Run>
Pilot run_pilot(const at::Tensor& positions, int64_t largest_cloud, const Run& run, PositionOutputs& out) {
  const int64_t n = positions.size(0);
  const int64_t stride = std::max<int64_t>(1, n / 1024);
  const at::Tensor sample = positions.slice(0, 0, n, stride).contiguous();
  const int64_t pilot_k = std::min<int64_t>(64, largest_cloud);
  run(sample, PassSettings{pilot_k, 0, Precision::kInput}, c10::nullopt);
  // One small kernel and one read: the statistics of ~1000 integers in
  // neighbour counts up to pilot_k come from their histogram. torch's
  // quantile, mean and standard deviation took ~25 launches, most of their
  // time an idle GPU waiting for the host: 1M blue noise took 5.32 ms with
  // them, 4.83 with this (H100, benchmarks/NOTES.md).
  const int32_t num_bins = static_cast<int32_t>(pilot_k) + 1;
  const at::Tensor bins = at::zeros({num_bins}, positions.options());
  Exec::for_each(sample.size(0), NeededHistogramFunctor<io_t>{sample.data_ptr<int32_t>(), out.data<io_t>(),
                                                              bins.data_ptr<int32_t>(), num_bins});
  const at::Tensor read = bins.to(at::kCPU);
  double at_quantile = 0.0, mean = 0.0, deviation = 0.0;
  needed_statistics(read.data_ptr<int32_t>(), num_bins, pilot_quantile(), at_quantile, mean, deviation);
  const int64_t covered = static_cast<int64_t>(at_quantile);
  // A sample of one cell has no standard deviation (NaN): call it even.
  const double spread = (mean > 0 && std::isfinite(deviation)) ? deviation / mean : 0.0;
  return {std::min<int64_t>(256, std::max<int64_t>(8, covered + 2)), spread};
}

// TORCHVOR_TEST_UNWRITTEN_CELL=p (tests only): the first pass's result for
// grid position p is dropped, its record zeroed and its status set back to
// "not computed", as if no pass had written it. Such a cell asks for nothing
// to be raised, so unless other cells do, no later pass computes it. The
// tests check that it then reads as not computed, not as its zeroed record.
template <typename io_t>
void forget_cell_for_tests(int attempt, PositionOutputs& out) {
  const char* chosen = std::getenv("TORCHVOR_TEST_UNWRITTEN_CELL");
  if (chosen == nullptr || attempt != 0) return;
  const int64_t position = std::atoll(chosen);
  if (position < 0 || position >= out.status.size(0)) return;
  out.records.select(0, position).zero_();
  out.status.select(0, position).fill_(int(core::kNotComputed));
}

// What a pass's failed cells ask the next pass to raise.
struct RetryAsks {
  bool neighbors;  // some ran out of neighbours before the radius of security
  bool planes;     // some overflowed their plane or triangle arrays
  bool precision;  // some were inconsistent or ill-conditioned in this arithmetic
};

// The settings of the pass after `pass`, raised as `ask` asks (equal to
// `pass` when nothing is left to raise).
inline PassSettings escalated(const PassSettings& pass, const RetryAsks& ask, int64_t largest_cloud,
                              bool is_double) {
  PassSettings next = pass;
  // 1.5x, not 2x: the failed cells mostly need only a few more neighbours
  // (2 CPU cores, 100K white / perturbed / blue: 502 / 396 / 256 ms at 2x,
  // 488 / 384 / 251 at 1.5x, 496 / 386 / 254 at 1.25x).
  if (ask.neighbors) {
    // Up to vertex_balls_k neighbours by the radius of security, then that
    // many and the grid: whether and how a cell is finished on the grid
    // depends on the cell alone, not on the passes before.
    const int64_t most = vertex_balls_k();
    const int64_t more = std::min(pass.k + std::max<int64_t>(8, pass.k / 2), largest_cloud);
    if (more <= most || pass.k < most) {
      next.k = std::min(more, most);
    } else {
      next.k = most;
      next.vertex_balls = true;
    }
  }
  if (ask.planes) next.tier = std::min(pass.tier + 1, 2);
  if (next.vertex_balls) next.tier = 2;  // kVertexBallPlanes
  if (ask.precision) {
    next.precision = (pass.precision == Precision::kInput && !is_double) ? Precision::kFloat64
                                                                         : Precision::kDoubleDouble;
  }
  return next;
}

// The retry that the first pass most likely needs (more neighbours for the
// cells that ran out: blue noise at the pilot's k, 825 of 10M cells; a
// Lloyd step at 1M, ~80), launched before the host has read how many cells
// failed: its kernels take the count from the device (core::DeviceCount).
// Without it the GPU idled while the words travelled and the host launched the
// retry, and a second read followed.
//
// Its outcome stands for the round's whenever the failed cells fit its
// capacity; the loop then goes on from its settings. That is also what the
// loop would have run when the cells asked only for neighbours (the same
// settings and kernels: a retry of up to 16384 cells runs warp cells and
// warp kNN, Exec::cooperative_cells); other asks are raised after it. When
// the cells overflow the capacity, it runs no cell at all and the loop
// retries as before. So the cells that a pass computes depend on counts,
// never on the order of the scan's appends.
struct Speculation {
  PassSettings pass{0, 0, Precision::kInput};
  int64_t capacity = 0;  // 0: none
};

// At most this many cells, or TORCHVOR_SPECULATIVE_CELLS (0: no speculative
// retry; tests use small ones), and at most the memory budget's worth of
// neighbours (but at least 1024 cells, as run_pass's chunks).
inline int64_t speculative_cells() {
  constexpr int64_t kDefault = 16384;
  const char* chosen = std::getenv("TORCHVOR_SPECULATIVE_CELLS");
  return chosen != nullptr ? std::max<int64_t>(0, std::atoll(chosen)) : kDefault;
}

inline Speculation speculative_retry(const PassSettings& first, int64_t cells, int64_t largest_cloud,
                                     int64_t memory_budget) {
  const PassSettings more = escalated(first, RetryAsks{true, false, false}, largest_cloud, false);
  if (more.vertex_balls || more.k <= first.k) return {};
  const int64_t by_budget = std::max<int64_t>(1024, memory_budget / (more.k * int64_t(sizeof(int32_t))));
  return {more, std::min({cells, speculative_cells(), by_budget})};
}

// The speculative retry pass: kNN and clip of the cells of `cells` that
// `live` says are valid, with `pass`'s neighbours, at the first tier and in
// the points' precision (speculative_retry's settings).
template <typename Exec, typename io_t>
void run_speculative_pass(const at::Tensor& points, const at::Tensor& box,
                          const c10::optional<at::Tensor>& batch, const Grid& grid, const at::Tensor& cells,
                          const PassSettings& pass, c10::optional<double> neighbor_spread,
                          const core::DeviceCount& live, PositionOutputs& out) {
  TORCH_CHECK(pass.tier == 0 && pass.precision == Precision::kInput && !pass.vertex_balls,
              "torchvor: internal error: a speculative pass beyond the first tier");
  const int64_t m = cells.size(0);
  at::Tensor no_distances;
  at::Tensor neighbors = at::empty({m, pass.k}, points.options().dtype(at::kInt));
  run_knn<Exec, io_t, int32_t, true>(grid.view<io_t>(), points.data_ptr<io_t>(), /*queries_in_order=*/false,
                                     batch.has_value() ? batch->data_ptr<int64_t>() : nullptr,
                                     cells.data_ptr<int32_t>(), m, pass.k, /*exclude_self=*/true,
                                     /*row_by_query=*/false, Exec::kColumnMajorNeighbors, no_distances, neighbors,
                                     live);
  clip_chunk_up_to_device_count<Exec, io_t>(points, box, batch, cells, neighbors, neighbor_spread, live, out);
}

// What voronoi_forward puts on the device while it reads the bounds (work
// that needs none of them, which then runs while the host takes them in).
struct Prepared {
  at::Tensor positions;  // (N,) int32: 0, 1, ..., N - 1 (every cell, in grid order)
  at::Tensor status;     // (N,) int8: not_computed_statuses
};

// The passes of voronoi_forward on checked inputs; `bounds` is point_bounds()
// of the points, already read.
template <typename Exec, typename io_t>
VoronoiOutputs voronoi_passes(const at::Tensor& points, const at::Tensor& box,
                              const c10::optional<at::Tensor>& batch, const at::Tensor& bounds,
                              const Prepared& prepared, c10::optional<int64_t> k_in, int64_t memory_budget,
                              bool grid_order, const LaunchOnOutputs& on_outputs) {
  const int64_t n = points.size(0);
  const int64_t num_boxes = box.size(0);
  PositionOutputs out = poisoned_outputs<io_t>(prepared.status, points.options());
  int64_t first_pass_k = 0;
  const auto finished = [&] {
    VoronoiOutputs outputs = finish_outputs<Exec, io_t>(out, points.options(), grid_order);
    outputs.first_pass_k = first_pass_k;
    if (on_outputs) on_outputs(outputs);
    return outputs;
  };
  if (n == 0) return finished();
  // The largest batch element bounds the useful k: a query that asks for as
  // many neighbours as its cloud has points gets -1 padding, i.e. all of them.
  int64_t largest_cloud = 0;  // from the counts already read with the bounds
  for (int64_t b = 0; b < num_boxes; ++b) {
    largest_cloud = std::max(largest_cloud, static_cast<int64_t>(bounds.data_ptr<double>()[7 * b + 6]));
  }
  // Work in grid order: cells, neighbours and outputs are numbered by their
  // position in the grid's sorted order, so that nearby cells (nearby
  // threads) read nearby neighbour coordinates from cache; the outputs go
  // to the caller's rows at the end. The sort is stable, so exact
  // duplicates keep their order and "the lowest index keeps the cell" holds.
  // The grid over the points by position has no index array (the kNN then
  // reads no index a candidate: GridView::original_index).
  Grid grid;
  at::Tensor work_points;  // points by position
  c10::optional<at::Tensor> work_batch;
  const at::Tensor& positions = prepared.positions;
  const auto sort_into_grid = [&](double points_per_cell) {
    const Grid sorted = build_grid<Exec>(points, batch, num_boxes, points_per_cell, bounds, positions);
    out.row_of_position = sorted.sorted_index;
    grid = sorted;
    grid.sorted_index = at::Tensor();
    work_points = sorted.sorted_points;
    work_batch = batch.has_value() ? c10::optional<at::Tensor>(batch->index_select(0, sorted.sorted_index))
                                   : c10::nullopt;
  };
  const auto run = [&](const at::Tensor& cells, const PassSettings& pass, c10::optional<double> neighbor_spread) {
    run_pass<Exec, io_t>(work_points, box, work_batch, grid, cells, pass, neighbor_spread, memory_budget, out);
  };
  const auto run_speculative = [&](const at::Tensor& cells, const PassSettings& pass,
                                   c10::optional<double> neighbor_spread, const core::DeviceCount& live) {
    run_speculative_pass<Exec, io_t>(work_points, box, work_batch, grid, cells, pass, neighbor_spread, live, out);
  };
  // The grid's density follows k (points_per_cell_for). Without k, the pilot
  // runs on the densest grid of that rule (1.5 points a cell, which is blue
  // noise's: k ~ 19) and the grid is rebuilt when the measured k wants cells
  // half as full again or more (k >= 36; white noise: k ~ 62, 4 points a
  // cell; on 2 CPU cores 100K white 511 -> 484 ms). The main pass recomputes
  // every cell, so the pilot's outputs, numbered in the old order, are
  // overwritten.
  const double first_points_per_cell = points_per_cell_for(k_in.value_or(0));
  sort_into_grid(first_points_per_cell);
  int64_t k = k_in.value_or(0);
  c10::optional<double> neighbor_spread;  // from the pilot, where one runs
  if (!k_in.has_value()) {
    const Pilot pilot = run_pilot<Exec, io_t>(positions, largest_cloud, run, out);
    k = pilot.k;
    neighbor_spread = pilot.neighbor_spread;
    if (points_per_cell_for(k) >= 1.5 * first_points_per_cell) sort_into_grid(points_per_cell_for(k));
  } else if (Exec::cells_need_spread(n, std::min(k, largest_cloud))) {
    // The caller's k leaves the backend's choice of cells to the spread.
    neighbor_spread = run_pilot<Exec, io_t>(positions, largest_cloud, run, out).neighbor_spread;
  }
  PassSettings pass{std::min(k, largest_cloud), 0, Precision::kInput};
  first_pass_k = pass.k;
  at::Tensor pending = positions;
  // The last scan's failed cells, and whether some of them no pass wrote.
  at::Tensor last_failed;
  bool unwritten = false;
  const bool is_double = points.scalar_type() == at::kDouble;
  const auto scan = [&](const at::Tensor& cells, bool all_positions, const at::Tensor& failed_cells,
                        int32_t* words, const int32_t* live_count) {
    const int64_t scan_threads = StatusScanFunctor::threads(cells.size(0));
    Exec::for_each(scan_threads, StatusScanFunctor{out.status.data_ptr<int8_t>(),
                                                   all_positions ? nullptr : cells.data_ptr<int32_t>(),
                                                   cells.size(0), scan_threads, failed_cells.data_ptr<int32_t>(),
                                                   words, live_count});
  };
  // The outputs finished before the first read (with on_outputs), which
  // stand unless a later pass runs (dropped then, so that two sets of
  // outputs are not held at once) or unwritten cells are poisoned.
  c10::optional<VoronoiOutputs> finished_early;
  for (int attempt = 0; attempt < 64 && pending.size(0) > 0; ++attempt) {
    if (attempt > 0) finished_early.reset();
    run(pending, pass, neighbor_spread);
    forget_cell_for_tests<io_t>(attempt, out);
    // Which status codes this pass produced and which cells failed (words 0
    // and 1), in one read (one device sync). The failed cells come in no set
    // order (the scan appends them as it finds them); each cell's result
    // does not depend on the order of a pass.
    const at::Tensor failed_cells = at::empty({pending.size(0)}, pending.options());
    const at::Tensor words = at::zeros({4}, pending.options());
    scan(pending, pending.is_same(positions), failed_cells, words.data_ptr<int32_t>(), nullptr);
    // After the first pass, the retry it most likely needs runs before the
    // host reads the words: on the failed cells with more neighbours, if
    // they fit its capacity (core::DeviceCount), its own outcome in words 2
    // and 3 (the same read).
    const Speculation speculation =
        attempt == 0 ? speculative_retry(pass, pending.size(0), largest_cloud, memory_budget) : Speculation{};
    at::Tensor speculative_failed;
    if (speculation.capacity > 0) {
      const at::Tensor cells = failed_cells.slice(0, 0, speculation.capacity);
      const core::DeviceCount live{words.data_ptr<int32_t>() + 1, speculation.capacity};
      run_speculative(cells, speculation.pass, neighbor_spread, live);
      forget_cell_for_tests<io_t>(attempt, out);
      speculative_failed = at::empty({speculation.capacity}, pending.options());
      scan(cells, false, speculative_failed, words.data_ptr<int32_t>() + 2, live.count);
    }
    const typename Exec::HostRead reading(words);
    if (attempt == 0 && !grid_order) {
      // The inverse order depends on the grid alone: the device computes it
      // while the host waits for the words (a round trip it would idle; 10M
      // blue noise, H100: 35.69 ms a call with the inverse after the passes,
      // 35.33 here).
      out.position_of_row = invert_order<Exec>(out.row_of_position);
    }
    if (attempt == 0 && on_outputs) finished_early = finished();
    const at::Tensor read = reading.wait();
    int32_t seen_bits = read.data_ptr<int32_t>()[0];
    int64_t failed = read.data_ptr<int32_t>()[1];
    at::Tensor failed_list = failed_cells;
    if (speculation.capacity > 0 && failed > 0 && failed <= speculation.capacity) {
      // The speculative pass recomputed every failed cell: its outcome
      // stands for this round's.
      pass = speculation.pass;
      seen_bits = read.data_ptr<int32_t>()[2];
      failed = read.data_ptr<int32_t>()[3];
      failed_list = speculative_failed;
    }
    const auto seen = [&](core::CellStatus code) { return ((seen_bits >> (code - core::kNotComputed)) & 1) != 0; };
    const RetryAsks ask{seen(core::kSecurityRadiusNotReached),
                        seen(core::kTooManyPlanes) || seen(core::kTooManyVertices),
                        seen(core::kBoundaryError) || seen(core::kIllConditioned)};
    last_failed = failed_list.slice(0, 0, failed);
    unwritten = seen(core::kNotComputed);
    if (!(ask.neighbors || ask.planes || ask.precision || unwritten)) break;
    pending = last_failed;
    // Escalate what the failures ask for; stop when nothing is left to raise.
    const PassSettings next = escalated(pass, ask, largest_cloud, is_double);
    if (next == pass) break;  // nothing left to raise
    pass = next;
  }
  if (unwritten) {
    Exec::for_each(last_failed.size(0), PoisonUnwrittenFunctor<io_t>{last_failed.data_ptr<int32_t>(),
                                                                    out.status.data_ptr<int8_t>(), out.data<io_t>()});
  }
  if (finished_early.has_value() && !unwritten) return *finished_early;
  return finished();
}

// torchvor::voronoi_cells, or with `grid_order` torchvor::voronoi_cells_grid_order;
// `on_outputs` (torchvor::lloyd_step) is launched on the outputs before the
// call returns (LaunchOnOutputs). Each backend instantiates it once
// (voronoi.cpp, voronoi.cu), for its voronoi ops and its lloyd_step.
template <typename Exec>
VoronoiOutputs voronoi_forward(const at::Tensor& points_in, const at::Tensor& box_in,
                               const c10::optional<at::Tensor>& batch_in, c10::optional<int64_t> k_in,
                               int64_t memory_budget, bool grid_order, const LaunchOnOutputs& on_outputs) {
  check_voronoi_inputs(points_in, box_in, batch_in, k_in, memory_budget);
  const int64_t num_boxes = box_in.size(0);
  const at::Tensor points = points_in.contiguous();
  const at::Tensor box = box_in.contiguous();
  const c10::optional<at::Tensor> batch =
      batch_in.has_value() ? c10::optional<at::Tensor>(batch_in->contiguous()) : c10::nullopt;
  // One read from the device for the value checks and the grid: the points'
  // bounds per batch element and the box. Without a batch, the bounds also
  // say whether every point is finite (see point_bounds); with one, that is
  // checked separately.
  ValueChecks values;
  if (batch.has_value()) values.finite(points, "points");
  std::vector<at::Tensor> to_read = values.conditions();
  to_read.push_back(box);
  std::vector<double> read;
  // The positions and statuses need no bounds: launched after the read's
  // copy, they run while the host takes the bounds in and launches the grid.
  // Launched before it, they delayed the copy by their ~52 us of kernels at
  // 10M points (H100), for which the host then waited too.
  Prepared prepared;
  const at::Tensor bounds = point_bounds<Exec>(points, batch, num_boxes, to_read, &read, [&] {
    prepared = {Exec::iota(points.size(0), points.options()), not_computed_statuses(points.size(0), points.options())};
  });
  values.verify(read.data());
  check_voronoi_values(bounds, read.data() + values.conditions().size(), num_boxes);
  VoronoiOutputs result;
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "torchvor::voronoi_cells", [&] {
    result = voronoi_passes<Exec, scalar_t>(points, box, batch, bounds, prepared, k_in, memory_budget, grid_order,
                                            on_outputs);
  });
  return result;
}

}  // namespace ops
}  // namespace torchvor

// TORCHVOR_VORONOI_FORWARD(, Exec) instantiates voronoi_forward for a backend
// (voronoi.cpp, voronoi.cu); TORCHVOR_VORONOI_FORWARD(extern, Exec) declares
// that instantiation where torchvor::lloyd_step calls it (lloyd.cpp,
// lloyd.cu), so that each backend compiles its passes once.
#define TORCHVOR_VORONOI_FORWARD(EXTERN, Exec)                                                                \
  EXTERN template torchvor::ops::VoronoiOutputs torchvor::ops::voronoi_forward<Exec>(                          \
      const at::Tensor& points, const at::Tensor& box, const c10::optional<at::Tensor>& batch,                \
      c10::optional<int64_t> k, int64_t memory_budget, bool grid_order,                                       \
      const torchvor::ops::LaunchOnOutputs& on_outputs)
