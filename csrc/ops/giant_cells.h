// The cells that overflow even the largest tier of recovery, finished on the
// host without a bound on their planes (core::UnboundedCell).
#pragma once

#include <ATen/ATen.h>

#include "cell_records.h"

namespace torchvor {
namespace ops {

// Of `cells` (positions, int32, on the points' device), those whose status
// says that their arrays overflowed are recomputed on the host as unbounded
// cells, in double-double with exact predicates, against every point of their
// cloud nearest first (the nearest 65,536, then four times more until the
// radius of security). Their records and statuses in `out` are replaced.
// `points`, `batch` by position; `box` (B, 2, 3). Returns how many it computed.
int64_t finish_giant_cells(const at::Tensor& points, const at::Tensor& box, const c10::optional<at::Tensor>& batch,
                           const at::Tensor& cells, PositionOutputs& out);

}  // namespace ops
}  // namespace torchvor
