// The pilot: a sample of cells that measures the first pass's k and how
// unequal the cells' work is.
#pragma once

#include <ATen/ATen.h>

#include <algorithm>
#include <cmath>
#include <limits>

#include "../core/common.h"
#include "cell_records.h"
#include "clip_pass.h"

namespace torchvor {
namespace ops {

// What a pilot measures: about 1000 cells spread over the grid order,
// computed with k = 64 (a larger pilot k costs latency), and the neighbours
// they needed:
// - `k`, their 98th percentile (Options::pilot_quantile) plus 2, the first
//   pass's k when the caller gives none: blue noise ~19, perturbed grids
//   ~50, white noise 66 (its 98th percentile is past the pilot's 64). Most
//   cells then succeed in one pass and the rest retry.
// - `neighbor_spread`, their standard deviation over their mean (each capped
//   at the pilot's k, as a cell that fails there reports it): how unequal
//   the cells' work is, by which the backend chooses a thread or a warp per
//   cell (Exec::cooperative_cells).
struct Pilot {
  int64_t k;
  double neighbor_spread;
};


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

// Runs the pilot's pass (`run`) on its sample of `positions` and measures it;
// `quantile` is the share of the sample's cells that the returned k covers.
template <typename Exec, typename io_t, typename Run>
Pilot run_pilot(const at::Tensor& positions, int64_t largest_cloud, double quantile, const Run& run,
                PositionOutputs& out) {
  const int64_t n = positions.size(0);
  const int64_t stride = std::max<int64_t>(1, n / 1024);
  const at::Tensor sample = positions.slice(0, 0, n, stride).contiguous();
  const int64_t pilot_k = std::min<int64_t>(64, largest_cloud);
  run(sample, PassSettings{pilot_k, 0, Precision::kInput}, c10::nullopt);
  // One small kernel and one read: the statistics of ~1000 integers in
  // neighbour counts up to pilot_k come from their histogram (torch's
  // quantile, mean and standard deviation would take ~25 launches, with the
  // device idle between them).
  const int32_t num_bins = static_cast<int32_t>(pilot_k) + 1;
  const at::Tensor bins = at::zeros({num_bins}, positions.options());
  Exec::for_each(sample.size(0), NeededHistogramFunctor<io_t>{sample.data_ptr<int32_t>(), out.data<io_t>(),
                                                              bins.data_ptr<int32_t>(), num_bins});
  const at::Tensor read = bins.to(at::kCPU);
  double at_quantile = 0.0, mean = 0.0, deviation = 0.0;
  needed_statistics(read.data_ptr<int32_t>(), num_bins, quantile, at_quantile, mean, deviation);
  const int64_t covered = static_cast<int64_t>(at_quantile);
  // A sample of one cell has no standard deviation (NaN): call it even.
  const double spread = (mean > 0 && std::isfinite(deviation)) ? deviation / mean : 0.0;
  return {std::min<int64_t>(256, std::max<int64_t>(8, covered + 2)), spread};
}

}  // namespace ops
}  // namespace torchvor
