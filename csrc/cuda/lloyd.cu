#include <c10/cuda/CUDAGuard.h>
#include <torch/library.h>

#include "../ops/lloyd.h"
#include "exec.cuh"

// Compiled in voronoi.cu.
TORCHVOR_VORONOI_FORWARD(extern, torchvor::cuda::CudaExec);

namespace torchvor {
namespace cuda {

ops::LloydStepOutputs lloyd_step_cuda(const at::Tensor& points, const at::Tensor& box,
                                      const c10::optional<at::Tensor>& batch, c10::optional<int64_t> k,
                                      int64_t sample_stride, int64_t histogram_bins, int64_t memory_budget) {
  // Any CUDA argument routes the call here; a CPU `points` then fails the
  // device check with a clear message instead of a guard error.
  c10::cuda::OptionalCUDAGuard guard;
  if (points.is_cuda()) guard.set_device(points.device());
  return ops::lloyd_step_forward<CudaExec>(points, box, batch, k, sample_stride, histogram_bins, memory_budget);
}

TORCH_LIBRARY_IMPL(torchvor, CUDA, m) { m.impl("lloyd_step", &lloyd_step_cuda); }

}  // namespace cuda
}  // namespace torchvor
