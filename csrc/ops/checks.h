// Argument checks of every op. They raise Python exceptions that name the
// argument: TORCH_CHECK_VALUE -> ValueError, TORCH_CHECK_TYPE -> TypeError.
//
// Defined once in checks.cpp, so both backends share one set of messages.
#pragma once

#include <ATen/ATen.h>

#include <cstdint>

namespace torchvor {
namespace ops {

// Validates the arguments of torchvor::knn; returns the number of batch
// elements (max of both batch vectors + 1, or 1 without batches).
int64_t check_knn_inputs(const at::Tensor& points, const at::Tensor& queries, int64_t k,
                         const c10::optional<at::Tensor>& points_batch,
                         const c10::optional<at::Tensor>& queries_batch, bool exclude_self);

// Validates the arguments of torchvor::voronoi_cells, including that every
// point lies inside its box.
void check_voronoi_inputs(const at::Tensor& points, const at::Tensor& box,
                          const c10::optional<at::Tensor>& batch, c10::optional<int64_t> k,
                          int64_t memory_budget);

}  // namespace ops
}  // namespace torchvor
