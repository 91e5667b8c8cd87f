#include <c10/cuda/CUDAGuard.h>
#include <torch/library.h>

#include "../ops/knn.h"
#include "exec.cuh"

namespace torchvor {
namespace cuda {

std::tuple<at::Tensor, at::Tensor> knn_cuda(const at::Tensor& points, const at::Tensor& queries,
                                            int64_t k, const c10::optional<at::Tensor>& batch,
                                            const c10::optional<at::Tensor>& query_batch,
                                            bool exclude_self) {
  // Any CUDA argument routes the call here; a CPU `points` then fails the
  // device check with a clear message instead of a guard error.
  c10::cuda::OptionalCUDAGuard guard;
  if (points.is_cuda()) guard.set_device(points.device());
  return ops::knn_forward<CudaExec>(points, queries, k, batch, query_batch, exclude_self);
}

TORCH_LIBRARY_IMPL(torchvor, CUDA, m) { m.impl("knn", &knn_cuda); }

}  // namespace cuda
}  // namespace torchvor
