#include <c10/cuda/CUDAGuard.h>
#include <torch/library.h>

#include "../ops/radius.h"
#include "exec.cuh"

namespace torchvor {
namespace cuda {

std::tuple<at::Tensor, at::Tensor, at::Tensor> radius_cuda(const at::Tensor& points, const at::Tensor& queries,
                                                           double r, const c10::optional<at::Tensor>& batch,
                                                           const c10::optional<at::Tensor>& query_batch,
                                                           bool exclude_self) {
  // Any CUDA argument routes the call here; a CPU `points` then fails the
  // device check with a clear message instead of a guard error.
  c10::cuda::OptionalCUDAGuard guard;
  if (points.is_cuda()) guard.set_device(points.device());
  return ops::radius_forward<CudaExec>(points, queries, r, batch, query_batch, exclude_self);
}

TORCH_LIBRARY_IMPL(torchvor, CUDA, m) { m.impl("radius", &radius_cuda); }

}  // namespace cuda
}  // namespace torchvor
