#include <torch/library.h>

#include "../ops/knn.h"
#include "exec.h"

namespace torchvor {
namespace cpu {

std::tuple<at::Tensor, at::Tensor> knn_cpu(const at::Tensor& points, const at::Tensor& queries,
                                           int64_t k, const c10::optional<at::Tensor>& batch,
                                           const c10::optional<at::Tensor>& query_batch,
                                           bool exclude_self) {
  return ops::knn_forward<CpuExec>(points, queries, k, batch, query_batch, exclude_self);
}

TORCH_LIBRARY_IMPL(torchvor, CPU, m) { m.impl("knn", &knn_cpu); }

}  // namespace cpu
}  // namespace torchvor
