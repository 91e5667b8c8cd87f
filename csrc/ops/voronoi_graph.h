// torchvor::voronoi_graph, shared by the CPU and CUDA backends: the faces
// that voronoi_forward's passes wrote (GraphFaces), as a graph in the
// caller's rows.
#pragma once

#include <ATen/ATen.h>

#include <tuple>

#include "voronoi.h"

namespace torchvor {
namespace ops {

using GraphOutputs = std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor,
                                at::Tensor, at::Tensor>;

// The faces as edges j -> i (row 0 the neighbour j, row 1 the cell i),
// sorted by i then j, every face in both directions. Cells i and j compute
// their shared face apart: where both found it, each direction gets the
// mean of their areas and the area-weighted mean of their centroids; a face
// only one of them found (one near the area floor, core::FaceAreaFloor) is
// kept in both directions with that cell's values.
inline std::tuple<at::Tensor, at::Tensor, at::Tensor> symmetric_edges(const at::Tensor& cell, const at::Tensor& neighbor,
                                                                      const at::Tensor& area, const at::Tensor& centroid,
                                                                      int64_t n) {
  // Each cell's faces are one range in row order: sorting by (i, j) orders
  // them within it.
  const auto sorted_by_key = [n](const at::Tensor& i, const at::Tensor& j, const at::Tensor& a, const at::Tensor& c) {
    const at::Tensor key = i * n + j;
    const at::Tensor order = std::get<1>(key.sort());
    return std::make_tuple(key.index_select(0, order), a.index_select(0, order), c.index_select(0, order));
  };
  auto [key, a, c] = sorted_by_key(cell, neighbor, area, centroid);
  const int64_t edges = key.numel();
  if (edges == 0) return {key, a, c};
  const at::Tensor i = key.div(n, "floor"), j = key.remainder(n);
  const at::Tensor reverse = j * n + i;
  const at::Tensor at_reverse = at::searchsorted(key, reverse).clamp_max(edges - 1);
  const at::Tensor matched = key.index_select(0, at_reverse).eq(reverse);
  const at::Tensor other_area = at::where(matched, a.index_select(0, at_reverse), at::zeros_like(a));
  const at::Tensor other_centroid = c.index_select(0, at_reverse);
  const at::Tensor total = a + other_area;
  const at::Tensor mean_centroid =
      (a.unsqueeze(1) * c + other_area.unsqueeze(1) * other_centroid) / total.unsqueeze(1);
  const at::Tensor both = matched.unsqueeze(1);
  c = at::where(both, mean_centroid, c);
  a = at::where(matched, total * 0.5, a);
  const at::Tensor lonely = matched.logical_not().nonzero().squeeze(1);
  if (lonely.numel() > 0) {  // mirror them, then merge
    auto [merged_key, merged_area, merged_centroid] =
        sorted_by_key(at::cat({i, j.index_select(0, lonely)}), at::cat({j, i.index_select(0, lonely)}),
                      at::cat({a, a.index_select(0, lonely)}), at::cat({c, c.index_select(0, lonely)}));
    return {merged_key, merged_area, merged_centroid};
  }
  return {key, a, c};
}

// The op's outputs: the cells (voronoi_cells'), then edge_index (2, E)
// int64, area (E,), face centroid (E, 3) and wall_area (N, 6).
template <typename Exec>
GraphOutputs voronoi_graph_forward(const at::Tensor& points, const at::Tensor& box,
                                   const c10::optional<at::Tensor>& batch, c10::optional<int64_t> k,
                                   int64_t memory_budget) {
  GraphFaces graph;
  const VoronoiOutputs cells = voronoi_forward<Exec>(points, box, batch, k, memory_budget, false, {}, &graph);
  const int64_t n = points.size(0);
  const at::TensorOptions longs = points.options().dtype(at::kLong);
  const FaceTensors& faces = graph.faces;
  at::Tensor edge_index = at::empty({2, 0}, longs), area = faces.area, centroid = faces.centroid;
  at::Tensor wall_area = at::zeros({n, 6}, points.options());
  if (n > 0) {
    const at::Tensor row_of_position = graph.row_of_position.to(at::kLong);
    wall_area.index_copy_(0, row_of_position, faces.wall_area);
    // The faces lie in the caller's row order (face_layout): cell row r has
    // its count's range.
    const at::Tensor count_by_row = at::zeros({n}, longs).index_copy_(0, row_of_position, faces.count.to(at::kLong));
    const at::Tensor cell = at::repeat_interleave(count_by_row);
    const at::Tensor neighbor = row_of_position.index_select(0, faces.neighbor.to(at::kLong));
    auto [key, symmetric_area, symmetric_centroid] = symmetric_edges(cell, neighbor, faces.area, faces.centroid, n);
    edge_index = at::stack({key.remainder(n), key.div(n, "floor")});
    area = symmetric_area;
    centroid = symmetric_centroid;
  }
  const auto& [volume, cell_centroid, second_moment, status, neighbors_needed] = cells.cells;
  return {volume, cell_centroid, second_moment, status, neighbors_needed, edge_index, area, centroid, wall_area};
}

}  // namespace ops
}  // namespace torchvor
