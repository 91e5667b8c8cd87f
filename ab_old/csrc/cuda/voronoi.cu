#include <c10/cuda/CUDAGuard.h>
#include <torch/library.h>

#include "../ops/voronoi.h"
#include "exec.cuh"

namespace torchvor {
namespace cuda {

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> voronoi_cells_cuda(
    const at::Tensor& points, const at::Tensor& box, const c10::optional<at::Tensor>& batch,
    c10::optional<int64_t> k, int64_t memory_budget) {
  // Any CUDA argument routes the call here; a CPU `points` then fails the
  // device check with a clear message instead of a guard error.
  c10::cuda::OptionalCUDAGuard guard;
  if (points.is_cuda()) guard.set_device(points.device());
  return ops::voronoi_forward<CudaExec>(points, box, batch, k, memory_budget);
}

TORCH_LIBRARY_IMPL(torchvor, CUDA, m) { m.impl("voronoi_cells", &voronoi_cells_cuda); }

}  // namespace cuda
}  // namespace torchvor
