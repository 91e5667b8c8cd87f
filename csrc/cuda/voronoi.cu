#include <c10/cuda/CUDAGuard.h>
#include <torch/library.h>

#include "../cpu/clip_on_host.h"
#include "../ops/voronoi.h"
#include "../ops/voronoi_graph.h"
#include "clip_tiers.cuh"
#include "exec.cuh"

// Compiled in clip_*.cu and, for the host's clips, cpu/clip_on_host_*.cpp.
TORCHVOR_CLIP_CHUNK_TIERS(extern);
TORCHVOR_CLIPS_ON_HOST(extern);

// The one instantiation of this backend's passes, for the voronoi ops below
// and for lloyd.cu's torchvor::lloyd_step.
TORCHVOR_VORONOI_FORWARD(, torchvor::cuda::CudaExec);

namespace torchvor {
namespace cuda {

ops::VoronoiOutputs voronoi_forward_cuda(const at::Tensor& points, const at::Tensor& box,
                                         const c10::optional<at::Tensor>& batch, c10::optional<int64_t> k,
                                         int64_t memory_budget, bool grid_order,
                                         const c10::optional<at::Tensor>& rows = c10::nullopt) {
  // Any CUDA argument routes the call here; a CPU `points` then fails the
  // device check with a clear message instead of a guard error.
  c10::cuda::OptionalCUDAGuard guard;
  if (points.is_cuda()) guard.set_device(points.device());
  return ops::voronoi_forward<CudaExec>(points, box, batch, k, memory_budget, grid_order, {}, nullptr, rows);
}

ops::CallerOutputs voronoi_cells_cuda(
    const at::Tensor& points, const at::Tensor& box, const c10::optional<at::Tensor>& batch,
    c10::optional<int64_t> k, int64_t memory_budget, const c10::optional<at::Tensor>& rows) {
  return voronoi_forward_cuda(points, box, batch, k, memory_budget, false, rows).cells;
}

ops::GridOrderOutputs voronoi_cells_grid_order_cuda(
    const at::Tensor& points, const at::Tensor& box, const c10::optional<at::Tensor>& batch,
    c10::optional<int64_t> k, int64_t memory_budget) {
  const ops::VoronoiOutputs out = voronoi_forward_cuda(points, box, batch, k, memory_budget, true);
  return std::tuple_cat(out.cells, std::make_tuple(out.order));
}

ops::GraphOutputs voronoi_graph_cuda(const at::Tensor& points, const at::Tensor& box,
                                    const c10::optional<at::Tensor>& batch, c10::optional<int64_t> k,
                                    int64_t memory_budget, bool moments) {
  c10::cuda::OptionalCUDAGuard guard;
  if (points.is_cuda()) guard.set_device(points.device());
  return ops::voronoi_graph_forward<CudaExec>(points, box, batch, k, memory_budget, moments);
}

at::Tensor voronoi_cells_backward_cuda(const at::Tensor& points, const at::Tensor& box,
                                       const c10::optional<at::Tensor>& batch, c10::optional<int64_t> k,
                                       int64_t memory_budget, const at::Tensor& upstream, bool moments) {
  c10::cuda::OptionalCUDAGuard guard;
  if (points.is_cuda()) guard.set_device(points.device());
  return ops::voronoi_cells_backward<CudaExec>(points, box, batch, k, memory_budget, upstream, moments);
}

TORCH_LIBRARY_IMPL(torchvor, CUDA, m) {
  m.impl("voronoi_cells", &voronoi_cells_cuda);
  m.impl("voronoi_graph", &voronoi_graph_cuda);
  m.impl("voronoi_cells_backward", &voronoi_cells_backward_cuda);
  m.impl("voronoi_cells_grid_order", &voronoi_cells_grid_order_cuda);
}

}  // namespace cuda
}  // namespace torchvor
