// torchvor::lloyd_move, shared by the CPU and CUDA backends: one Lloyd move
// of points whose cells came in grid order (voronoi_cells_grid_order).
#pragma once

#include <ATen/ATen.h>

#include <tuple>

#include "../core/common.h"
#include "../core/status.h"
#include "checks.h"

namespace torchvor {
namespace ops {

// Row i: the cell of points[order[i]]. Its point moves to the centroid,
// clamped into the box (rounding can put a boundary cell's centroid an ulp
// outside, which the next voronoi call would reject), unless the cell failed
// (not SUCCESS or DUPLICATE: NaN centroid), whose point stays. One pass where
// lloyd's tail was six tensor ops (a gather of the points into grid order,
// clamp, subtraction, norm, the failed cells' where): 0.6 ms at 10M points
// on an H100, and a launch each at 1M, where launches cost more host time
// than device time.
template <typename T>
struct LloydMoveFunctor {
  const T* points;         // (N, 3), the previous order
  const int64_t* order;    // (N,): row i is the cell of points[order[i]]
  const T* centroid;       // (N, 3), by row
  const int8_t* status;    // (N,), by row
  const T* lower;          // (1 or N, 3): the box of each row
  const T* upper;
  int64_t bounds_stride;   // 0 (one box) or 3
  int64_t n;
  T* moved;                // (N, 3), by row
  T* displacement2;        // (N,) |moved - point|^2

  TV_HD void operator()(int64_t i) const {
    const int64_t row = order[i];
    const T nan = T(0) / T(0);
    if (row < 0 || row >= n) {  // not a permutation: NaN, never a read out of bounds
      moved[3 * i] = moved[3 * i + 1] = moved[3 * i + 2] = displacement2[i] = nan;
      return;
    }
    const int8_t code = status[i];
    const bool stays = code != core::kSuccess && code != core::kDuplicate;
    const T* lo = lower + i * bounds_stride;
    const T* hi = upper + i * bounds_stride;
    T sum = T(0);
    for (int a = 0; a < 3; ++a) {
      const T point = points[3 * row + a];
      const T c = centroid[3 * i + a];  // clamped as torch.clamp: NaN stays NaN
      const T to = stays ? point : (c < lo[a] ? lo[a] : (c > hi[a] ? hi[a] : c));
      moved[3 * i + a] = to;
      sum += (to - point) * (to - point);
    }
    displacement2[i] = sum;
  }
};

template <typename Exec>
std::tuple<at::Tensor, at::Tensor> lloyd_move_forward(const at::Tensor& points_in, const at::Tensor& order_in,
                                                      const at::Tensor& centroid_in, const at::Tensor& status_in,
                                                      const at::Tensor& lower_in, const at::Tensor& upper_in) {
  check_lloyd_move_inputs(points_in, order_in, centroid_in, status_in, lower_in, upper_in);
  const at::Tensor points = points_in.contiguous(), order = order_in.contiguous();
  const at::Tensor centroid = centroid_in.contiguous(), status = status_in.contiguous();
  const at::Tensor lower = lower_in.contiguous(), upper = upper_in.contiguous();
  const int64_t n = points.size(0);
  const at::Tensor moved = Exec::empty({n, 3}, points.options());
  const at::Tensor displacement2 = Exec::empty({n}, points.options());
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "torchvor::lloyd_move", [&] {
    Exec::for_each(n, LloydMoveFunctor<scalar_t>{
                          points.data_ptr<scalar_t>(), order.data_ptr<int64_t>(), centroid.data_ptr<scalar_t>(),
                          status.data_ptr<int8_t>(), lower.data_ptr<scalar_t>(), upper.data_ptr<scalar_t>(),
                          lower.size(0) == 1 ? 0 : 3, n, moved.data_ptr<scalar_t>(),
                          displacement2.data_ptr<scalar_t>()});
  });
  return {moved, displacement2};
}

}  // namespace ops
}  // namespace torchvor
