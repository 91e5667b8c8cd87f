#include <torch/library.h>

#include "../ops/lloyd.h"
#include "exec.h"

namespace torchvor {
namespace cpu {

std::tuple<at::Tensor, at::Tensor> lloyd_move_cpu(const at::Tensor& points, const at::Tensor& order,
                                                  const at::Tensor& centroid, const at::Tensor& status,
                                                  const at::Tensor& lower, const at::Tensor& upper) {
  return ops::lloyd_move_forward<CpuExec>(points, order, centroid, status, lower, upper);
}

TORCH_LIBRARY_IMPL(torchvor, CPU, m) { m.impl("lloyd_move", &lloyd_move_cpu); }

}  // namespace cpu
}  // namespace torchvor
