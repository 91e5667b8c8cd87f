#include <torch/library.h>

#include "../ops/lloyd.h"
#include "exec.h"

// Compiled in voronoi.cpp.
TORCHVOR_VORONOI_FORWARD(extern, torchvor::cpu::CpuExec);

namespace torchvor {
namespace cpu {

ops::LloydStepOutputs lloyd_step_cpu(const at::Tensor& points, const at::Tensor& box,
                                     const c10::optional<at::Tensor>& batch, c10::optional<int64_t> k,
                                     int64_t sample_stride, int64_t histogram_bins, int64_t memory_budget) {
  return ops::lloyd_step_forward<CpuExec>(points, box, batch, k, sample_stride, histogram_bins, memory_budget);
}

TORCH_LIBRARY_IMPL(torchvor, CPU, m) { m.impl("lloyd_step", &lloyd_step_cpu); }

}  // namespace cpu
}  // namespace torchvor
