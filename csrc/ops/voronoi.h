// torchvor::voronoi_cells, shared by the CPU and CUDA backends.
//
// Cells are computed chunk by chunk (kNN into a bounded buffer, then clipping),
// so no N x k neighbour array ever exists. Failed cells are retried with what
// their status asks for: more neighbours, larger arrays, or more precision
// (float64, then double-double on the CPU, whose clips decide by exact
// predicates; ill-conditioned integrals ask for precision too).
// A cell that fails every pass keeps its status and NaN outputs.
#pragma once

#include <ATen/ATen.h>

#include <algorithm>
#include <vector>

#include "../core/device_count.h"
#include "../core/status.h"
#include "cell_records.h"
#include "checks.h"
#include "clip_pass.h"
#include "giant_cells.h"
#include "grid.h"
#include "options.h"
#include "pilot.h"
#include "recovery.h"
#include "test_faults.h"

namespace torchvor {
namespace ops {

// What voronoi_forward puts on the device while it reads the bounds (work
// that needs none of them, which then runs while the host takes them in).
struct Prepared {
  at::Tensor positions;  // (N,) int32: 0, 1, ..., N - 1 (every cell, in grid order)
  at::Tensor status;     // (N,) int8: not_computed_statuses
};

// The passes of voronoi_forward on checked inputs; `bounds` is point_bounds()
// of the points, already read.
// With `faces` (voronoi_graph), the passes after the pilot also write the
// cells' faces there (FaceTensors), and the outputs carry the face counts
// and the grid order. With `rows`, only the cells of those rows are
// computed (the pilot's too) and returned, row m the cell of rows[m].
template <typename Exec, typename io_t>
VoronoiOutputs voronoi_passes(const at::Tensor& points, const at::Tensor& box,
                              const c10::optional<at::Tensor>& batch, const at::Tensor& bounds,
                              const Prepared& prepared, c10::optional<int64_t> k_in, int64_t memory_budget,
                              bool grid_order, const LaunchOnOutputs& on_outputs, const Options& options,
                              const FaceTensors* faces = nullptr, const c10::optional<at::Tensor>& rows = c10::nullopt) {
  const int64_t n = points.size(0);
  const int64_t num_boxes = box.size(0);
  PositionOutputs out = poisoned_outputs<io_t>(prepared.status, points.options());
  int64_t first_pass_k = 0;
  const auto finished = [&] {
    VoronoiOutputs outputs = finish_outputs<Exec, io_t>(out, points.options(), grid_order, rows);
    outputs.first_pass_k = first_pass_k;
    if (faces != nullptr) {
      outputs.face_count = face_counts<io_t>(out.records);
      outputs.row_of_position = n > 0 ? out.row_of_position : at::empty({0}, points.options().dtype(at::kInt));
    }
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
  // Exact copies go behind the other points, outside the grid, as DUPLICATE
  // cells (set_copies_aside): a point copied thousands of times would
  // otherwise fill the neighbour lists of its cell and theirs with one plane.
  Grid grid;
  at::Tensor work_points;  // points by position
  c10::optional<at::Tensor> work_batch;
  at::Tensor positions = prepared.positions;  // the cells to compute: every position but the copies'
  const auto sort_into_grid_once = [&](double points_per_cell) {
    at::Tensor sorted_ids;
    grid = build_grid<Exec>(points, batch, num_boxes, points_per_cell, bounds, prepared.positions, &sorted_ids);
    const int64_t kept = set_copies_aside<Exec>(grid, sorted_ids);
    out.row_of_position = grid.sorted_index;
    grid.sorted_index = at::Tensor();
    grid.tie_order = out.row_of_position;  // neighbours at equal distances in the caller's order
    work_points = grid.sorted_points;
    work_batch = batch.has_value() ? c10::optional<at::Tensor>(batch->index_select(0, out.row_of_position))
                                   : c10::nullopt;
    positions = prepared.positions.slice(0, 0, kept);
    if (rows.has_value()) {  // the asked rows' positions, in grid order
      const at::Tensor asked = at::zeros({n}, rows->options().dtype(at::kBool)).index_fill_(0, *rows, true);
      positions = asked.index_select(0, out.row_of_position.slice(0, 0, kept)).nonzero().squeeze(1).to(at::kInt);
    }
    return kept;
  };
  // The grid at `points_per_cell` of the points it holds: when copies are
  // most of the points, it is rebuilt as dense as their count says.
  const auto sort_into_grid = [&](double points_per_cell) {
    int64_t kept = sort_into_grid_once(points_per_cell);
    if (2 * kept < n) kept = sort_into_grid_once(points_per_cell * double(n) / double(kept));
    if (kept < n) {
      Exec::for_each(n - kept, DuplicateRecordFunctor<io_t>{work_points.data_ptr<io_t>(), kept,
                                                            out.status.data_ptr<int8_t>(), out.data<io_t>()});
    }
    if (rows.has_value() && kept > 0) {
      // Every cell not computed yet (after a rebuild too, where the pilot's
      // cells are numbered in the old order). The records of cells not asked
      // for are never written nor returned.
      out.status.slice(0, 0, kept).fill_(int(core::kNotComputed));
    }
  };
  const auto run = [&](const at::Tensor& cells, const PassSettings& pass, c10::optional<double> neighbor_spread) {
    run_pass<Exec, io_t>(work_points, box, work_batch, grid, cells, pass, neighbor_spread, memory_budget, options,
                         out);
  };
  const auto run_speculative = [&](const at::Tensor& cells, const PassSettings& pass,
                                   c10::optional<double> neighbor_spread, const core::DeviceCount& live) {
    run_speculative_pass<Exec, io_t>(work_points, box, work_batch, grid, cells, pass, neighbor_spread, live,
                                     options, out);
  };
  // The grid's density follows k (points_per_cell_for). Without k, the pilot
  // runs on the densest grid of that rule (1.5 points a cell, which is blue
  // noise's: k ~ 19) and the grid is rebuilt when the measured k wants cells
  // half as full again or more (k >= 36; white noise: k ~ 62, 4 points a
  // cell). The main pass recomputes every cell, so the pilot's outputs,
  // numbered in the old order, are overwritten.
  const double scale = options.points_per_cell_scale;
  const double first_points_per_cell = points_per_cell_for(k_in.value_or(0), scale);
  sort_into_grid(first_points_per_cell);
  if (positions.size(0) == 0) {  // no cell asked for (rows), or only copies
    if (!grid_order) out.position_of_row = invert_order<Exec>(out.row_of_position, options.testing.scatter_bytes);
    return finished();
  }
  int64_t k = k_in.value_or(0);
  c10::optional<double> neighbor_spread;  // from the pilot, where one runs
  if (!k_in.has_value()) {
    const Pilot pilot = run_pilot<Exec, io_t>(positions, largest_cloud, options.pilot_quantile, run, out);
    k = pilot.k;
    neighbor_spread = pilot.neighbor_spread;
    if (points_per_cell_for(k, scale) >= 1.5 * first_points_per_cell) sort_into_grid(points_per_cell_for(k, scale));
  } else if (Exec::cells_need_spread(n, std::min(k, largest_cloud))) {
    // The caller's k leaves the backend's choice of cells to the spread.
    neighbor_spread = run_pilot<Exec, io_t>(positions, largest_cloud, options.pilot_quantile, run, out).neighbor_spread;
  }
  FaceTensors faces_by_position;  // the backward's upstream in the grid's order
  if (faces != nullptr) {  // not the pilot's cells: the main pass recomputes them in the final grid
    faces_by_position = *faces;
    if (faces->upstream.defined()) {
      faces_by_position.upstream = faces->upstream.index_select(0, out.row_of_position.to(at::kLong)).contiguous();
    }
    out.face_tensors = &faces_by_position;
    out.faces = faces_by_position.outputs_on<io_t>(points.device());
  }
  // The retry loop's passes (the tests may inject a fault after the first).
  auto run_round = with_test_faults(options.testing, out, run);
  auto run_speculative_round = with_test_faults(options.testing, out, run_speculative);
  const PassSettings first_pass{std::min(k, largest_cloud), 0, Precision::kInput};
  first_pass_k = first_pass.k;
  // Cells still to compute, in groups of one pass's settings each: a round
  // runs every group; its failed cells that ask for more precision go on in
  // a group of their own, so that the cells asking only for neighbours or
  // planes keep their arithmetic (double-double is many times slower).
  struct Group {
    at::Tensor cells;
    PassSettings pass;
  };
  std::vector<Group> groups{{positions, first_pass}};
  // Failed cells no pass can help further (all of them in `stuck`): those at
  // the largest tier go to the host (giant cells), any no pass wrote are
  // poisoned (`unwritten`: some may be).
  std::vector<at::Tensor> stuck, giant;
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
  // Adds `cells` to the next round's group of `settings` (one group a setting).
  const auto add_to = [](std::vector<Group>& next, const at::Tensor& cells, const PassSettings& settings) {
    if (cells.size(0) == 0) return;
    for (Group& group : next) {
      if (group.pass == settings) {
        group.cells = at::cat({group.cells, cells});
        return;
      }
    }
    next.push_back({cells, settings});
  };
  // The outputs finished before the first read (with on_outputs), which
  // stand unless a later pass runs (dropped then, so that two sets of
  // outputs are not held at once) or unwritten cells are poisoned.
  c10::optional<VoronoiOutputs> finished_early;
  for (int attempt = 0; attempt < 64 && !groups.empty(); ++attempt) {
    if (attempt > 0) finished_early.reset();
    std::vector<Group> next_groups;
    for (const Group& group : groups) {
      const at::Tensor& pending = group.cells;
      PassSettings pass = group.pass;
      run_round(pending, pass, neighbor_spread);
      // Which status codes this pass produced and which cells failed (words 0
      // and 1), in one read (one device sync). The failed cells come in no set
      // order (the scan appends them as it finds them); each cell's result
      // does not depend on the order of a pass.
      const at::Tensor failed_cells = at::empty({pending.size(0)}, pending.options());
      const at::Tensor words = at::zeros({4}, pending.options());
      scan(pending, !rows.has_value() && pending.is_same(positions), failed_cells, words.data_ptr<int32_t>(),
           nullptr);
      // After the first pass, the retry it most likely needs runs before the
      // host reads the words: on the failed cells with more neighbours, if
      // they fit its capacity (core::DeviceCount), its own outcome in words 2
      // and 3 (the same read).
      // (Not in voronoi_graph's passes: their cells write faces, the speculative kernels do not.)
      const Speculation speculation =
          attempt == 0 && faces == nullptr
              ? speculative_retry(pass, pending.size(0), largest_cloud, memory_budget, options)
              : Speculation{};
      at::Tensor speculative_failed;
      if (speculation.capacity > 0) {
        const at::Tensor cells = failed_cells.slice(0, 0, speculation.capacity);
        const core::DeviceCount live{words.data_ptr<int32_t>() + 1, speculation.capacity};
        run_speculative_round(cells, speculation.pass, neighbor_spread, live);
        speculative_failed = at::empty({speculation.capacity}, pending.options());
        scan(cells, false, speculative_failed, words.data_ptr<int32_t>() + 2, live.count);
      }
      const typename Exec::HostRead reading(words);
      if (attempt == 0 && !grid_order) {
        // The inverse order depends on the grid alone: the device computes it
        // while the host waits for the words (a round trip it would idle).
        out.position_of_row = invert_order<Exec>(out.row_of_position, options.testing.scatter_bytes);
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
      const auto seen = [&](core::CellStatus code) {
        return ((seen_bits >> (code - core::kNotComputed)) & 1) != 0;
      };
      const RetryAsks ask{seen(core::kSecurityRadiusNotReached),
                          seen(core::kTooManyPlanes) || seen(core::kTooManyVertices),
                          seen(core::kBoundaryError) || seen(core::kIllConditioned)};
      const at::Tensor still_failed = failed_list.slice(0, 0, failed);
      if (failed == 0) continue;
      // Escalate what the failures ask for; a cell whose group has nothing
      // left to raise stays failed.
      const auto go_on = [&](const at::Tensor& cells, const RetryAsks& asks) {
        const PassSettings next = escalated(pass, asks, largest_cloud, is_double, options.vertex_balls_k);
        if (next == pass || !(asks.neighbors || asks.planes || asks.precision)) {
          stuck.push_back(cells);
          if (pass.tier == kLastTier) giant.push_back(cells);
          unwritten = unwritten || seen(core::kNotComputed);
        } else {
          add_to(next_groups, cells, next);
        }
      };
      if (ask.precision && (ask.neighbors || ask.planes)) {
        const at::Tensor status = out.status.index_select(0, still_failed.to(at::kLong));
        const at::Tensor imprecise = (status == int(core::kBoundaryError)) | (status == int(core::kIllConditioned));
        go_on(still_failed.masked_select(imprecise), RetryAsks{false, false, true});
        go_on(still_failed.masked_select(imprecise.logical_not()), RetryAsks{ask.neighbors, ask.planes, false});
      } else {
        go_on(still_failed, ask);
      }
    }
    groups = std::move(next_groups);
  }
  for (const Group& group : groups) stuck.push_back(group.cells);  // past the attempts
  unwritten = unwritten || !groups.empty();
  // Cells that overflow even the largest tier: on the host, without bounds.
  // Those still failed keep their status; any no pass wrote are poisoned.
  const at::Tensor empty_cells = at::empty({0}, positions.options());
  const at::Tensor giant_cells = giant.empty() ? empty_cells : at::cat(giant);
  if (giant_cells.size(0) > 0 && !options.testing.bounded_cells &&
      finish_giant_cells(work_points, box, work_batch, giant_cells, out) > 0) {
    finished_early.reset();
  }
  if (unwritten) {
    const at::Tensor left = at::cat(stuck);
    Exec::for_each(left.size(0), PoisonUnwrittenFunctor<io_t>{left.data_ptr<int32_t>(),
                                                              out.status.data_ptr<int8_t>(), out.data<io_t>()});
  }
  if (finished_early.has_value() && !unwritten) return *finished_early;
  return finished();
}

// torchvor::voronoi_cells, or with `grid_order` torchvor::voronoi_cells_grid_order;
// `on_outputs` (torchvor::lloyd_step) is launched on the outputs before the
// call returns (LaunchOnOutputs). Each backend instantiates it once
// (voronoi.cpp, voronoi.cu), for its voronoi ops and its lloyd_step.
// voronoi_graph's faces, by position (voronoi_forward with `graph`).
// With `upstream` (voronoi_cells' backward), one pass instead: no faces
// are kept, each cell's terms go to `faces.gradient` (FaceGradient).
struct GraphFaces {
  bool moments = false;        // asked: the faces' second and third moments too
  FaceTensors faces;           // FaceTensors of the fill pass: offsets in the caller's row order
  at::Tensor row_of_position;  // (N,) int32
  at::Tensor upstream;         // (N, 5) float64 by caller row, or undefined (FaceGradient)
};

// The face arrays of `faces` (neighbor to moments), `rows` faces for n cells.
template <typename Exec>
void allocate_face_arrays(FaceTensors& faces, int64_t n, int64_t rows, bool moments,
                          const at::TensorOptions& options) {
  faces.neighbor = Exec::empty({rows}, options.dtype(at::kInt));
  faces.area = Exec::empty({rows}, options);
  faces.centroid = Exec::empty({rows, 3}, options);
  faces.wall_area = at::zeros({n, 6}, options);
  if (moments) faces.moments = Exec::empty({rows, 9}, options);
}

// Where each position's faces go: the caller's rows in order, each its
// count's share (counts by position from the count pass).
template <typename Exec>
FaceTensors face_layout(const at::Tensor& count, const at::Tensor& row_of_position, bool moments,
                        const at::TensorOptions& options) {
  const int64_t n = count.size(0);
  FaceTensors faces;
  faces.count = count;
  const at::Tensor rows = row_of_position.to(at::kLong);
  const at::Tensor count_by_row = at::zeros({n}, count.options().dtype(at::kLong)).index_copy_(0, rows, count.to(at::kLong));
  const at::Tensor ends = count_by_row.cumsum(0);
  faces.offset = (ends - count_by_row).index_select(0, rows);
  allocate_face_arrays<Exec>(faces, n, n > 0 ? ends[-1].item<int64_t>() : 0, moments, options);
  return faces;
}

// Face arrays for `capacity` faces that the passes' cells claim ranges of
// (FaceOutputs::next_face), each cell's first face in `offset` by position
// (-1: none).
template <typename Exec>
FaceTensors claimed_layout(int64_t n, int64_t capacity, bool moments, const at::TensorOptions& options) {
  FaceTensors faces;
  faces.offset = at::full({n}, -1, options.dtype(at::kLong));
  faces.next_face = at::zeros({1}, options.dtype(at::kLong));
  allocate_face_arrays<Exec>(faces, n, capacity, moments, options);
  return faces;
}

template <typename Exec>
VoronoiOutputs voronoi_forward(const at::Tensor& points_in, const at::Tensor& box_in,
                               const c10::optional<at::Tensor>& batch_in, c10::optional<int64_t> k_in,
                               int64_t memory_budget, bool grid_order, const LaunchOnOutputs& on_outputs,
                               GraphFaces* graph, const c10::optional<at::Tensor>& rows) {
  const int64_t clouds = check_voronoi_inputs(points_in, box_in, batch_in, k_in, memory_budget);
  TORCH_INTERNAL_ASSERT(!rows.has_value() || (graph == nullptr && !grid_order), "rows: voronoi_cells only");
  const Options options = Options::from_environment();
  // One box for several clouds: each cloud gets its copy.
  const at::Tensor box = (box_in.size(0) == 1 && clouds > 1 ? box_in.expand({clouds, 2, 3}) : box_in).contiguous();
  const int64_t num_boxes = box.size(0);
  const at::Tensor points = points_in.contiguous();
  const c10::optional<at::Tensor> batch =
      batch_in.has_value() ? c10::optional<at::Tensor>(batch_in->contiguous()) : c10::nullopt;
  // One read from the device for the value checks and the grid: the points'
  // bounds per batch element and the box. Without a batch, the bounds also
  // say whether every point is finite (see point_bounds); with one, that is
  // checked separately.
  ValueChecks values;
  if (batch.has_value()) values.finite(points, "points");
  check_cell_rows(rows, points, values);
  std::vector<at::Tensor> to_read = values.conditions();
  to_read.push_back(box);
  std::vector<double> read;
  // The positions and statuses need no bounds: launched after the read's
  // copy (not before it, which would delay the copy), they run while the host
  // takes the bounds in and launches the grid.
  Prepared prepared;
  const at::Tensor bounds = point_bounds<Exec>(points, batch, num_boxes, to_read, &read, [&] {
    prepared = {Exec::iota(points.size(0), points.options()), not_computed_statuses(points.size(0), points.options())};
  });
  values.verify(read.data());
  check_voronoi_values(bounds, read.data() + values.conditions().size(), num_boxes);
  VoronoiOutputs result;
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "torchvor::voronoi_cells", [&] {
    if (graph == nullptr) {
      result = voronoi_passes<Exec, scalar_t>(points, box, batch, bounds, prepared, k_in, memory_budget, grid_order,
                                              on_outputs, options, nullptr, rows);
      return;
    }
    if (graph->upstream.defined()) {  // the backward: one pass, its sums by position
      graph->faces.upstream = graph->upstream;  // voronoi_passes puts it in the grid's order
      graph->faces.gradient = at::zeros({points.size(0), 3}, points.options().dtype(at::kDouble));
      graph->faces.gradient_moments = graph->moments;
      result = voronoi_passes<Exec, scalar_t>(points, box, batch, bounds, prepared, k_in, memory_budget, false, {},
                                              options, &graph->faces);
      graph->row_of_position = result.row_of_position;
      return;
    }
    // voronoi_graph: one pass whose cells claim their faces' ranges; where
    // the room ran out (or a host pass computed cells, which do not claim),
    // the passes again, the same cells each time (no result depends on the
    // order of a pass), writing where the first one's counts say.
    const int64_t n = points.size(0);
    // (Options::graph_claimed_faces: the room a cell; 0: the count pass.)
    FaceTensors claiming;
    if (options.graph_claimed_faces > 0) {
      claiming = claimed_layout<Exec>(n, options.graph_claimed_faces * n, graph->moments, points.options());
    }
    const VoronoiOutputs counted = voronoi_passes<Exec, scalar_t>(points, box, batch, bounds, prepared, k_in,
                                                                  memory_budget, false, {}, options, &claiming);
    if (claiming.next_face.defined() && claiming.next_face.item<int64_t>() <= claiming.neighbor.numel()) {
      claiming.count = counted.face_count;
      graph->faces = claiming;
      graph->row_of_position = counted.row_of_position;
      result = counted;
      return;
    }
    claiming = FaceTensors();
    graph->faces = face_layout<Exec>(counted.face_count, counted.row_of_position, graph->moments, points.options());
    const Prepared again{Exec::iota(points.size(0), points.options()),
                         not_computed_statuses(points.size(0), points.options())};
    result = voronoi_passes<Exec, scalar_t>(points, box, batch, bounds, again, k_in, memory_budget, false, {},
                                            options, &graph->faces);
    graph->row_of_position = result.row_of_position;
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
      const torchvor::ops::LaunchOnOutputs& on_outputs, torchvor::ops::GraphFaces* graph,                     \
      const c10::optional<at::Tensor>& rows)
