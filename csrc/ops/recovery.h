// Recovery: what a pass's failed cells ask of the next pass, and the
// speculative retry launched before the host reads them.
#pragma once

#include <ATen/ATen.h>

#include <algorithm>

#include "../core/device_count.h"
#include "../core/status.h"
#include "clip_pass.h"
#include "options.h"

namespace torchvor {
namespace ops {

// After a pass, in one kernel: which status codes its cells got (bit
// code - kNotComputed of words[0]) and the list of the cells that failed
// (words[1] of them); the host reads the two words in one copy.
// Each thread scans kItems cells, `stride` apart (a warp's reads stay
// coalesced), and ORs what it saw into words[0] once: with a thread per
// cell, every warp's update of that one word (set_bits) would queue at one
// L2 slice. The first pass's scan reads no cell list: every position.
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

// What a pass's failed cells ask the next pass to raise.
struct RetryAsks {
  bool neighbors;  // some ran out of neighbours before the radius of security
  bool planes;     // some overflowed their plane or triangle arrays
  bool precision;  // some were inconsistent or ill-conditioned in this arithmetic
};

// The settings of the pass after `pass`, raised as `ask` asks (equal to
// `pass` when nothing is left to raise). `most_neighbors`
// (Options::vertex_balls_k) is the most neighbours a retry asks for: a cell
// that needs more is finished on the grid, by the empty balls of its
// vertices, from a list of that many (core::finish_by_vertex_balls), as a
// cell that reaches into empty space would ask for up to the whole cloud.
inline PassSettings escalated(const PassSettings& pass, const RetryAsks& ask, int64_t largest_cloud,
                              bool is_double, int64_t most_neighbors) {
  PassSettings next = pass;
  // 1.5x, not 2x: the failed cells mostly need only a few more neighbours.
  if (ask.neighbors) {
    // Up to most_neighbors by the radius of security, then that many and the
    // grid: whether and how a cell is finished on the grid depends on the
    // cell alone, not on the passes before.
    const int64_t most = most_neighbors;
    const int64_t more = std::min(pass.k + std::max<int64_t>(8, pass.k / 2), largest_cloud);
    if (more <= most || pass.k < most) {
      next.k = std::min(more, most);
    } else {
      next.k = most;
      next.vertex_balls = true;
    }
  }
  if (ask.planes) next.tier = std::min(pass.tier + 1, kLastTier);
  if (next.vertex_balls) next.tier = std::max(next.tier, kLastDeviceTier);  // kVertexBallPlanes at least
  if (ask.precision) {
    next.precision = (pass.precision == Precision::kInput && !is_double) ? Precision::kFloat64
                                                                         : Precision::kDoubleDouble;
  }
  return next;
}

// The retry that the first pass most likely needs (more neighbours for the
// few cells that ran out), launched before the host has read how many cells
// failed: its kernels take the count from the device (core::DeviceCount).
// Without it the GPU would idle while the words travel and the host launches
// the retry, and a second read would follow.
//
// Its outcome stands for the round's whenever the failed cells fit its
// capacity; the loop then goes on from its settings. That is also what the
// loop would have run when the cells asked only for neighbours (the same
// settings and kernels: a small retry runs warp cells and warp kNN on the
// GPU, Exec::cooperative_cells); other asks are raised after it. When
// the cells overflow the capacity, it runs no cell at all and the loop
// retries as before. So the cells that a pass computes depend on counts,
// never on the order of the scan's appends.
struct Speculation {
  PassSettings pass{0, 0, Precision::kInput};
  int64_t capacity = 0;  // 0: none
};

// The speculative retry after the first pass `first` of `cells` cells: at
// most Options::speculative_cells cells (0: none), and at most the memory
// budget's worth of neighbours (but at least 1024 cells, as run_pass's chunks).
inline Speculation speculative_retry(const PassSettings& first, int64_t cells, int64_t largest_cloud,
                                     int64_t memory_budget, const Options& options) {
  const PassSettings more =
      escalated(first, RetryAsks{true, false, false}, largest_cloud, false, options.vertex_balls_k);
  if (more.vertex_balls || more.k <= first.k) return {};
  const int64_t by_budget = std::max<int64_t>(1024, memory_budget / (more.k * int64_t(sizeof(int32_t))));
  return {more, std::min({cells, options.speculative_cells, by_budget})};
}

// The speculative retry pass: kNN and clip of the cells of `cells` that
// `live` says are valid, with `pass`'s neighbours, at the first tier and in
// the points' precision (speculative_retry's settings).
template <typename Exec, typename io_t>
void run_speculative_pass(const at::Tensor& points, const at::Tensor& box,
                          const c10::optional<at::Tensor>& batch, const Grid& grid, const at::Tensor& cells,
                          const PassSettings& pass, c10::optional<double> neighbor_spread,
                          const core::DeviceCount& live, const Options& options, PositionOutputs& out) {
  TORCH_CHECK(pass.tier == 0 && pass.precision == Precision::kInput && !pass.vertex_balls,
              "torchvor: internal error: a speculative pass beyond the first tier");
  const int64_t m = cells.size(0);
  at::Tensor no_distances;
  at::Tensor neighbors = at::empty({m, pass.k}, points.options().dtype(at::kInt));
  run_knn<Exec, io_t, int32_t, true>(grid, points.data_ptr<io_t>(), /*queries_in_order=*/false,
                                     batch.has_value() ? batch->data_ptr<int64_t>() : nullptr,
                                     cells.data_ptr<int32_t>(), m, pass.k, /*exclude_self=*/true,
                                     /*row_by_query=*/false, Exec::kColumnMajorNeighbors,
                                     /*stream_rows=*/false, options.knn, no_distances, neighbors, live);
  clip_chunk_up_to_device_count<Exec, io_t>(points, box, batch, cells, neighbors, neighbor_spread, live, options,
                                            out);
}

}  // namespace ops
}  // namespace torchvor
