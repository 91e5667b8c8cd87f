#include <torch/library.h>

#include "../ops/voronoi.h"
#include "../ops/voronoi_graph.h"
#include "clip_on_host.h"
#include "exec.h"

// Compiled in clip_on_host_float.cpp and clip_on_host_double.cpp.
TORCHVOR_CLIPS_ON_HOST(extern);

// The one instantiation of this backend's passes, for the voronoi ops below
// and for lloyd.cpp's torchvor::lloyd_step.
TORCHVOR_VORONOI_FORWARD(, torchvor::cpu::CpuExec);

namespace torchvor {
namespace cpu {

ops::CallerOutputs voronoi_cells_cpu(
    const at::Tensor& points, const at::Tensor& box, const c10::optional<at::Tensor>& batch,
    c10::optional<int64_t> k, int64_t memory_budget, const c10::optional<at::Tensor>& rows) {
  return ops::voronoi_forward<CpuExec>(points, box, batch, k, memory_budget, false, {}, nullptr, rows).cells;
}

ops::GridOrderOutputs voronoi_cells_grid_order_cpu(
    const at::Tensor& points, const at::Tensor& box, const c10::optional<at::Tensor>& batch,
    c10::optional<int64_t> k, int64_t memory_budget) {
  const ops::VoronoiOutputs out = ops::voronoi_forward<CpuExec>(points, box, batch, k, memory_budget, true, {}, nullptr,
                                                                  c10::nullopt);
  return std::tuple_cat(out.cells, std::make_tuple(out.order));
}

ops::GraphOutputs voronoi_graph_cpu(const at::Tensor& points, const at::Tensor& box,
                                   const c10::optional<at::Tensor>& batch, c10::optional<int64_t> k,
                                   int64_t memory_budget, bool moments) {
  return ops::voronoi_graph_forward<CpuExec>(points, box, batch, k, memory_budget, moments);
}

at::Tensor voronoi_cells_backward_cpu(const at::Tensor& points, const at::Tensor& box,
                                      const c10::optional<at::Tensor>& batch, c10::optional<int64_t> k,
                                      int64_t memory_budget, const at::Tensor& upstream, bool moments) {
  return ops::voronoi_cells_backward<CpuExec>(points, box, batch, k, memory_budget, upstream, moments);
}

TORCH_LIBRARY_IMPL(torchvor, CPU, m) {
  m.impl("voronoi_cells", &voronoi_cells_cpu);
  m.impl("voronoi_graph", &voronoi_graph_cpu);
  m.impl("voronoi_cells_backward", &voronoi_cells_backward_cpu);
  m.impl("voronoi_cells_grid_order", &voronoi_cells_grid_order_cpu);
}

}  // namespace cpu
}  // namespace torchvor
