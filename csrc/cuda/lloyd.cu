#include <c10/cuda/CUDAGuard.h>
#include <torch/library.h>

#include "../ops/lloyd.h"
#include "exec.cuh"

namespace torchvor {
namespace cuda {

std::tuple<at::Tensor, at::Tensor> lloyd_move_cuda(const at::Tensor& points, const at::Tensor& order,
                                                   const at::Tensor& centroid, const at::Tensor& status,
                                                   const at::Tensor& lower, const at::Tensor& upper) {
  // Any CUDA argument routes the call here; a CPU `points` then fails the
  // device check with a clear message instead of a guard error.
  c10::cuda::OptionalCUDAGuard guard;
  if (points.is_cuda()) guard.set_device(points.device());
  return ops::lloyd_move_forward<CudaExec>(points, order, centroid, status, lower, upper);
}

TORCH_LIBRARY_IMPL(torchvor, CUDA, m) { m.impl("lloyd_move", &lloyd_move_cuda); }

}  // namespace cuda
}  // namespace torchvor
