#include <torch/library.h>

#include "../ops/radius.h"
#include "exec.h"

namespace torchvor {
namespace cpu {

std::tuple<at::Tensor, at::Tensor, at::Tensor> radius_cpu(const at::Tensor& points, const at::Tensor& queries,
                                                          double r, const c10::optional<at::Tensor>& batch,
                                                          const c10::optional<at::Tensor>& query_batch,
                                                          bool exclude_self) {
  return ops::radius_forward<CpuExec>(points, queries, r, batch, query_batch, exclude_self);
}

TORCH_LIBRARY_IMPL(torchvor, CPU, m) { m.impl("radius", &radius_cpu); }

}  // namespace cpu
}  // namespace torchvor
