#include <c10/cuda/CUDAGuard.h>
#include <torch/library.h>

#include "../ops/power.h"
#include "exec.cuh"

namespace torchvor {
namespace cuda {

ops::PowerCellsAndFaces power_cells_cuda(const at::Tensor& points, const at::Tensor& weights, const at::Tensor& box,
                                         const c10::optional<at::Tensor>& batch, const at::Tensor& rows,
                                         const at::Tensor& weight_max, int64_t tier, int64_t face_room) {
  c10::cuda::OptionalCUDAGuard guard;
  if (points.is_cuda()) guard.set_device(points.device());
  return ops::power_cells<CudaExec>(points, weights, box, batch, rows, weight_max, tier, face_room);
}

ops::PowerFaceOutputs power_faces_cuda(const at::Tensor& points, const at::Tensor& weights, const at::Tensor& box,
                                       const c10::optional<at::Tensor>& batch, const at::Tensor& rows,
                                       const at::Tensor& weight_max, int64_t tier,
                                       const at::Tensor& face_offsets) {
  c10::cuda::OptionalCUDAGuard guard;
  if (points.is_cuda()) guard.set_device(points.device());
  return ops::power_faces<CudaExec>(points, weights, box, batch, rows, weight_max, tier, face_offsets);
}

TORCH_LIBRARY_IMPL(torchvor, CUDA, m) {
  m.impl("power_cells", &power_cells_cuda);
  m.impl("power_faces", &power_faces_cuda);
}

}  // namespace cuda
}  // namespace torchvor
