// One clip pass over a list of cells: the kNN of a chunk of cells, then their
// clipping, at a pass's tier and precision, by threads or groups of lanes.
#pragma once

#include <ATen/ATen.h>

#include <algorithm>
#include <limits>
#include <memory>
#include <type_traits>

#include "../core/cell_faces.h"
#include "../core/voronoi_cell.h"
#include "cell_records.h"
#include "grid.h"
#include "knn.h"
#include "options.h"

namespace torchvor {
namespace ops {

// The grid that the vertex-ball passes sweep, held only by their functors
// (an empty base of the others): past 128 bytes of kernel parameter, nvcc
// reads a functor's fields at each use instead of once at the kernel's
// entry. The static_assert below the functor keeps the hot ones within.
template <typename io_t, bool kVertexBalls>
struct VertexBallsGridMember {
  core::GridView<io_t> grid;  // the points by position
};
template <typename io_t>
struct VertexBallsGridMember<io_t, false> {};

// Where voronoi_graph's passes write faces, held only by their functors (the
// plain passes' kernels stay as they were: no face code, no parameter).
template <typename io_t, bool kFaces>
struct FacesMember {
  const FaceOutputs<io_t>* faces;  // on the device that runs the pass
};
template <typename io_t>
struct FacesMember<io_t, false> {};

// The planes a cell may hold at each tier of recovery. The device runs tiers
// up to kLastDeviceTier, in kernels; the larger ones run on the host
// (Exec::HostExec), for the rare cells with hundreds of faces (a point next
// to a dense layer of points, as on the walls of a clamped cloud).
constexpr int kTierPlanes[] = {32, 64, 160, 1024, 4096};
constexpr int kLastDeviceTier = 2;
constexpr int kLastTier = 4;

// The planes a cell of a vertex-ball pass may hold at least: those passes run
// at the device's largest tier or beyond, whatever the cells asked for
// before (their cells are few, and a kernel per tier and precision would
// triple the vertex-ball kernels to compile).
constexpr int kVertexBallPlanes = kTierPlanes[kLastDeviceTier];

// A scalar type as a value (clip_chunk_on_host's dispatch).
template <typename T>
struct ScalarTag {
  using type = T;
};

// Tiers whose cells hold more planes than a thread's stack should: the host
// keeps such a cell on the heap (ClipFunctor).
constexpr bool on_heap(int planes) { return planes > 255; }

// Clip cell `cells[t]` by its neighbours (row t of `neighbors`); with
// kVertexBalls, a cell whose neighbours run out before the radius of
// security is finished on the grid (core::finish_by_vertex_balls). With
// kCompactTriangles, a thread cell keeps its triangles in 12 bytes
// (core::CompactTriangles: float32, at most 32 planes). With kFaces (one
// thread a cell), each computed cell's faces go to `faces` (emit_faces).
template <typename io_t, typename T, int MAX_PLANES, bool kVertexBalls = false, bool kCompactTriangles = false,
          bool kFaces = false>
struct ClipFunctor : VertexBallsGridMember<io_t, kVertexBalls>, FacesMember<io_t, kFaces> {
  static constexpr int kMaxTriangles = 2 * MAX_PLANES;
  using Arrays = core::CooperativeCellArrays<T, MAX_PLANES, kMaxTriangles>;

  const io_t* points;          // (N, 3)
  const io_t* box;             // (B, 2, 3)
  const int64_t* batch;        // (N,) or nullptr
  const int32_t* cells;        // (chunk,) cell (= point) ids
  const int32_t* neighbors;    // (chunk, k) row-major, or (k, chunk) if neighbors_column_major
  int32_t k;
  bool neighbors_column_major;
  int32_t chunk;               // cells in this chunk (the column stride)
  T tolerance;
  bool tetrahedron_start;      // core::compute_cell: from a tetrahedron where one fits (false: the box)
  bool rows_by_step;           // write record t (chunk-local outputs) instead of record cells[t]
  CellRecord<io_t>* records;   // (N,) by position
  int8_t* status;              // (N,) by position: the records' statuses again

  // One thread computes cell t (the host's largest tiers: on the heap).
  TV_HD void operator()(int64_t t) const {
    using Cell = core::ConvexCell<T, MAX_PLANES, kMaxTriangles, kCompactTriangles>;
    if constexpr (on_heap(MAX_PLANES)) {
#if !defined(__CUDA_ARCH__)
      const std::unique_ptr<Cell> cell(new Cell);
      core::CellIntegrals<T> out = compute(*cell, t);
      if constexpr (kFaces) {
        const std::unique_ptr<int32_t[]> plane_target(new int32_t[MAX_PLANES]);
        check_faces_resolved(*cell, t, out, plane_target.get());
        write(t, out, emit_faces(*cell, t, out, plane_target.get()));
      } else {
        write(t, out, 0);
      }
#endif
    } else {
      Cell cell;
      core::CellIntegrals<T> out = compute(cell, t);
      if constexpr (kFaces) {
        int32_t plane_target[MAX_PLANES];
        check_faces_resolved(cell, t, out, plane_target);
        write(t, out, emit_faces(cell, t, out, plane_target));
      } else {
        write(t, out, 0);
      }
    }
  }

  // voronoi_graph: a computed cell whose faces the arithmetic does not
  // resolve (core::faces_resolved, or a face's near copy dropped within the
  // tolerance band: near_copies_of_faces) is ill-conditioned: a later pass
  // recomputes it wider. plane_target (MAX_PLANES): each bisector face's
  // neighbour where the check met it in the list, else -1 (emit_faces).
  template <typename Cell>
  TV_HD void check_faces_resolved(const Cell& cell, int64_t t, core::CellIntegrals<T>& out,
                                  int32_t* plane_target) const {
    for (int q = 0; q < cell.plane_count(); ++q) plane_target[q] = -1;
    if (out.status != core::kSuccess) return;
    if (core::faces_resolved<io_t>(cell) && !near_copies_of_faces(cell, t, plane_target)) return;
    const T nan = T(0) / T(0);
    out.status = core::kIllConditioned;
    out.volume = nan;
    out.centroid = {nan, nan, nan};
    out.second_moment = nan;
  }

  // A group of lanes computes cell t together, its arrays in `arrays`.
  template <typename Lanes>
  TV_HD void operator()(int64_t t, Lanes lanes, Arrays& arrays) const {
    core::CooperativeCell<T, MAX_PLANES, kMaxTriangles, Lanes> cell(arrays, lanes);
    const core::CellIntegrals<T> out = compute(cell, t);
    int num_faces = 0;
    if constexpr (kFaces) num_faces = emit_faces(cell, t, out, nullptr);
    if (lanes.index() == 0) write(t, out, num_faces);
  }

  // Whether a listed neighbour j lies within core::FaceSeparationLimit of a
  // face's neighbour q (relative to q's distance) and either its bisector
  // meets q's nearly parallel within the cell's reach (the faces' split is
  // not resolved, whatever faces the rounding left:
  // core::nearly_parallel_bisectors), or j is no face and its bisector comes
  // within core::FaceBandMargin tolerance bands of a vertex (its face may
  // have been dropped within the band).
  // Such a pair has |r_j|^2 within 2.5 x the limit of |r_q|^2: the faces,
  // sorted by |r_q|^2, are swept beside the list (sorted by distance). The
  // sweep meets each listed face's own neighbour (r_j = r_q): it goes to
  // plane_target[q].
  template <typename Cell>
  TV_HD bool near_copies_of_faces(const Cell& cell, int64_t t, int32_t* plane_target) const {
    constexpr double limit = core::FaceSeparationLimit<io_t, T>::value;
    if constexpr (limit > 0.0) {
      bool named[MAX_PLANES];  // the planes a vertex names: the faces
      const int planes = cell.plane_count(), vertices = cell.vertex_count();
      for (int q = 0; q < planes; ++q) named[q] = false;
      for (int v = 0; v < vertices; ++v) {
        int ids[3];
        if (!cell.vertex_planes(v, ids)) continue;
        for (int e = 0; e < 3; ++e) named[ids[e]] = true;
      }
      T face_r2[MAX_PLANES];  // the bisector faces' |r_q|^2, ascending (insertion: nearly sorted already)
      int face_plane[MAX_PLANES];
      int faces = 0;
      for (int q = core::kBoxPlanes; q < planes; ++q) {  // the box's planes 0-5 may be unwritten
        if (!named[q]) continue;
        const core::Vec3<T> normal = cell.plane(q).normal;
        const T r2 = core::dot(normal, normal);
        int at = faces++;
        for (; at > 0 && face_r2[at - 1] > r2; --at) {
          face_r2[at] = face_r2[at - 1];
          face_plane[at] = face_plane[at - 1];
        }
        face_r2[at] = r2;
        face_plane[at] = q;
      }
      const int32_t cell_id = cells[t];
      const core::Vec3<T> seed = {T(points[3 * cell_id]), T(points[3 * cell_id + 1]), T(points[3 * cell_id + 2])};
      const int32_t* row = neighbors + (neighbors_column_major ? t : t * int64_t(k));
      const int64_t stride = neighbors_column_major ? int64_t(chunk) : int64_t(1);
      constexpr T window = T(2.5 * limit);
      constexpr T sine_limit = T(core::FaceSineLimit<io_t, T>::value);
      int low = 0;  // the first face with |r_q|^2 >= |r_j|^2 (1 - window)
      for (int32_t n = 0; n < k && low < faces; ++n) {
        const int32_t j = row[n * stride];
        if (j < 0) break;
        const core::Vec3<T> rj = {T(points[3 * j]) - seed.x, T(points[3 * j + 1]) - seed.y,
                                  T(points[3 * j + 2]) - seed.z};
        const T rj2 = core::dot(rj, rj);
        while (low < faces && face_r2[low] < rj2 * (T(1) - window)) ++low;
        bool near = false, face = false;
        for (int m = low; m < faces && face_r2[m] <= rj2 * (T(1) + window); ++m) {
          const core::Vec3<T> normal = cell.plane(face_plane[m]).normal;
          const core::Vec3<T> d = {rj.x + normal.x, rj.y + normal.y, rj.z + normal.z};  // r_j - r_q
          const T d2 = core::dot(d, d);
          if (d2 == T(0) && plane_target[face_plane[m]] < 0) plane_target[face_plane[m]] = j;
          face = face || d2 == T(0);
          if (d2 > T(0) && d2 <= T(limit * limit) * face_r2[m]) {
            near = true;
            const core::Vec3<T> rq = {-normal.x, -normal.y, -normal.z};
            if (core::nearly_parallel_bisectors(rq, rj, cell.largest_radius2(), sine_limit)) return true;
          }
        }
        if (!near || face) continue;
        const core::Plane<T> pj = core::bisector_plane(rj, rj2);
        const T band = T(core::FaceBandMargin) * tolerance * rj2;
        for (int v = 0; v < vertices; ++v) {
          int ids[3];
          if (cell.vertex_planes(v, ids) && core::dot(pj.normal, cell.vertex(v)) + pj.offset < band) return true;
        }
      }
    }
    return false;
  }

  template <typename Cell>
  TV_HD core::CellIntegrals<T> compute(Cell& cell, int64_t t) const {
    const int32_t cell_id = cells[t];
    const int64_t b = batch ? batch[cell_id] : 0;
    const int32_t* row = neighbors + (neighbors_column_major ? t : t * int64_t(k));
    const int64_t stride = neighbors_column_major ? int64_t(chunk) : int64_t(1);
    if constexpr (kVertexBalls) {
      const core::VertexBallGrid<io_t> vertex_balls{this->grid, b};
      return core::compute_cell(cell, points, cell_id, row, stride, k, box + 6 * b, tolerance, tetrahedron_start,
                                &vertex_balls);
    } else {
      return core::compute_cell(cell, points, cell_id, row, stride, k, box + 6 * b, tolerance, tetrahedron_start);
    }
  }

  TV_HD void write(int64_t t, const core::CellIntegrals<T>& out, int num_faces) const {
    const int64_t i = rows_by_step ? t : cells[t];
    records[i] = {static_cast<io_t>(out.volume),
                  {static_cast<io_t>(out.centroid.x), static_cast<io_t>(out.centroid.y),
                   static_cast<io_t>(out.centroid.z)},
                  static_cast<io_t>(out.second_moment), out.radius, out.neighbors, out.status,
                  static_cast<uint16_t>(num_faces)};
    status[i] = out.status;
  }

  // The faces of computed cell t (core::for_each_face): counted, written at
  // their offsets, or summed into the point's gradient (FaceOutputs). A bisector's point is found by its offset
  // from the seed, in the cell's list or (a cell finished on the grid) the
  // grid (plane_target: the planes' neighbours found already, -1 where not;
  // or nullptr). Returns the neighbour faces' count.
  template <typename Cell>
  TV_HD int emit_faces(const Cell& cell, int64_t t, const core::CellIntegrals<T>& out,
                       const int32_t* plane_target) const {
    if (out.status != core::kSuccess) return 0;
    const int64_t i = rows_by_step ? t : cells[t];
    const int32_t cell_id = cells[t];
    const int64_t b = batch ? batch[cell_id] : 0;
    const core::Vec3<T> seed = {T(points[3 * cell_id]), T(points[3 * cell_id + 1]), T(points[3 * cell_id + 2])};
    const io_t* corners = box + 6 * b;
    const core::Vec3<T> lo = core::Vec3<T>{T(corners[0]), T(corners[1]), T(corners[2])} - seed;
    const core::Vec3<T> hi = core::Vec3<T>{T(corners[3]), T(corners[4]), T(corners[5])} - seed;
    const int32_t* row = neighbors + (neighbors_column_major ? t : t * int64_t(k));
    const int64_t stride = neighbors_column_major ? int64_t(chunk) : int64_t(1);
    // The planes follow the list's order but for the start's: each search
    // starts after the last match and wraps around.
    int32_t listed = -1, cursor = 0;  // the list's length (-1 padding after), found at the first search
    const auto target_of = [&](int q, const core::Plane<T>& p) -> int32_t {
      if (q < core::kBoxPlanes) {  // planes 0-5 are the box's, the others bisectors
        const int wall = core::wall_of(p, lo, hi);
        if (wall >= 0) return core::wall_target(wall);
      }
      if (plane_target != nullptr && plane_target[q] >= 0) return plane_target[q];
      const core::Vec3<T> r = {-p.normal.x, -p.normal.y, -p.normal.z};  // bisector_plane's normal
      if (listed < 0) {
        listed = 0;
        while (listed < k && row[listed * stride] >= 0) ++listed;
      }
      for (int32_t step = 0; step < listed; ++step) {
        const int32_t n = cursor + step < listed ? cursor + step : cursor + step - listed;
        const int32_t j = row[n * stride];
        if (T(points[3 * j]) - seed.x == r.x && T(points[3 * j + 1]) - seed.y == r.y &&
            T(points[3 * j + 2]) - seed.z == r.z) {
          cursor = n + 1 < listed ? n + 1 : 0;
          return j;
        }
      }
      if constexpr (kVertexBalls) {
        const int32_t j = core::point_at_offset(core::VertexBallGrid<io_t>{this->grid, b}, seed, r);
        if (j >= 0) return j;
      }
      return core::kNoFace;
    };
    const FaceOutputs<io_t> to = *this->faces;
    return emit_cell_faces(to, cell, target_of, i, cell_id, points, seed);
  }
};
static_assert(sizeof(ClipFunctor<float, float, 32>) <= 128 && sizeof(ClipFunctor<double, double, 32>) <= 128,
              "clip functors beyond 128 bytes get slower kernels (VertexBallsGridMember)");

// How hard a pass tries: neighbours per cell, array tier, precision.
enum class Precision { kInput, kFloat64, kDoubleDouble };

struct PassSettings {
  int64_t k;
  int tier;            // 0 to kLastTier: at most kTierPlanes[tier] planes
  Precision precision;
  bool vertex_balls = false;  // cells whose k neighbours run out are finished on the grid

  bool operator==(const PassSettings& o) const {
    return k == o.k && tier == o.tier && precision == o.precision && vertex_balls == o.vertex_balls;
  }
};

// Clips a chunk of cells. With `vertex_balls` (the grid of `points` by
// position), cells whose neighbours run out before the radius of security
// are finished on it (ClipFunctor's kVertexBalls).
// With kUpToDeviceCount, only the cells that `live` says are valid run (the
// speculative retry pass; kernels of their own).
template <typename Exec, typename io_t, typename T, int MAX_PLANES, bool kVertexBalls,
          bool kUpToDeviceCount = false>
void clip_chunk(const at::Tensor& points, const at::Tensor& box,
                const c10::optional<at::Tensor>& batch, const at::Tensor& cells,
                const at::Tensor& neighbors, bool column_major, bool rows_by_step, const Grid* vertex_balls, c10::optional<double> neighbor_spread,
                const Options& options, PositionOutputs& out, const core::DeviceCount& live = {}) {
  static_assert(!kVertexBalls || MAX_PLANES >= kVertexBallPlanes, "vertex-ball passes run at the largest tiers");
  constexpr bool kCompactPossible = std::is_same<T, float>::value && MAX_PLANES <= 32;
  // The functor with or without compact triangles, with or without faces
  // (std::true_type or std::false_type).
  const auto functor = [&](auto compact, auto faces) {
    ClipFunctor<io_t, T, MAX_PLANES, kVertexBalls, decltype(compact)::value, decltype(faces)::value> clip{
        {},
        {},
        points.data_ptr<io_t>(),        box.data_ptr<io_t>(),
        batch.has_value() ? batch->data_ptr<int64_t>() : nullptr,
        cells.data_ptr<int32_t>(),      neighbors.data_ptr<int32_t>(),
        static_cast<int32_t>(neighbors.size(1)), column_major, static_cast<int32_t>(cells.size(0)),
        T(core::ClipTolerance<T>::value), options.tetrahedron_start,
        rows_by_step,                   out.data<io_t>(),
        out.status.data_ptr<int8_t>()};
    if constexpr (kVertexBalls) clip.grid = vertex_balls->view<io_t>();
    if constexpr (decltype(faces)::value) clip.faces = out.face_outputs<io_t>();
    if constexpr (kUpToDeviceCount) {
      return core::up_to_device_count(clip, live);
    } else {
      return clip;
    }
  };
  // One thread per cell (ConvexCell) or a group of lanes per cell
  // (CooperativeCell): the backend chooses by the pass's size, k and the
  // pilot's neighbour spread, and options.cells may force one
  // (use_cooperative). Cells finished on the grid vary the most
  // (their sweeps' lengths): the backend's choice for the widest spread,
  // warps on the GPU (each sweeps its cell's rows and points together,
  // where a thread's cell waited on its own loads: vertex_balls.h).
  // Float32 thread cells of the first tier keep their triangles in 12 bytes
  // where the backend asks for it (Exec::kCompactTriangles, unless
  // options.compact_triangles is off).
  // Double-double's products must round separately (Dekker's split); it
  // runs on the CPU only, one thread per cell.
  // The host's largest tiers run thread cells only (a warp cell's ids are bytes).
  // voronoi_graph's passes: thread cells, whose functors write the faces
  // (no speculative pass runs then), in float64 or wider (the op computes
  // float32 points as float64: voronoi_graph_forward).
  if constexpr (!kUpToDeviceCount && !std::is_same<T, float>::value) {
    if (out.faces.defined()) {
      if constexpr (std::is_same<T, core::DoubleDouble>::value) {
        Exec::for_each(cells.size(0), functor(std::false_type(), std::true_type()));
      } else {
        Exec::for_each_cell(cells.size(0), neighbors.size(1), options, functor(std::false_type(), std::true_type()));
      }
      return;
    }
  }
  TORCH_CHECK(!out.faces.defined(), "torchvor: internal error: a float32 pass of voronoi_graph");
  if constexpr (std::is_same<T, core::DoubleDouble>::value) {
    Exec::for_each(cells.size(0), functor(std::false_type(), std::false_type()));
  } else if constexpr (on_heap(MAX_PLANES)) {
    Exec::for_each_cell(cells.size(0), neighbors.size(1), options, functor(std::false_type(), std::false_type()));
  } else {
    const c10::optional<double> spread =
        kVertexBalls ? c10::optional<double>(std::numeric_limits<double>::infinity()) : neighbor_spread;
    if (use_cooperative(options.cells, Exec::cooperative_cells(cells.size(0), neighbors.size(1), spread))) {
      Exec::template for_each_cooperative<typename ClipFunctor<io_t, T, MAX_PLANES>::Arrays>(
          cells.size(0), functor(std::false_type(), std::false_type()));
    } else {
      if constexpr (kCompactPossible && Exec::kCompactTriangles) {
        if (options.compact_triangles) {
          Exec::for_each_cell(cells.size(0), neighbors.size(1), options, functor(std::true_type(), std::false_type()));
          return;
        }
      }
      Exec::for_each_cell(cells.size(0), neighbors.size(1), options, functor(std::false_type(), std::false_type()));
    }
  }
}

template <typename Exec, typename io_t, typename T>
void clip_chunk_tier(const at::Tensor& points, const at::Tensor& box,
                     const c10::optional<at::Tensor>& batch, const at::Tensor& cells,
                     const at::Tensor& neighbors, int tier, const Grid* vertex_balls,
                     c10::optional<double> neighbor_spread, const Options& options, PositionOutputs& out) {
  constexpr bool column_major = Exec::kColumnMajorNeighbors;
  // The arguments that every tier's clip takes alike.
  const auto clip = [&](auto planes, auto finish_by_vertex_balls, const Grid* grid) {
    clip_chunk<Exec, io_t, T, decltype(planes)::value, decltype(finish_by_vertex_balls)::value>(
        points, box, batch, cells, neighbors, column_major, /*rows_by_step=*/false, grid,
        neighbor_spread, options, out);
  };
  if (vertex_balls != nullptr) {
    TORCH_CHECK(tier == kLastDeviceTier, "torchvor: internal error: a vertex-ball pass below the largest tier");
    clip(std::integral_constant<int, kVertexBallPlanes>(), std::true_type(), vertex_balls);
    return;
  }
  switch (tier) {
    case 0: clip(std::integral_constant<int, 32>(), std::false_type(), nullptr); break;
    case 1: clip(std::integral_constant<int, 64>(), std::false_type(), nullptr); break;
    default: clip(std::integral_constant<int, 160>(), std::false_type(), nullptr); break;
  }
}

// The speculative retry pass's clip (voronoi_passes): the first tier, in
// the points' precision, on the cells of `cells` that `live` says are valid.
template <typename Exec, typename io_t>
void clip_chunk_up_to_device_count(const at::Tensor& points, const at::Tensor& box,
                                   const c10::optional<at::Tensor>& batch, const at::Tensor& cells,
                                   const at::Tensor& neighbors, c10::optional<double> neighbor_spread,
                                   const core::DeviceCount& live, const Options& options,
                                   PositionOutputs& out) {
  clip_chunk<Exec, io_t, io_t, 32, false, true>(points, box, batch, cells, neighbors, Exec::kColumnMajorNeighbors,
                                                false, nullptr, neighbor_spread, options, out, live);
}

// The passes the device does not run, on the CPU whatever the device
// (Exec::HostExec; the paper's fallback): the tiers beyond kLastDeviceTier,
// and the last resort, double-double arithmetic, whose clips decide by exact
// predicates (core/exact_predicates.h). Only a handful of cells
// ever get here. `pass` gives the tier, the precision and vertex balls.
template <typename HostExec, typename io_t>
void clip_chunk_on_host(const at::Tensor& points, const at::Tensor& box, const c10::optional<at::Tensor>& batch,
                        const at::Tensor& cells, const at::Tensor& neighbors, bool column_major,
                        const PassSettings& pass, const Grid* vertex_balls, const Options& options,
                        PositionOutputs& out) {
  const int64_t m = cells.size(0);
  const auto cpu = [](const at::Tensor& t) { return t.to(at::kCPU).contiguous(); };
  const c10::optional<at::Tensor> batch_cpu =
      batch.has_value() ? c10::optional<at::Tensor>(cpu(*batch)) : c10::nullopt;
  const Grid vertex_balls_cpu = vertex_balls != nullptr ? vertex_balls->to_cpu() : Grid{};
  PositionOutputs part;
  part.records = empty_records<io_t>(m, points.options().device(at::kCPU));
  part.status = at::empty({m}, points.options().device(at::kCPU).dtype(at::kChar));
  HostFaces host_faces;
  if (out.face_tensors != nullptr) {
    host_faces = HostFaces::make<io_t>(*out.face_tensors, cells);
    part.faces = host_faces.bytes;
    part.face_tensors = &host_faces.part;
  }
  const bool double_double = pass.precision == Precision::kDoubleDouble;
  const auto clip = [&](auto scalar, auto planes, auto finish_by_vertex_balls) {
    using T = typename decltype(scalar)::type;
    clip_chunk<HostExec, io_t, T, decltype(planes)::value, decltype(finish_by_vertex_balls)::value>(
        cpu(points), cpu(box), batch_cpu, cpu(cells), cpu(neighbors), column_major,
        /*rows_by_step=*/true,
        vertex_balls != nullptr ? &vertex_balls_cpu : nullptr, /*neighbor_spread=*/c10::nullopt, options, part);
  };
  const auto at_tier = [&](auto scalar, auto finish_by_vertex_balls) {
    switch (pass.tier) {
      case kLastTier: clip(scalar, std::integral_constant<int, kTierPlanes[kLastTier]>(), finish_by_vertex_balls); break;
      case kLastTier - 1:
        clip(scalar, std::integral_constant<int, kTierPlanes[kLastTier - 1]>(), finish_by_vertex_balls);
        break;
      default: clip(scalar, std::integral_constant<int, kVertexBallPlanes>(), finish_by_vertex_balls); break;
    }
  };
  const auto in_precision = [&](auto finish_by_vertex_balls) {
    // Float32 points in float32 or float64; float64 points in float64 (as run_pass).
    if (double_double) {
      at_tier(ScalarTag<core::DoubleDouble>(), finish_by_vertex_balls);
    } else if (std::is_same<io_t, double>::value || pass.precision == Precision::kFloat64) {
      at_tier(ScalarTag<double>(), finish_by_vertex_balls);
    } else {
      at_tier(ScalarTag<io_t>(), finish_by_vertex_balls);
    }
  };
  if (vertex_balls != nullptr) {
    in_precision(std::true_type{});
  } else {
    in_precision(std::false_type{});
  }
  const at::Tensor rows = cells.to(at::kLong);
  out.records.index_copy_(0, rows, part.records.to(out.records.device()));
  out.status.index_copy_(0, rows, part.status.to(out.status.device()));
  if (out.face_tensors != nullptr) host_faces.copy_back(*out.face_tensors, cells);
}

// One pass over `cells` (int32 point ids), in chunks of bounded memory.
template <typename Exec, typename io_t>
void run_pass(const at::Tensor& points, const at::Tensor& box,
              const c10::optional<at::Tensor>& batch, const Grid& grid, const at::Tensor& cells,
              const PassSettings& pass, c10::optional<double> neighbor_spread, int64_t memory_budget,
              const Options& options, PositionOutputs& out) {
  TORCH_CHECK(cells.is_contiguous(), "torchvor: internal error: cell list not contiguous");
  // The budget holds the chunk's neighbour ids. Chunks of equal size: a
  // small last chunk would leave most of the GPU idle while its few cells
  // run, and every chunk ends in such a tail, so fewer chunks are better.
  const int64_t bytes_per_cell = pass.k * int64_t(sizeof(int32_t));
  const int64_t largest_chunk = std::max<int64_t>(1024, memory_budget / bytes_per_cell);
  const int64_t chunks = std::max<int64_t>(1, (cells.size(0) + largest_chunk - 1) / largest_chunk);
  const int64_t chunk = (cells.size(0) + chunks - 1) / chunks;
  const Grid swept = pass.vertex_balls ? with_cell_bounds<Exec>(grid) : Grid{};  // the vertex-ball sweep's
  for (int64_t begin = 0; begin < cells.size(0); begin += chunk) {
    const at::Tensor part = cells.slice(0, begin, std::min(cells.size(0), begin + chunk));
    const int64_t m = part.size(0);
    at::Tensor no_distances;  // the clipper recomputes distances from coordinates
    // m * k neighbour ids, laid out as Exec prefers (see kColumnMajorNeighbors)
    at::Tensor neighbors = at::empty({m, pass.k}, points.options().dtype(at::kInt));
    run_knn<Exec, io_t, int32_t>(grid, points.data_ptr<io_t>(), /*queries_in_order=*/false,
                        batch.has_value() ? batch->data_ptr<int64_t>() : nullptr,
                        part.data_ptr<int32_t>(), m, pass.k, /*exclude_self=*/true,
                        /*row_by_query=*/false, Exec::kColumnMajorNeighbors, /*stream_rows=*/false, options.knn,
                        no_distances, neighbors);
    const Grid* vertex_balls = pass.vertex_balls ? &swept : nullptr;
    // Float32 points are clipped in float32 or float64; float64 points only
    // in float64 (`if constexpr`: no float32 cells of float64 points are
    // compiled, which nothing would run).
    const auto clip_in_float64 = [&] {
      clip_chunk_tier<Exec, io_t, double>(points, box, batch, part, neighbors, pass.tier, vertex_balls,
                                          neighbor_spread, options, out);
    };
    if (pass.precision == Precision::kDoubleDouble || pass.tier > kLastDeviceTier) {
      clip_chunk_on_host<typename Exec::HostExec, io_t>(points, box, batch, part, neighbors,
                                                        Exec::kColumnMajorNeighbors, pass, vertex_balls, options,
                                                        out);
    } else if constexpr (std::is_same<io_t, double>::value) {
      clip_in_float64();
    } else if (pass.precision == Precision::kFloat64) {
      clip_in_float64();
    } else {
      clip_chunk_tier<Exec, io_t, float>(points, box, batch, part, neighbors, pass.tier, vertex_balls,
                                         neighbor_spread, options, out);
    }
  }
}

}  // namespace ops
}  // namespace torchvor
