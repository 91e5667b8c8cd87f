// torchvor::lloyd_step, shared by the CPU and CUDA backends: one Lloyd
// iteration in one op. The cells come in grid order (voronoi_forward with
// grid_order), every point moves to its cell's centroid, and what
// torchvor.lloyd reads of the step (the energy, the largest move, the
// neighbours the cells needed) is launched on the outputs before the passes'
// status read (LaunchOnOutputs): the host waits for one read a step, where
// the voronoi op, then the move and its sums from Python, waited for two,
// with the device idle while the host launched the tail between them.
#pragma once

#include <ATen/ATen.h>

#include <memory>
#include <tuple>

#include "../core/common.h"
#include "../core/status.h"
#include "checks.h"
#include "voronoi.h"

namespace torchvor {
namespace ops {

// Position i (the grid order) is the cell of points[order[i]]. Its point
// moves to the centroid, clamped into its box (rounding can put a boundary
// cell's centroid an ulp outside, which the next step would reject), unless
// the cell failed (not SUCCESS or DUPLICATE: NaN centroid), whose point
// stays. The displacement is measured in float64, relative to the box's
// diagonal (a float32 square overflows for coordinates past ~1e19).
template <typename T>
struct LloydMoveFunctor {
  const T* points;         // (N, 3), the caller's rows
  const int64_t* order;    // (N,): position i is the cell of points[order[i]], a permutation
  const T* centroid;       // (N, 3), by position
  const int8_t* status;    // (N,), by position
  const T* box;            // (B, 2, 3)
  const int64_t* batch;    // (N,), the batch element of each caller's row; nullptr or B == 1: one box
  T* moved;                // (N, 3), by position
  double* displacement2;   // (N,), by position: |moved - point|^2 / |hi - lo|^2

  TV_HD void operator()(int64_t i) const {
    const int64_t row = order[i];
    const T* lo = box + 6 * (batch != nullptr ? batch[row] : 0);
    const T* hi = lo + 3;
    const int8_t code = status[i];
    const bool stays = code != core::kSuccess && code != core::kDuplicate;
    double moved2 = 0.0, diagonal2 = 0.0;
    for (int a = 0; a < 3; ++a) {
      const T point = points[3 * row + a];
      const T c = centroid[3 * i + a];
      const T to = stays ? point : (c < lo[a] ? lo[a] : (c > hi[a] ? hi[a] : c));
      moved[3 * i + a] = to;
      const double step = double(to) - double(point);
      const double side = double(hi[a]) - double(lo[a]);
      moved2 += step * step;
      diagonal2 += side * side;
    }
    // A box of one point (lo == hi) holds its points still: 0, not 0 / 0.
    displacement2[i] = diagonal2 > 0.0 ? moved2 / diagonal2 : 0.0;
  }
};

// bins[c] counts the sampled positions (every `stride`-th) whose cells
// needed c neighbours, the last bin also those that needed exactly
// num_bins; counts past that or below 0 are left out (as torch.histc over
// [0, num_bins] with num_bins bins). torchvor.lloyd takes the next step's k
// from its quantile: a strided sample, as ~10 busy bins contended by every
// cell would serialise the atomic adds.
struct StridedHistogramFunctor {
  const int32_t* needed;  // (N,) the neighbours each cell needed
  int64_t stride;
  int32_t* bins;          // (num_bins,), zeroed
  int32_t num_bins;

  TV_HD void operator()(int64_t i) const {
    const int32_t count = needed[i * stride];
    if (count >= 0 && count <= num_bins) core::atomic_increment(bins + core::min_of(count, num_bins - 1));
  }
};

using LloydStepOutputs = std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor,
                                    at::Tensor, at::Tensor, at::Tensor>;

// torchvor::lloyd_step (registration.cpp has the schema). The measures
// and the histogram are read from the device once, with the passes' last
// status read when no pass follows the first (LaunchOnOutputs).
template <typename Exec>
LloydStepOutputs lloyd_step_forward(const at::Tensor& points_in, const at::Tensor& box_in,
                                    const c10::optional<at::Tensor>& batch_in, c10::optional<int64_t> k,
                                    int64_t sample_stride, int64_t histogram_bins, int64_t memory_budget) {
  check_lloyd_step_inputs(sample_stride, histogram_bins);
  const at::Tensor points = points_in.contiguous();
  const at::Tensor box = box_in.contiguous();
  const c10::optional<at::Tensor> batch =
      batch_in.has_value() ? c10::optional<at::Tensor>(batch_in->contiguous()) : c10::nullopt;
  const int64_t n = points.size(0);
  at::Tensor moved;
  std::unique_ptr<typename Exec::HostRead> summary_read;
  // Launched by voronoi_forward once the outputs are complete (the inputs
  // are checked by then); a second launch replaces the first's results.
  const auto launch_tail = [&](const VoronoiOutputs& cells) {
    moved.reset();  // an earlier launch's, no longer wanted: not held beside the new one
    const at::Tensor& centroid = std::get<1>(cells.cells);
    const at::Tensor& second_moment = std::get<2>(cells.cells);
    const at::Tensor& status = std::get<3>(cells.cells);
    const at::Tensor& neighbors = std::get<4>(cells.cells);
    moved = Exec::empty({n, 3}, points.options());
    const at::Tensor displacement2 = Exec::empty({n}, points.options().dtype(at::kDouble));
    // (energy, largest displacement2) in float64, then the histogram's int32
    // bins, two a float64 word, so that one copy reads all.
    const at::Tensor summary = at::zeros({2 + (histogram_bins + 1) / 2}, points.options().dtype(at::kDouble));
    const bool one_box = !batch.has_value() || box.size(0) == 1;  // one box for every cloud
    AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "torchvor::lloyd_step", [&] {
      Exec::for_each(n, LloydMoveFunctor<scalar_t>{
                            points.data_ptr<scalar_t>(), cells.order.data_ptr<int64_t>(),
                            centroid.data_ptr<scalar_t>(), status.data_ptr<int8_t>(), box.data_ptr<scalar_t>(),
                            one_box ? nullptr : batch->data_ptr<int64_t>(), moved.data_ptr<scalar_t>(),
                            displacement2.data_ptr<double>()});
    });
    if (n > 0) {  // an empty reduction is an error; the zeros stand
      at::Tensor energy = summary.select(0, 0), largest = summary.select(0, 1);
      at::sum_out(energy, second_moment, {0}, /*keepdim=*/false, at::kDouble);
      at::amax_out(largest, displacement2, {0}, /*keepdim=*/false);
      const at::Tensor bins = summary.slice(0, 2).view(at::kInt);
      Exec::for_each((n + sample_stride - 1) / sample_stride,
                     StridedHistogramFunctor{neighbors.data_ptr<int32_t>(), sample_stride, bins.data_ptr<int32_t>(),
                                             static_cast<int32_t>(histogram_bins)});
    }
    summary_read = std::make_unique<typename Exec::HostRead>(summary);
  };
  const VoronoiOutputs cells = voronoi_forward<Exec>(points, box, batch, k, memory_budget, true, launch_tail, nullptr,
                                                     c10::nullopt);
  const at::Tensor read = summary_read->wait();
  // The first pass's k joins the measures on the host (the pilot's choice,
  // where k was None: torchvor.lloyd's history reports it).
  at::Tensor measures = at::empty({3}, at::TensorOptions().dtype(at::kDouble));
  measures.slice(0, 0, 2).copy_(read.slice(0, 0, 2));
  measures.data_ptr<double>()[2] = static_cast<double>(cells.first_pass_k);
  const at::Tensor histogram = read.slice(0, 2).view(at::kInt).slice(0, 0, histogram_bins).clone();
  const auto& [volume, centroid, second_moment, status, neighbors, radius] = cells.cells;
  return {moved, volume, centroid, second_moment, status, neighbors, radius, cells.order, measures, histogram};
}

}  // namespace ops
}  // namespace torchvor
