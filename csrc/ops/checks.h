// Argument checks shared by every op. They raise Python exceptions that name
// the argument: TORCH_CHECK_VALUE -> ValueError, TORCH_CHECK_TYPE -> TypeError.
#pragma once

#include <ATen/ATen.h>

#include <string>

namespace torchvor {
namespace ops {

// "(20, 2)": formatted by hand because streaming c10::IntArrayRef from code
// compiled by nvcc crashed on the GPU machine (torch 2.11, nvcc 13.0).
inline std::string shape_string(const at::Tensor& t) {
  std::string text = "(";
  for (int64_t d = 0; d < t.dim(); ++d) {
    if (d > 0) text += ", ";
    text += std::to_string(t.size(d));
  }
  return text + (t.dim() == 1 ? ",)" : ")");
}

inline void check_points(const at::Tensor& points, const char* name) {
  TORCH_CHECK_TYPE(points.scalar_type() == at::kFloat || points.scalar_type() == at::kDouble,
                   "torchvor: ", name, " must be float32 or float64, got ",
                   c10::toString(points.scalar_type()));
  TORCH_CHECK_VALUE(points.dim() == 2 && points.size(1) == 3, "torchvor: ", name,
                    " must have shape (N, 3), got ", shape_string(points));
  TORCH_CHECK_VALUE(points.size(0) < (int64_t(1) << 31) - 1, "torchvor: ", name,
                    " has too many points (at most 2^31 - 2)");
}

inline void check_finite(const at::Tensor& points, const char* name) {
  if (points.numel() == 0) return;
  TORCH_CHECK_VALUE(at::isfinite(points).all().item<bool>(), "torchvor: ", name,
                    " contains NaN or Inf coordinates");
}

inline void check_same_device(const at::Tensor& a, const char* a_name, const at::Tensor& b,
                              const char* b_name) {
  // Device::str(), not operator<<: streaming c10 types from nvcc-compiled code
  // crashed on the GPU machine (see shape_string).
  TORCH_CHECK_VALUE(a.device() == b.device(), "torchvor: ", b_name, " is on ", b.device().str(),
                    " but ", a_name, " is on ", a.device().str());
}

// A batch vector (PyG convention): int64, shape (n,), sorted, non-negative.
// Returns the number of batch elements it implies (max + 1; 1 if undefined).
inline int64_t check_batch(const c10::optional<at::Tensor>& batch, int64_t n, const at::Tensor& like,
                           const char* name) {
  if (!batch.has_value()) return 1;
  const at::Tensor& b = *batch;
  TORCH_CHECK_TYPE(b.scalar_type() == at::kLong, "torchvor: ", name, " must be int64, got ",
                   c10::toString(b.scalar_type()));
  TORCH_CHECK_VALUE(b.dim() == 1 && b.size(0) == n, "torchvor: ", name, " must have shape (",
                    n, ",), got ", shape_string(b));
  check_same_device(like, "points", b, name);
  if (n == 0) return 1;
  TORCH_CHECK_VALUE(b.min().item<int64_t>() >= 0, "torchvor: ", name,
                    " must be non-negative");
  if (n > 1) {
    TORCH_CHECK_VALUE((b.slice(0, 1) >= b.slice(0, 0, n - 1)).all().item<bool>(), "torchvor: ",
                      name, " must be sorted in non-decreasing order");
  }
  return b[n - 1].item<int64_t>() + 1;
}

}  // namespace ops
}  // namespace torchvor
