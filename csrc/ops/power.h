// torchvor::power_cells and torchvor::power_faces, shared by the CPU and
// CUDA backends: the cells of a power diagram (core/power_cell.h) for given
// rows, each walking a grid of the points (built here, with the largest
// weight of each cube), one thread a cell, in float64 (float32 points'
// cells first in float32 where the caller asks), writing their faces where asked
// (each cell claiming its rows).
// torchvor/power.py bounds the weights that can reach each cell, retries the
// cells whose arrays overflowed (the next tier), and gathers the faces.
#pragma once

#include <ATen/ATen.h>

#include <cstdint>
#include <memory>
#include <tuple>
#include <type_traits>

#include "../core/cell_faces.h"
#include "grid.h"
#include "options.h"
#include "../core/power_cell.h"
#include "../core/status.h"

namespace torchvor {
namespace ops {

// The planes (and twice as many vertices) a power cell may hold at each
// tier; the tiers past kLastDevicePowerTier run on the host only, their
// cells on the heap. Tier 0 computes float32 points' cells in float32 (the
// compact thread cell, behind the float checks; faces where the caller
// takes float32's faces, as power_weights' first steps do): calls with
// float64 points are refused there. Tiers 1-5 compute in float64
// (the largest for the cells above a dense layer of points, with thousands
// of faces); the last two, for the cells whose float64 integrals or clips
// the arithmetic does not resolve (ILL_CONDITIONED, BOUNDARY_ERROR), in
// double-double.
constexpr int kPowerTierPlanes[] = {32, 64, 160, 1024, 4096, 16384, 4096, 16384};
constexpr int kFloatPowerTier = 0;
constexpr int kLastDevicePowerTier = 2;
constexpr int kDoubleDoublePowerTier = 6;
constexpr int kLastPowerTier = 7;

// kCompact: float32 triangles in 12 bytes (core::CompactTriangles), where
// the backend keeps them so (Exec::kCompactTriangles: the GPU's L1 cache).
template <int kPlanes, typename T, bool kCompact = false>
using PowerCell = core::ConvexCell<T, kPlanes, 2 * kPlanes, kCompact, true>;

// What a power cell does with its faces: counts them; counts them, claims a
// range of the faces' arrays that long and writes them there; or writes them
// at offsets given. Each its own kernel: the claims' code slowed the count's.
enum class PowerFaceMode { kCount, kClaim, kFill };

// Cell m of `rows`: its integrals, status, neighbours used, radius and face
// count (neighbour faces and wall faces); with kFill, also its faces from
// face_offsets[m] on (target: the neighbour's index, or -1 - wall for the
// box walls -x, +x, -y, +y, -z, +z; area; centroid; inertia, the integral
// over the face of |y - centroid|^2: the weights' gradients' term); with
// kClaim, the same in a range it claims from `next_face` (face_first[m]:
// the range's start; -1: no faces, or past `capacity`, none written).
template <typename io_t, int kPlanes, PowerFaceMode kMode, typename T = double, bool kCompact = false>
struct PowerCellFunctor {
  const io_t* points;         // (N, 3)
  const io_t* weights;        // (N,)
  const io_t* box;            // (B, 2, 3)
  const int64_t* batch;       // (N,) or nullptr (one box)
  const int64_t* rows;        // (M,)
  core::GridView<io_t> grid;  // of the points, one grid a cloud
  const io_t* sorted_weights;   // (N,) in the grid's order
  const io_t* cube_weight_max;  // (cubes,): the largest weight of each, -inf where empty
  const double* weight_max;   // (M,)
  io_t* volume;               // (M,)
  io_t* centroid;             // (M, 3)
  io_t* second_moment;        // (M,)
  int8_t* status;             // (M,)
  int32_t* needed;            // (M,)
  float* radius;              // (M,)
  int32_t* face_count;        // (M,)
  const int64_t* face_offsets;  // kFill: (M + 1,)
  int64_t* face_target;         // kFill, kClaim: (F,)
  io_t* face_area;              // kFill, kClaim: (F,)
  io_t* face_centroid;          // kFill, kClaim: (F, 3)
  io_t* face_inertia;           // kFill, kClaim: (F,)
  unsigned long long* next_face;  // kClaim: the arrays' first free row
  int64_t capacity;               // kClaim: the arrays' rows
  int64_t* face_first;            // kClaim: (M,)
  Options::NearestFirstCells nearest_first;  // Options::power_nearest_first (the tier's cells decide)

  using Cell = PowerCell<kPlanes, T, kCompact>;
  static constexpr bool kOnHeap = kPlanes > kPowerTierPlanes[kLastDevicePowerTier];

  TV_HD void operator()(int64_t m) const {
    if constexpr (kOnHeap) {
#if !defined(__CUDA_ARCH__)
      const auto cell = std::make_unique<Cell>();
      run(*cell, m);
#endif
    } else {
      Cell cell;
      run(cell, m);
    }
  }

  TV_HD void run(Cell& cell, int64_t m) const {
    const int64_t seed = rows[m];
    const int64_t b = batch != nullptr ? batch[seed] : 0;
    const core::CellIntegrals<T> out = core::compute_power_cell<io_t>(
        cell, points, weights, seed, grid, sorted_weights, cube_weight_max, b, box + 6 * b, weight_max[m],
        T(core::ClipTolerance<T>::value),
        nearest_first == Options::NearestFirstCells::kAll ||
            (nearest_first == Options::NearestFirstCells::kFloat64 && !std::is_same<T, float>::value));
    volume[m] = io_t(out.volume);
    centroid[3 * m] = io_t(out.centroid.x);
    centroid[3 * m + 1] = io_t(out.centroid.y);
    centroid[3 * m + 2] = io_t(out.centroid.z);
    second_moment[m] = io_t(out.second_moment);
    status[m] = out.status;
    needed[m] = out.neighbors;
    radius[m] = out.radius;
    int32_t faces = 0;
    if (out.status == core::kSuccess) {
      const core::Vec3<double> at = {double(points[3 * seed]), double(points[3 * seed + 1]),
                                     double(points[3 * seed + 2])};
      const auto target_of = [&](int q, const core::Plane<T>&) -> int32_t {
        return q < core::kBoxPlanes ? core::wall_target(q) : cell.owner_of(q);
      };
      const auto store = [&](int64_t f, int32_t target, const core::Face<T>& face) {
        face_target[f] = target;
        face_area[f] = io_t(face.area);
        face_centroid[3 * f] = io_t(at.x + double(face.centroid.x));
        face_centroid[3 * f + 1] = io_t(at.y + double(face.centroid.y));
        face_centroid[3 * f + 2] = io_t(at.z + double(face.centroid.z));
        face_inertia[f] = io_t(face.second[0] + face.second[1] + face.second[2]);
      };
      constexpr bool kFill = kMode == PowerFaceMode::kFill;
      core::for_each_face<kFill>(cell, target_of, [&](int, int32_t target, const core::Face<T>& face) {
        if constexpr (kFill) store(face_offsets[m] + faces, target, face);
        ++faces;
      });
      if constexpr (kMode == PowerFaceMode::kClaim) {
        if (faces > 0) {  // counted: claim that many rows, then write them
          const int64_t first = int64_t(core::fetch_add(next_face, static_cast<unsigned long long>(faces)));
          if (first + faces <= capacity) {
            int32_t slot = 0;
            core::for_each_face<true>(cell, target_of, [&](int, int32_t target, const core::Face<T>& face) {
              if (slot < faces) store(first + slot, target, face);
              ++slot;
            });
            face_first[m] = first;
          }
        }
      }
    }
    face_count[m] = faces;
  }
};

// A cell scalar type as a value (run_power_tier).
template <typename T>
struct PowerScalar {
  using type = T;
};

// The arguments both ops take, checked.
inline void check_power_inputs(const at::Tensor& points, const at::Tensor& weights, const at::Tensor& box,
                               const c10::optional<at::Tensor>& batch, const at::Tensor& rows,
                               const at::Tensor& weight_max, int64_t tier) {
  TORCH_CHECK_TYPE(points.scalar_type() == at::kFloat || points.scalar_type() == at::kDouble,
                   "torchvor.power_cells: points must be float32 or float64, got ", points.scalar_type());
  TORCH_CHECK_VALUE(points.dim() == 2 && points.size(1) == 3, "torchvor.power_cells: points must be (N, 3), got ",
                    points.sizes());
  TORCH_CHECK_TYPE(weights.scalar_type() == points.scalar_type() && box.scalar_type() == points.scalar_type(),
                   "torchvor.power_cells: weights and box must have the points' dtype");
  TORCH_CHECK_VALUE(weights.dim() == 1 && weights.size(0) == points.size(0),
                    "torchvor.power_cells: weights must be (N,), got ", weights.sizes());
  TORCH_CHECK_VALUE(box.dim() == 3 && box.size(1) == 2 && box.size(2) == 3 && box.size(0) >= 1,
                    "torchvor.power_cells: box must be (B, 2, 3), got ", box.sizes());
  TORCH_CHECK_VALUE(points.size(0) < (int64_t(1) << 31), "torchvor.power_cells: fewer than 2^31 points, got ",
                    points.size(0));
  TORCH_CHECK_TYPE(rows.scalar_type() == at::kLong, "torchvor.power_cells: rows must be int64");
  TORCH_CHECK_VALUE(rows.dim() == 1, "torchvor.power_cells: rows must be (M,), got ", rows.sizes());
  TORCH_CHECK_TYPE(weight_max.scalar_type() == at::kDouble, "torchvor.power_cells: weight_max must be float64");
  TORCH_CHECK_VALUE(weight_max.dim() == 1 && weight_max.size(0) == rows.size(0),
                    "torchvor.power_cells: weight_max must be (M,), one per row");
  if (batch.has_value()) {
    TORCH_CHECK_VALUE(batch->scalar_type() == at::kLong && batch->dim() == 1 && batch->size(0) == points.size(0),
                      "torchvor.power_cells: batch must be (N,) int64");
  } else {
    TORCH_CHECK_VALUE(box.size(0) == 1, "torchvor.power_cells: several boxes need a batch");
  }
  TORCH_CHECK_VALUE(tier >= 0 && tier <= kLastPowerTier, "torchvor.power_cells: tier must be in [0, ",
                    kLastPowerTier, "], got ", tier);
  for (const at::Tensor* t : {&weights, &box, &rows, &weight_max}) {
    TORCH_CHECK_VALUE(t->device() == points.device(), "torchvor.power_cells: every tensor must be on the points' device");
  }
  if (batch.has_value()) {
    TORCH_CHECK_VALUE(batch->device() == points.device(), "torchvor.power_cells: every tensor must be on the points' device");
  }
}

// volume (M,), centroid (M, 3), second_moment (M,), status (M,) int8,
// neighbors_needed (M,) int32, radius (M,) float32, face_count (M,) int32.
using PowerCellOutputs = std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor>;
// face_target (F,) int64, face_area (F,), face_centroid (F, 3), face_inertia (F,).
using PowerFaceOutputs = std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor>;
// power_cells: the cells' outputs, then face_first (M,) int64 and the faces
// the cells claimed (F = M * face_room rows, PowerFaceOutputs' layout).
using PowerCellsAndFaces = std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor,
                                      at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor>;

// Runs the functor of the pass's tier over the rows (`Exec` the backend;
// the host tiers run on Exec::HostExec, with the tensors on the host).
template <typename Exec, typename io_t, PowerFaceMode kMode>
void run_power_tier(int64_t tier, int64_t m, const Options& options, PowerCellFunctor<io_t, 64, kMode> base) {
  const auto run = [&](auto planes, auto scalar) {
    constexpr int kPlanes = decltype(planes)::value;
    using Scalar = typename decltype(scalar)::type;
    constexpr bool kCompact = std::is_same<Scalar, float>::value && Exec::kCompactTriangles;
    PowerCellFunctor<io_t, kPlanes, kMode, Scalar, kCompact> functor;
    functor.points = base.points;
    functor.weights = base.weights;
    functor.box = base.box;
    functor.batch = base.batch;
    functor.rows = base.rows;
    functor.grid = base.grid;
    functor.sorted_weights = base.sorted_weights;
    functor.cube_weight_max = base.cube_weight_max;
    functor.weight_max = base.weight_max;
    functor.volume = base.volume;
    functor.centroid = base.centroid;
    functor.second_moment = base.second_moment;
    functor.status = base.status;
    functor.needed = base.needed;
    functor.radius = base.radius;
    functor.face_count = base.face_count;
    functor.face_offsets = base.face_offsets;
    functor.face_target = base.face_target;
    functor.face_area = base.face_area;
    functor.face_centroid = base.face_centroid;
    functor.face_inertia = base.face_inertia;
    functor.next_face = base.next_face;
    functor.capacity = base.capacity;
    functor.face_first = base.face_first;
    functor.nearest_first = base.nearest_first;
    // The double-double tiers by for_each: their products must round apart.
    if constexpr (std::is_same<typename decltype(scalar)::type, core::DoubleDouble>::value) {
      Exec::HostExec::for_each(m, functor);
    } else if constexpr (kPlanes > kPowerTierPlanes[kLastDevicePowerTier]) {
      Exec::HostExec::for_each_walk(m, options, functor);
    } else {
      Exec::for_each_walk(m, options, functor);
    }
  };
  using Double = PowerScalar<double>;
  switch (tier) {
    case 0:  // float32 points' cells only (power_forward checks)
      if constexpr (std::is_same<io_t, float>::value) {
        run(std::integral_constant<int, kPowerTierPlanes[0]>(), PowerScalar<float>());
      } else {
        TORCH_INTERNAL_ASSERT(false, "torchvor.power_cells: tier 0 is float32 points' cells");
      }
      break;
    case 1: run(std::integral_constant<int, kPowerTierPlanes[1]>(), Double()); break;
    case 2: run(std::integral_constant<int, kPowerTierPlanes[2]>(), Double()); break;
    case 3: run(std::integral_constant<int, kPowerTierPlanes[3]>(), Double()); break;
    case 4: run(std::integral_constant<int, kPowerTierPlanes[4]>(), Double()); break;
    case 5: run(std::integral_constant<int, kPowerTierPlanes[5]>(), Double()); break;
    case 6: run(std::integral_constant<int, kPowerTierPlanes[6]>(), PowerScalar<core::DoubleDouble>()); break;
    default: run(std::integral_constant<int, kPowerTierPlanes[7]>(), PowerScalar<core::DoubleDouble>()); break;
  }
}

// The walk's grid of the points (one a cloud of `clouds`), the weights in
// its order (`sorted_weights`) and the largest weight of each of its cubes
// (`cube_weight_max`, -inf where empty).
template <typename Exec>
Grid power_grid(const at::Tensor& points, const at::Tensor& weights, const c10::optional<at::Tensor>& batch,
                int64_t clouds, double points_per_cube, at::Tensor& sorted_weights, at::Tensor& cube_weight_max) {
  at::Tensor sorted_ids;
  const Grid grid = build_grid<Exec>(points, batch, clouds, points_per_cube, {}, {}, &sorted_ids);
  sorted_weights = weights.index_select(0, grid.sorted_index.to(at::kLong));
  cube_weight_max = at::full({grid.cell_start.size(0) - 1}, -INFINITY, weights.options());
  cube_weight_max.scatter_reduce_(0, sorted_ids.to(at::kLong), sorted_weights, "amax", /*include_self=*/true);
  return grid;
}

// The shared body of both ops: with face_offsets, fills the faces too;
// without, with face_room > 0, the cells claim the faces' rows (face_first).
template <typename Exec, bool kFaces>
std::tuple<PowerCellOutputs, at::Tensor, PowerFaceOutputs> power_forward(
    const at::Tensor& points_in, const at::Tensor& weights_in, const at::Tensor& box_in,
    const c10::optional<at::Tensor>& batch_in, const at::Tensor& rows_in, const at::Tensor& weight_max_in,
    int64_t tier, const at::Tensor& face_offsets_in, int64_t face_room) {
  check_power_inputs(points_in, weights_in, box_in, batch_in, rows_in, weight_max_in, tier);
  TORCH_CHECK_VALUE(face_room >= 0, "torchvor.power_cells: face_room must be >= 0, got ", face_room);
  TORCH_CHECK_VALUE(tier != kFloatPowerTier || points_in.scalar_type() == at::kFloat,
                    "torchvor.power_cells: tier 0 (float32 cells) takes float32 points");
  const Options tuning = Options::from_environment();
  // The host tiers run on the host: their tensors go there (and back).
  const bool on_host = tier > kLastDevicePowerTier && !points_in.device().is_cpu();
  const auto here = [&](const at::Tensor& t) { return (on_host ? t.cpu() : t).contiguous(); };
  const at::Tensor points = here(points_in), weights = here(weights_in), box = here(box_in);
  const at::Tensor rows = here(rows_in), weight_max = here(weight_max_in);
  const c10::optional<at::Tensor> batch = batch_in.has_value() ? c10::optional<at::Tensor>(here(*batch_in)) : c10::nullopt;
  const int64_t m = rows.size(0);
  const at::TensorOptions options = points.options();
  at::Tensor volume = at::full({m}, NAN, options);
  at::Tensor centroid = at::full({m, 3}, NAN, options);
  at::Tensor second_moment = at::full({m}, NAN, options);
  at::Tensor status = at::full({m}, int(core::kNotComputed), options.dtype(at::kChar));
  at::Tensor needed = at::zeros({m}, options.dtype(at::kInt));
  at::Tensor radius = at::full({m}, NAN, options.dtype(at::kFloat));
  at::Tensor face_count = at::zeros({m}, options.dtype(at::kInt));
  at::Tensor face_offsets, face_target, face_area, face_centroid, face_inertia;
  int64_t faces = 0;
  if constexpr (kFaces) {
    face_offsets = here(face_offsets_in);
    TORCH_CHECK_VALUE(face_offsets.scalar_type() == at::kLong && face_offsets.dim() == 1 && face_offsets.size(0) == m + 1,
                      "torchvor.power_faces: face_offsets must be (M + 1,) int64");
    faces = face_offsets[m].item<int64_t>();
    TORCH_CHECK_VALUE(faces >= 0, "torchvor.power_faces: face_offsets must end at the face count");
  } else {
    faces = m * face_room;
  }
  at::Tensor face_first = at::full({!kFaces && face_room > 0 ? m : 0}, int64_t(-1), options.dtype(at::kLong));
  at::Tensor next_face;  // claims' counter
  if (!kFaces && faces > 0) next_face = at::zeros({1}, options.dtype(at::kLong));
  face_target = at::full({faces}, int64_t(-7), options.dtype(at::kLong));
  face_area = at::full({faces}, NAN, options);
  face_centroid = at::full({faces, 3}, NAN, options);
  face_inertia = at::full({faces}, NAN, options);
  if (m > 0) {
    at::Tensor sorted_weights, cube_weight_max;
    const Grid grid =
        on_host ? power_grid<typename Exec::HostExec>(points, weights, batch, box.size(0), tuning.power_points_per_cube,
                                                      sorted_weights, cube_weight_max)
                : power_grid<Exec>(points, weights, batch, box.size(0), tuning.power_points_per_cube, sorted_weights,
                                   cube_weight_max);
    AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "power_cells", [&] {
      const auto launch = [&](auto mode) {
        constexpr PowerFaceMode kMode = decltype(mode)::value;
        PowerCellFunctor<scalar_t, 64, kMode> functor;
        functor.points = points.data_ptr<scalar_t>();
        functor.weights = weights.data_ptr<scalar_t>();
        functor.box = box.data_ptr<scalar_t>();
        functor.batch = batch.has_value() ? batch->data_ptr<int64_t>() : nullptr;
        functor.rows = rows.data_ptr<int64_t>();
        functor.grid = grid.view<scalar_t>();
        functor.sorted_weights = sorted_weights.data_ptr<scalar_t>();
        functor.cube_weight_max = cube_weight_max.data_ptr<scalar_t>();
        functor.weight_max = weight_max.data_ptr<double>();
        functor.volume = volume.data_ptr<scalar_t>();
        functor.centroid = centroid.data_ptr<scalar_t>();
        functor.second_moment = second_moment.data_ptr<scalar_t>();
        functor.status = status.data_ptr<int8_t>();
        functor.needed = needed.data_ptr<int32_t>();
        functor.radius = radius.data_ptr<float>();
        functor.face_count = face_count.data_ptr<int32_t>();
        functor.face_offsets = kFaces ? face_offsets.data_ptr<int64_t>() : nullptr;
        functor.face_target = face_target.data_ptr<int64_t>();
        functor.face_area = face_area.data_ptr<scalar_t>();
        functor.face_centroid = face_centroid.data_ptr<scalar_t>();
        functor.face_inertia = face_inertia.data_ptr<scalar_t>();
        functor.next_face =
            next_face.defined() ? reinterpret_cast<unsigned long long*>(next_face.data_ptr<int64_t>()) : nullptr;
        functor.capacity = faces;
        functor.face_first = face_first.data_ptr<int64_t>();
        functor.nearest_first = tuning.power_nearest_first;
        run_power_tier<Exec, scalar_t, kMode>(tier, m, tuning, functor);
      };
      if constexpr (kFaces) {
        launch(std::integral_constant<PowerFaceMode, PowerFaceMode::kFill>());
      } else if (next_face.defined()) {
        launch(std::integral_constant<PowerFaceMode, PowerFaceMode::kClaim>());
      } else {
        launch(std::integral_constant<PowerFaceMode, PowerFaceMode::kCount>());
      }
    });
  }
  const auto back = [&](const at::Tensor& t) { return on_host ? t.to(points_in.device()) : t; };
  return {PowerCellOutputs{back(volume), back(centroid), back(second_moment), back(status), back(needed), back(radius),
                           back(face_count)},
          back(face_first),
          PowerFaceOutputs{back(face_target), back(face_area), back(face_centroid), back(face_inertia)}};
}

template <typename Exec>
PowerCellsAndFaces power_cells(const at::Tensor& points, const at::Tensor& weights, const at::Tensor& box,
                               const c10::optional<at::Tensor>& batch, const at::Tensor& rows,
                               const at::Tensor& weight_max, int64_t tier, int64_t face_room) {
  const auto out = power_forward<Exec, false>(points, weights, box, batch, rows, weight_max, tier, {}, face_room);
  const PowerCellOutputs& c = std::get<0>(out);
  const PowerFaceOutputs& f = std::get<2>(out);
  return {std::get<0>(c), std::get<1>(c), std::get<2>(c), std::get<3>(c), std::get<4>(c), std::get<5>(c),
          std::get<6>(c), std::get<1>(out), std::get<0>(f), std::get<1>(f), std::get<2>(f), std::get<3>(f)};
}

template <typename Exec>
PowerFaceOutputs power_faces(const at::Tensor& points, const at::Tensor& weights, const at::Tensor& box,
                             const c10::optional<at::Tensor>& batch, const at::Tensor& rows,
                             const at::Tensor& weight_max, int64_t tier,
                             const at::Tensor& face_offsets) {
  return std::get<2>(power_forward<Exec, true>(points, weights, box, batch, rows, weight_max, tier,
                                              face_offsets, 0));
}

}  // namespace ops
}  // namespace torchvor
