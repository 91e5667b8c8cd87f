// Every torchvor operator schema. Backends register kernels in cpu/ and cuda/;
// the Python layer (torchvor/ops.py, torchvor/cvt.py) registers the fake
// (meta) kernels, the autograd formulas and the ops implemented in Python.
#include <torch/library.h>

TORCH_LIBRARY(torchvor, m) {
  // k nearest points of every query, sorted by (squared distance, index),
  // padded with (inf, -1). dist2: (M, k) points' dtype; idx: (M, k) int64.
  m.def(
      "knn(Tensor points, Tensor queries, int k, Tensor? batch=None, Tensor? query_batch=None, "
      "bool exclude_self=False) -> (Tensor dist2, Tensor idx)");
  // Every point within distance r of each query (|p - q| <= r), of the
  // query's batch element: idx (E,) int64 the point, row (E,) int64 the
  // query, dist2 (E,) points' dtype, sorted by (row, dist2, idx).
  m.def(
      "radius(Tensor points, Tensor queries, float r, Tensor? batch=None, Tensor? query_batch=None, "
      "bool exclude_self=False) -> (Tensor idx, Tensor row, Tensor dist2)");
  // Voronoi cells of points clipped to box (B, 2, 3): volume (N,), centroid
  // (N, 3), second moment about the seed (N,), status (N,) int8, the
  // number of nearest neighbours each cell needed (N,) int32, and radius (N,):
  // the largest distance from the point to a vertex of its cell, rounded up
  // to float32 (NaN for a failed cell, 0 for a duplicate). k: first-pass
  // neighbours; None measures it on a pilot sample of cells. rows (M,) int64:
  // only those cells are computed, and the outputs have M rows, row m the
  // cell of points[rows[m]].
  m.def(
      "voronoi_cells(Tensor points, Tensor box, Tensor? batch=None, int? k=None, "
      "int memory_budget=1073741824, Tensor? rows=None) -> (Tensor volume, Tensor centroid, Tensor second_moment, "
      "Tensor status, Tensor neighbors_needed, Tensor radius)");
  // The cells of voronoi_cells and their faces: edge_index (2, E) int64,
  // the neighbour j (row 0) across a face of cell i (row 1), sorted by i
  // then j, each face in both directions; face_area (E,), face_centroid
  // (E, 3), and wall_area (N, 6), the cells' areas on the box walls -x, +x,
  // -y, +y, -z, +z; with moments, face_moments (E, 9), each face's integrals
  // of u u^T (xx, yy, zz, xy, xz, yz) and |u|^2 u, u = y - face centroid
  // (else (0, 9)): the gradients' terms (ops/voronoi_graph.h).
  m.def(
      "voronoi_graph(Tensor points, Tensor box, Tensor? batch=None, int? k=None, "
      "int memory_budget=1073741824, bool moments=False) -> (Tensor volume, Tensor centroid, "
      "Tensor second_moment, Tensor status, Tensor neighbors_needed, Tensor radius, Tensor edge_index, Tensor face_area, "
      "Tensor face_centroid, Tensor wall_area, Tensor face_moments)");
  // voronoi_cells' backward: dL/dpoints (N, 3) float64 through the faces of
  // the same cells, from upstream (N, 5) float64, each cell's dL/dvolume,
  // dL/d(first moment about its point) (3) and dL/dsecond_moment; moments:
  // the last four may be nonzero (ops/voronoi_graph.h).
  m.def(
      "voronoi_cells_backward(Tensor points, Tensor box, Tensor? batch, int? k, int memory_budget, "
      "Tensor upstream, bool moments) -> Tensor");
  // The same cells in the op's grid order (cells of nearby points in nearby
  // rows), with order (N,) int64: row i is the cell of points[order[i]]. It
  // skips the scattered gather to the caller's rows; torchvor.lloyd keeps its
  // points in this order, so that the next call's order is nearly the identity.
  m.def(
      "voronoi_cells_grid_order(Tensor points, Tensor box, Tensor? batch=None, int? k=None, "
      "int memory_budget=1073741824) -> (Tensor volume, Tensor centroid, Tensor second_moment, "
      "Tensor status, Tensor neighbors_needed, Tensor radius, Tensor order)");
  // One Lloyd iteration on points (N, 3). The cells as voronoi_cells_grid_order
  // computes them with first-pass k (None: a pilot's, as there): volume,
  // centroid, second_moment, status, neighbors_needed and radius by grid position, and order
  // (N,) int64: row i is the cell of points[order[i]]. moved (N, 3), by grid
  // position: each point at its cell's centroid clamped into its box, or where
  // it was if its cell failed. measures (3,) float64 on the CPU: the sum of
  // the second moments (the CVT energy before the move; NaN if a cell
  // failed), the largest squared displacement over the square of its box's
  // diagonal, and the first pass's k (the pilot's where k is None; 0 for no
  // points). histogram (histogram_bins,) int32 on the CPU: bin c counts the
  // rows 0, s, 2s, ... (s = sample_stride) whose cells needed c neighbours
  // (the last bin also histogram_bins; more are left out).
  m.def(
      "lloyd_step(Tensor points, Tensor box, Tensor? batch, int? k, int sample_stride, int histogram_bins, "
      "int memory_budget=1073741824) -> (Tensor moved, Tensor volume, Tensor centroid, Tensor second_moment, "
      "Tensor status, Tensor neighbors_needed, Tensor radius, Tensor order, Tensor measures, Tensor histogram)");
  // Power (Laguerre) cells of points with weights (N,), clipped to box
  // (B, 2, 3), for the cells `rows` (M,) int64, each walking a grid of the
  // points (of its cloud: batch), at array tier `tier` (0-7), in float64
  // (tier 0: float32, for float32 points; double-double from
  // tier 6): volume (M,), centroid (M, 3),
  // second_moment (M,), status (M,) int8 (7: EMPTY), neighbors_needed (M,)
  // int32 (the points the walk examined), radius (M,) float32, and
  // face_count (M,) int32 (faces on neighbours and walls). weight_max (M,)
  // float64: for each row, no point that can cut its cell weighs more (the
  // caller checks that bound's reach: torchvor/power.py). With face_room
  // > 0, the cells' faces too, as power_faces gives them, in arrays of
  // M * face_room rows that each cell claims a range of: face_first (M,)
  // int64, the cell's first row (-1: no faces, or the arrays were full and
  // its faces are not written; the ranges' order is the threads'); otherwise
  // face_first and the arrays empty.
  m.def(
      "power_cells(Tensor points, Tensor weights, Tensor box, Tensor? batch, Tensor rows, "
      "Tensor weight_max, int tier, int face_room=0) -> (Tensor volume, Tensor centroid, Tensor second_moment, "
      "Tensor status, Tensor neighbors_needed, Tensor radius, Tensor face_count, Tensor face_first, "
      "Tensor face_target, Tensor face_area, Tensor face_centroid, Tensor face_inertia)");
  // The faces of the same cells, cell m's from face_offsets[m] (M + 1,)
  // int64 (the running sum of power_cells' face_count): face_target (F,)
  // int64, the neighbour's index or -1 - wall (walls -x, +x, -y, +y, -z, +z),
  // face_area (F,), face_centroid (F, 3), and face_inertia (F,), the integral
  // over the face of |y - face centroid|^2.
  m.def(
      "power_faces(Tensor points, Tensor weights, Tensor box, Tensor? batch, Tensor rows, "
      "Tensor weight_max, int tier, Tensor face_offsets) -> (Tensor face_target, Tensor face_area, "
      "Tensor face_centroid, Tensor face_inertia)");
  // The CVT energy of voronoi_cells' cells, energy () = the sum of the second
  // moments, with its gradient (N, 3) = 2 volume (points - centroid)
  // (implemented in Python: torchvor/cvt.py).
  m.def("cvt_energy(Tensor points, Tensor box, Tensor? batch, int? k) -> (Tensor energy, Tensor gradient)");
  // The columns of a (2, E) int64 edge index whose source is not -1 (kNN's
  // padding), for knn_graph (implemented in Python: torchvor/ops.py).
  m.def("drop_missing_edges(Tensor edge_index) -> Tensor");
  // How many threads the CPU kernels run on (a build without OpenMP would run
  // one), and the instruction set of the CPU's clip loop ("avx2+fma" or
  // "baseline"): cpu/cpu_info.cpp.
  m.def("cpu_threads_used() -> int");
  m.def("cpu_isa() -> str");
}

// `import torchvor._C` loads this library, which runs the registrations above.
#include <Python.h>

extern "C" PyObject* PyInit__C(void) {
  static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_C", nullptr, -1, nullptr};
  return PyModule_Create(&module);
}
