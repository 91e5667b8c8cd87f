// torchvor::voronoi_graph, shared by the CPU and CUDA backends: the faces
// that voronoi_forward's passes wrote (GraphFaces), as a graph in the
// caller's rows.
#pragma once

#include <ATen/ATen.h>

#include <tuple>
#include <vector>

#include "voronoi.h"

namespace torchvor {
namespace ops {

using GraphOutputs = std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor,
                                at::Tensor, at::Tensor, at::Tensor, at::Tensor>;

// The graph's edges j -> i, sorted by i then j, every face both ways.
struct Edges {
  at::Tensor edge_index;  // (2, E) int64: row 0 the neighbour j, row 1 the cell i
  at::Tensor area;        // (E,)
  at::Tensor centroid;    // (E, 3)
  at::Tensor moments;     // (E, 9), or empty without moments
};

// Each cell row r's faces, at [from[r], from[r] + count) of the passes'
// arrays (count = first[r + 1] - first[r]), as edges [first[r], first[r + 1]):
// the edges' cell rows, and their neighbours' rows from their positions.
struct EdgeRowsFunctor {
  const int64_t* from;
  const int64_t* first;     // (n + 1,)
  const int32_t* row_of_position;
  const int32_t* neighbor;  // the passes' (by face) positions
  int32_t* cell_row;        // (E,)
  int32_t* neighbor_row;    // (E,)

  TV_HD void operator()(int64_t r) const {
    const int64_t begin = first[r], count = first[r + 1] - begin;
    for (int64_t f = 0; f < count; ++f) {
      cell_row[begin + f] = static_cast<int32_t>(r);
      neighbor_row[begin + f] = row_of_position[neighbor[from[r] + f]];
    }
  }
};

// Edge e to its place in its cell's range sorted by neighbour row: its rank
// there (the rows in a range are distinct), its columns (area, centroid,
// moments) moved along from the passes' arrays.
template <typename io_t>
struct SortEdgesFunctor {
  const int64_t* from;
  const int64_t* first;  // (n + 1,)
  const int32_t* cell_row;
  const int32_t* neighbor_row;
  const io_t* area;      // the passes' (by face)
  const io_t* centroid;  // 3 a face
  const io_t* moments;   // 9 a face, or nullptr
  int64_t columns;       // 4, or 13 with moments
  int32_t* sorted_neighbor;
  io_t* sorted_values;   // (E, columns)

  TV_HD void operator()(int64_t e) const {
    const int32_t r = cell_row[e], j = neighbor_row[e];
    const int64_t begin = first[r], end = first[r + 1];
    int64_t to = begin;
    for (int64_t other = begin; other < end; ++other) to += neighbor_row[other] < j ? 1 : 0;
    const int64_t f = from[r] + (e - begin);
    sorted_neighbor[to] = j;
    io_t* values = sorted_values + to * columns;
    values[0] = area[f];
    for (int c = 0; c < 3; ++c) values[1 + c] = centroid[3 * f + c];
    for (int64_t c = 4; c < columns; ++c) values[c] = moments[9 * f + c - 4];
  }
};

// The reverse of each edge j -> i: i's place in j's sorted range
// [first[j], first[j + 1]), or -1.
struct ReverseEdgeFunctor {
  const int64_t* first;  // (n + 1,)
  const int32_t* cell_row;
  const int32_t* neighbor;  // sorted within each range
  int64_t* reverse;

  TV_HD void operator()(int64_t e) const {
    const int32_t i = cell_row[e], j = neighbor[e];
    const int64_t end = first[j + 1];
    int64_t lo = first[j], hi = end;  // the first entry >= i in [lo, hi)
    while (lo < hi) {
      const int64_t mid = lo + (hi - lo) / 2;
      if (neighbor[mid] < i) {
        lo = mid + 1;
      } else {
        hi = mid;
      }
    }
    reverse[e] = lo < end && neighbor[lo] == i ? lo : -1;
  }
};

// Edge e's values made symmetric with its reverse r (where one exists): the
// mean of the two cells' area and moments, their centroids weighted by area;
// written to the outputs with the edge's rows (products rounded alone, as
// by separate tensor operations, on both backends).
template <typename io_t>
struct SymmetricEdgeFunctor {
  const io_t* sorted;  // (E, columns): area, centroid, moments, each cell's own view
  int64_t columns;
  const int64_t* reverse;
  const int32_t* cell_row;
  const int32_t* neighbor_row;
  int64_t edges;
  int64_t* edge_index;  // (2, E)
  io_t* area;           // (E,)
  io_t* centroid;       // (E, 3)
  io_t* moments;        // (E, columns - 4), or nullptr

  TV_HD void operator()(int64_t e) const {
    const io_t* own = sorted + e * columns;
    const io_t* other = reverse[e] >= 0 ? sorted + reverse[e] * columns : own;
    const io_t a = own[0], b = other[0];
    edge_index[e] = neighbor_row[e];
    edge_index[edges + e] = cell_row[e];
    area[e] = (a + b) * io_t(0.5);
    for (int c = 0; c < 3; ++c) {
      centroid[3 * e + c] = reverse[e] >= 0 ? (core::mul_rn(a, own[1 + c]) + core::mul_rn(b, other[1 + c])) / (a + b)
                                            : own[1 + c];
    }
    if (moments != nullptr) {
      for (int64_t c = 4; c < columns; ++c) moments[(columns - 4) * e + c - 4] = (own[c] + other[c]) * io_t(0.5);
    }
  }
};

// The faces as edges j -> i (row 0 the neighbour j, row 1 the cell i),
// sorted by i then j, every face in both directions. Cells i and j compute
// their shared face apart: where both found it, each direction gets the
// mean of their areas and of their moments, and their centroids weighted by
// area (SymmetricEdgeFunctor); a face only one of them found (one near the
// area floor, core::FaceAreaFloor) is kept in both directions with that
// cell's values. Cell row r's faces are at [from[r], from[r] + count) of
// the passes' arrays (FaceTensors), and become edges [first[r], first[r +
// 1]) (first: (n + 1,), the counts' exclusive sum and E, the edges in all).
template <typename Exec, typename io_t>
Edges symmetric_edges(const at::Tensor& from, const at::Tensor& first, int64_t edges,
                      const at::Tensor& row_of_position, const FaceTensors& faces, int64_t n, bool moments) {
  const int64_t columns = moments ? 13 : 4;
  const at::Tensor& neighbor = faces.neighbor;
  const at::TensorOptions values = faces.area.options();
  const at::TensorOptions ints = neighbor.options().dtype(at::kInt);
  const at::Tensor cell_row = Exec::empty({edges}, ints), neighbor_row = Exec::empty({edges}, ints);
  Exec::for_each(n, EdgeRowsFunctor{from.data_ptr<int64_t>(), first.data_ptr<int64_t>(),
                                    row_of_position.data_ptr<int32_t>(), neighbor.data_ptr<int32_t>(),
                                    cell_row.data_ptr<int32_t>(), neighbor_row.data_ptr<int32_t>()});
  const at::Tensor sorted_neighbor = Exec::empty({edges}, ints), sorted = Exec::empty({edges, columns}, values);
  Exec::for_each(edges, SortEdgesFunctor<io_t>{from.data_ptr<int64_t>(), first.data_ptr<int64_t>(),
                                               cell_row.data_ptr<int32_t>(), neighbor_row.data_ptr<int32_t>(),
                                               faces.area.data_ptr<io_t>(), faces.centroid.data_ptr<io_t>(),
                                               moments ? faces.moments.data_ptr<io_t>() : nullptr, columns,
                                               sorted_neighbor.data_ptr<int32_t>(), sorted.data_ptr<io_t>()});
  const at::Tensor reverse = Exec::empty({edges}, neighbor.options().dtype(at::kLong));
  Exec::for_each(edges, ReverseEdgeFunctor{first.data_ptr<int64_t>(),
                                           cell_row.data_ptr<int32_t>(), sorted_neighbor.data_ptr<int32_t>(),
                                           reverse.data_ptr<int64_t>()});
  Edges out{Exec::empty({2, edges}, neighbor.options().dtype(at::kLong)), Exec::empty({edges}, values),
            Exec::empty({edges, 3}, values), Exec::empty({moments ? edges : 0, columns - 4}, values)};
  Exec::for_each(edges, SymmetricEdgeFunctor<io_t>{sorted.data_ptr<io_t>(), columns, reverse.data_ptr<int64_t>(),
                                                   cell_row.data_ptr<int32_t>(), sorted_neighbor.data_ptr<int32_t>(),
                                                   edges, out.edge_index.data_ptr<int64_t>(), out.area.data_ptr<io_t>(),
                                                   out.centroid.data_ptr<io_t>(),
                                                   moments ? out.moments.data_ptr<io_t>() : nullptr});
  const at::Tensor lonely = reverse.lt(0).nonzero().squeeze(1);
  if (lonely.numel() == 0) return out;
  // Mirror the faces only one cell found, then merge (rare: a full sort).
  const at::Tensor key = out.edge_index[1] * n + out.edge_index[0];
  const at::Tensor mirrored = out.edge_index[0].index_select(0, lonely) * n + out.edge_index[1].index_select(0, lonely);
  const at::Tensor order = std::get<1>(at::cat({key, mirrored}).sort());
  const auto merged = [&](const at::Tensor& t, int64_t dim) {
    return at::cat({t, t.index_select(dim, lonely)}, dim).index_select(dim, order);
  };
  const at::Tensor edge_index =
      at::cat({out.edge_index, out.edge_index.flip(0).index_select(1, lonely)}, 1).index_select(1, order);
  return {edge_index, merged(out.area, 0), merged(out.centroid, 0), moments ? merged(out.moments, 0) : out.moments};
}

// The op's outputs: the cells (voronoi_cells'), then edge_index (2, E)
// int64, area (E,), face centroid (E, 3), wall_area (N, 6) and, with
// `moments`, the faces' moments (E, 9) (core::Face; else (0, 9)).
// Float32 points (and box) are computed as float64 and the floating outputs
// rounded back: faces ask more than float32 resolves (a needle's long faces,
// two planes a few ulps apart), and a float32 kNN ranks neighbours whose
// distances differ below its rounding by index, which leaves a face to the
// wrong one.
template <typename Exec>
GraphOutputs voronoi_graph_forward(const at::Tensor& points, const at::Tensor& box,
                                   const c10::optional<at::Tensor>& batch, c10::optional<int64_t> k,
                                   int64_t memory_budget, bool moments) {
  if (points.scalar_type() == at::kFloat && box.scalar_type() == at::kFloat) {
    GraphOutputs out = voronoi_graph_forward<Exec>(points.to(at::kDouble), box.to(at::kDouble), batch, k,
                                                   memory_budget, moments);
    const auto as_float = [](at::Tensor& t) { t = t.to(at::kFloat); };
    as_float(std::get<0>(out));
    as_float(std::get<1>(out));
    as_float(std::get<2>(out));
    as_float(std::get<5>(out));  // a float bound already (core::radius_bound): exact
    as_float(std::get<7>(out));
    as_float(std::get<8>(out));
    as_float(std::get<9>(out));
    as_float(std::get<10>(out));
    return out;
  }
  GraphFaces graph;
  graph.moments = moments;
  const VoronoiOutputs cells = voronoi_forward<Exec>(points, box, batch, k, memory_budget, false, {}, &graph, c10::nullopt);
  const int64_t n = points.size(0);
  const at::TensorOptions longs = points.options().dtype(at::kLong);
  const FaceTensors& faces = graph.faces;
  at::Tensor edge_index = at::empty({2, 0}, longs), area = at::empty({0}, points.options());
  at::Tensor centroid = at::empty({0, 3}, points.options()), face_moments = at::empty({0, 9}, points.options());
  at::Tensor wall_area = at::zeros({n, 6}, points.options());
  if (n > 0) {
    const at::Tensor row_of_position = graph.row_of_position.to(at::kLong);
    wall_area.index_copy_(0, row_of_position, faces.wall_area);
    // Cell row r's faces: its count from its offset (face_layout's rows in
    // order, or the ranges the cells claimed), as edges in row order.
    const at::Tensor count_by_row = at::zeros({n}, longs).index_copy_(0, row_of_position, faces.count.to(at::kLong));
    const at::Tensor from_by_row = at::zeros({n}, longs).index_copy_(0, row_of_position, faces.offset);
    const at::Tensor first = at::zeros({n + 1}, longs);
    first.narrow(0, 1, n).copy_(count_by_row.cumsum(0));
    const int64_t num_edges = first[n].item<int64_t>();
    Edges edges;
    AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "torchvor::voronoi_graph", [&] {
      edges = symmetric_edges<Exec, scalar_t>(from_by_row, first, num_edges, graph.row_of_position.contiguous(),
                                              faces, n, moments);
    });
    edge_index = edges.edge_index;
    area = edges.area;
    centroid = edges.centroid;
    if (moments) face_moments = edges.moments;
  }
  const auto& [volume, cell_centroid, second_moment, status, neighbors_needed, radius] = cells.cells;
  return {volume,     cell_centroid, second_moment, status,    neighbors_needed, radius,
          edge_index, area,          centroid,      wall_area, face_moments};
}

// torchvor::voronoi_cells_backward: dL/dx (N, 3) float64 through the
// faces of voronoi_cells' cells (the same passes and cells), from
// `upstream` (N, 5) float64 by row: dL/dm, dL/dM (3) and dL/dI of each cell
// (FaceGradient; `moments`: the last four may be nonzero). One pass over
// the cells, no faces kept. Float32 points are computed as float64, as by
// voronoi_graph_forward.
template <typename Exec>
at::Tensor voronoi_cells_backward(const at::Tensor& points, const at::Tensor& box,
                                  const c10::optional<at::Tensor>& batch, c10::optional<int64_t> k,
                                  int64_t memory_budget, const at::Tensor& upstream, bool moments) {
  TORCH_CHECK(upstream.scalar_type() == at::kDouble && upstream.dim() == 2 && upstream.size(1) == 5 &&
                  upstream.size(0) == points.size(0) && upstream.device() == points.device(),
              "torchvor: voronoi_cells_backward: upstream must be (N, 5) float64 on the points' device, got ",
              upstream.sizes(), " ", upstream.scalar_type(), " on ", upstream.device());
  if (points.scalar_type() == at::kFloat) {
    return voronoi_cells_backward<Exec>(points.to(at::kDouble), box.to(at::kDouble), batch, k, memory_budget,
                                        upstream, moments);
  }
  GraphFaces graph;
  graph.moments = moments;
  graph.upstream = upstream.contiguous();
  voronoi_forward<Exec>(points, box, batch, k, memory_budget, false, {}, &graph, c10::nullopt);
  const at::Tensor gradient = at::zeros({points.size(0), 3}, upstream.options());
  if (points.size(0) == 0) return gradient;
  return gradient.index_copy_(0, graph.row_of_position.to(at::kLong), graph.faces.gradient);
}

}  // namespace ops
}  // namespace torchvor
