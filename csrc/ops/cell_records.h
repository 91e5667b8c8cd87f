// The outputs of the Voronoi passes, by grid position, and their way to the
// caller's rows.
#pragma once

#include <ATen/ATen.h>

#include <algorithm>
#include <cstddef>
#include <cstring>
#include <type_traits>
#include <functional>
#include <tuple>

#include "../core/cell_faces.h"
#include "../core/common.h"
#include "../core/status.h"

namespace torchvor {
namespace ops {

// One cell's outputs as one record (32 bytes in float32, 64 in float64), so
// that the gather to the caller's rows (ToRowsFunctor) reads one or two
// memory sectors a cell instead of one an output array.
template <typename io_t>
struct alignas(16) CellRecord {
  io_t volume;
  io_t centroid[3];
  io_t second_moment;
  float radius;        // core::CellIntegrals::radius
  int32_t num_neighbors;
  int8_t status;
  uint16_t num_faces;  // voronoi_graph: the cell's neighbour faces (for_each_face); 0 otherwise
};

// Where voronoi_graph's passes write a computed cell's faces
// (ClipFunctor::emit_faces), on the device that runs them. The record index
// (a position, or the step in a host pass) picks the cell's offset and walls.
// The offsets are given (`offset`: the count pass's layout), or each cell
// claims its range (`next_face`: one pass, no counts before), or neither:
// the faces are only counted (num_faces).
template <typename io_t>
struct FaceOutputs {
  const int64_t* offset;  // by record: the cell's first face, or nullptr
  // Claims: a cell takes a range as long as its bisector planes (a bound on
  // its faces) from *next_face and writes its first face to claimed[record];
  // a range past `capacity` is not written (claimed -1) and *next_face then
  // ends past `capacity`: the caller lays the faces out from the counts and
  // runs the passes again.
  unsigned long long* next_face;  // or nullptr
  int64_t* claimed;               // by record
  int64_t capacity;               // the faces' arrays' rows
  int32_t* neighbor;      // (E,) the position of the point across each face
  io_t* area;             // (E,)
  io_t* centroid;         // (E, 3)
  io_t* wall_area;        // by record, 6 each: -x, +x, -y, +y, -z, +z (zero where none)
  io_t* moments;          // (E, 9) core::Face's second (6) and third (3) moments, or nullptr: none asked
  // voronoi_cells' backward instead of faces (FaceGradient): each cell's
  // output gradients by position, and where each computed cell's point
  // gets its faces' terms (by record, 3 each); nullptr: not the backward.
  const double* upstream;  // (N, 5): FaceGradient's g_m, g_M (3), g_I
  double* gradient;
  bool gradient_moments;   // the faces' moments are needed (g_M or g_I may be nonzero)

  // Where record `record`'s faces go (-1: counted only), claiming a range
  // of `bound` faces where the faces are claimed.
  TV_HD int64_t first_face(int64_t record, int bound) const {
    if (offset != nullptr) return offset[record];
    if (next_face == nullptr) return -1;
    const unsigned long long start = core::fetch_add(next_face, static_cast<unsigned long long>(bound));
    const int64_t first = int64_t(start) + bound <= capacity ? int64_t(start) : -1;
    claimed[record] = first;
    return first;
  }
};

// voronoi_cells' backward, summed over one cell's faces with no atomics: the
// terms of dL/dx_s (s the cell's point) from the outputs of cell s and of
// each neighbour n across a face (both cells compute the face; the rows of
// `upstream` by position are dL/dm, dL/dM and dL/dI of a cell's volume m,
// first moment M about its point and second moment I, with the centroid's
// share already in dL/dm and dL/dM). Per face (area a, centroid c, d =
// |x_n - x_s|, w_s = c - x_s, w_n = c - x_n, moments S and T about c),
// GRADIENTS.md's formulas give
//   from s: (a g_m w_s + S g_M + a (g_M . w_s) w_s + g_I (R_s + Q_s w_s)) / d,
//   from n: -(a g_m w_s + S g_M + a (g_M . w_n) w_s + g_I (R_n + Q_n w_s)) / d,
// Q = tr S + a |w|^2, R = T + 2 S w (each with its cell's g and w). The
// cell's own term of I (the integrand's x_s) is the caller's.
struct FaceGradient {
  const double* upstream;
  const double* own;  // upstream's row of the cell
  core::Vec3<double> sum = {0.0, 0.0, 0.0};

  // The face across to neighbour `n` at offset `r` = x_n - x_s (kMoments:
  // the face carries its moments; needed where `moments`).
  template <bool kMoments, typename T>
  TV_HD void add(int32_t n, core::Vec3<T> r, const core::Face<T>& face) {
    const auto wide = [](core::Vec3<T> v) {
      return core::Vec3<double>{static_cast<double>(v.x), static_cast<double>(v.y), static_cast<double>(v.z)};
    };
    const double a = static_cast<double>(face.area);
    const core::Vec3<double> offset = wide(r), w_s = wide(face.centroid), w_n = w_s - offset;
    const double* other = upstream + 5 * int64_t(n);
    core::Vec3<double> term = (a * (own[0] - other[0])) * w_s;
    if constexpr (kMoments) {
      double S[6];
      for (int m = 0; m < 6; ++m) S[m] = static_cast<double>(face.second[m]);
      const core::Vec3<double> T3 = wide(face.third);
      const auto S_times = [&](core::Vec3<double> v) {
        return core::Vec3<double>{S[0] * v.x + S[3] * v.y + S[4] * v.z, S[3] * v.x + S[1] * v.y + S[5] * v.z,
                                  S[4] * v.x + S[5] * v.y + S[2] * v.z};
      };
      const double trace = S[0] + S[1] + S[2];
      const core::Vec3<double> G_s = core::load_vec3(own + 1), G_n = core::load_vec3(other + 1);
      const core::Vec3<double> R_s = T3 + 2.0 * S_times(w_s), R_n = T3 + 2.0 * S_times(w_n);
      const double Q_s = trace + a * core::dot(w_s, w_s), Q_n = trace + a * core::dot(w_n, w_n);
      term = term + S_times(G_s - G_n) + (a * (core::dot(G_s, w_s) - core::dot(G_n, w_n))) * w_s +
             own[4] * (R_s + Q_s * w_s) - other[4] * (R_n + Q_n * w_s);
    }
    sum = sum + (1.0 / sqrt(core::dot(offset, offset))) * term;
  }
};

// One face of a computed cell into `to` (ClipFunctor::emit_faces, the giant
// cells): record `record`'s face `slot` (-1: a wall, `target` names it) at
// `first + slot` (first -1: not written), its centroid from the seed's frame.
template <bool kMoments, typename io_t, typename T>
TV_HD void store_face(const FaceOutputs<io_t>& to, int64_t record, int64_t first, int slot, int32_t target,
                      core::Vec3<T> seed, const core::Face<T>& face) {
  if (slot < 0) {
    if (to.wall_area != nullptr) to.wall_area[6 * record + core::wall_of_target(target)] = static_cast<io_t>(face.area);
    return;
  }
  if (first < 0) return;
  const int64_t e = first + slot;
  const core::Vec3<T> centroid = seed + face.centroid;
  to.neighbor[e] = target;
  to.area[e] = static_cast<io_t>(face.area);
  to.centroid[3 * e] = static_cast<io_t>(centroid.x);
  to.centroid[3 * e + 1] = static_cast<io_t>(centroid.y);
  to.centroid[3 * e + 2] = static_cast<io_t>(centroid.z);
  if constexpr (kMoments) {
    for (int m = 0; m < 6; ++m) to.moments[9 * e + m] = static_cast<io_t>(face.second[m]);
    to.moments[9 * e + 6] = static_cast<io_t>(face.third.x);
    to.moments[9 * e + 7] = static_cast<io_t>(face.third.y);
    to.moments[9 * e + 8] = static_cast<io_t>(face.third.z);
  }
}

// The faces of a computed cell (core::for_each_face) into `to`: written at
// record `record`'s offset with their moments where asked, counted only, or
// (the backward) summed into the gradient of the cell's point, at position
// `position` with coordinates `seed` (FaceGradient). `points` by position.
// Returns the neighbour faces' count.
template <typename io_t, typename Cell, typename TargetOf, typename T = typename Cell::Scalar>
TV_HD int emit_cell_faces(const FaceOutputs<io_t>& to, const Cell& cell, TargetOf&& target_of, int64_t record,
                          int64_t position, const io_t* points, core::Vec3<T> seed) {
  // The faces with or without their moments (std::true_type or std::false_type).
  const auto faces = [&](auto with_moments) {
    constexpr bool kMoments = decltype(with_moments)::value;
    if (to.upstream == nullptr) {
      // A neighbour face's plane is a bisector: planes 0-5 are the box's.
      const int bound = cell.plane_count() - core::kBoxPlanes;
      const int64_t first = to.first_face(record, bound);
      const int count = core::for_each_face<kMoments>(cell, target_of, [&](int slot, int32_t target,
                                                                            const core::Face<T>& face) {
        store_face<kMoments>(to, record, to.next_face == nullptr || slot < bound ? first : -1, slot, target, seed,
                             face);
      });
      if (count > bound && to.next_face != nullptr) {  // never expected: lay the faces out from the counts
        to.claimed[record] = -1;
        core::fetch_add(to.next_face, static_cast<unsigned long long>(to.capacity) + 1);
      }
      return count;
    }
    FaceGradient gradient{to.upstream, to.upstream + 5 * position};
    const int count = core::for_each_face<kMoments>(cell, target_of, [&](int, int32_t target, const core::Face<T>& face) {
      if (target < 0) return;  // the walls stay
      const core::Vec3<T> r = core::Vec3<T>{T(points[3 * target]), T(points[3 * target + 1]),
                                            T(points[3 * target + 2])} - seed;
      gradient.add<kMoments>(target, r, face);
    });
    to.gradient[3 * record] = gradient.sum.x;
    to.gradient[3 * record + 1] = gradient.sum.y;
    to.gradient[3 * record + 2] = gradient.sum.z;
    return count;
  };
  const bool moments = to.upstream != nullptr ? to.gradient_moments : to.moments != nullptr;
  return moments ? faces(std::true_type()) : faces(std::false_type());
}

// voronoi_graph's faces as tensors (FaceOutputs): by position on the
// points' device, or by step in a host pass (HostFaces).
struct FaceTensors {
  at::Tensor count;      // (N,) int32: the count pass's num_faces (undefined in the count pass)
  at::Tensor offset;     // (N,) int64: the cell's first face (undefined in the count pass; claimed: -1 none)
  at::Tensor next_face;  // (1,) int64: claims (FaceOutputs::next_face), or undefined: `offset` is given
  at::Tensor neighbor;   // (E,) int32
  at::Tensor area;       // (E,)
  at::Tensor centroid;   // (E, 3)
  at::Tensor wall_area;  // (N, 6)
  at::Tensor moments;    // (E, 9), or undefined: none asked
  // voronoi_cells' backward (FaceOutputs::upstream), instead of the faces:
  at::Tensor upstream;   // (N, 5) float64 by position
  at::Tensor gradient;   // (N, 3) float64 by position, zeros: each computed cell's point's faces' terms
  bool gradient_moments = false;

  // The pointers as a FaceOutputs in bytes on `device`, for the passes' functors.
  template <typename io_t>
  at::Tensor outputs_on(const at::Device& device) const {
    const auto pointer = [](const at::Tensor& t, auto* type) -> decltype(type) {
      using V = std::remove_const_t<std::remove_pointer_t<decltype(type)>>;
      return t.defined() && t.numel() > 0 ? t.data_ptr<V>() : nullptr;
    };
    const bool claims = next_face.defined();
    const FaceOutputs<io_t> view{offset.defined() && !claims ? offset.data_ptr<int64_t>() : nullptr,
                                 claims ? reinterpret_cast<unsigned long long*>(next_face.data_ptr<int64_t>()) : nullptr,
                                 claims ? offset.data_ptr<int64_t>() : nullptr,
                                 neighbor.defined() ? neighbor.numel() : 0,
                                 pointer(neighbor, static_cast<int32_t*>(nullptr)),
                                 pointer(area, static_cast<io_t*>(nullptr)),
                                 pointer(centroid, static_cast<io_t*>(nullptr)),
                                 pointer(wall_area, static_cast<io_t*>(nullptr)),
                                 pointer(moments, static_cast<io_t*>(nullptr)),
                                 pointer(upstream, static_cast<const double*>(nullptr)),
                                 pointer(gradient, static_cast<double*>(nullptr)),
                                 gradient_moments};
    at::Tensor bytes = at::empty({int64_t(sizeof(view))}, at::TensorOptions().dtype(at::kByte));
    std::memcpy(bytes.data_ptr<uint8_t>(), &view, sizeof(view));
    return bytes.to(device);
  }
};

// The outputs by grid position (the numbering the passes work in): one
// CellRecord<io_t> a position, in a byte tensor, and the caller's row of
// each position. The statuses are kept twice: a byte a cell for the scan
// after each pass (which then reads a byte, not a record, a cell), and in
// the records for the gather to the caller's rows (one sector a cell).
struct PositionOutputs {
  at::Tensor records;          // (N, sizeof(CellRecord<io_t>)) uint8
  at::Tensor status;           // (N,) int8, the records' statuses again
  at::Tensor row_of_position;  // (N,) int32
  at::Tensor position_of_row;  // (N,) int32, its inverse: the first pass's status read computes it
  // voronoi_graph: where the passes write faces (FaceTensors::outputs_on), or undefined.
  at::Tensor faces;
  const FaceTensors* face_tensors = nullptr;  // the same as tensors

  template <typename io_t>
  CellRecord<io_t>* data() const {
    return reinterpret_cast<CellRecord<io_t>*>(records.data_ptr<uint8_t>());
  }
  template <typename io_t>
  const FaceOutputs<io_t>* face_outputs() const {
    return faces.defined() ? reinterpret_cast<const FaceOutputs<io_t>*>(faces.data_ptr<uint8_t>()) : nullptr;
  }
  // (N,) int32 view of the records' neighbour counts.
  template <typename io_t>
  at::Tensor num_neighbors() const {
    return records.view(at::kInt).select(1, offsetof(CellRecord<io_t>, num_neighbors) / sizeof(int32_t));
  }
};

// (N,) int32 copy of the records' face counts (voronoi_graph's count pass).
template <typename io_t>
at::Tensor face_counts(const at::Tensor& records) {
  const at::Tensor words = records.view(at::kShort).select(1, offsetof(CellRecord<io_t>, num_faces) / sizeof(int16_t));
  return words.to(at::kInt).bitwise_and(0xffff);
}

// A host pass's faces (clip_chunk_on_host, finish_giant_cells): written on
// the CPU step by step for `cells` (positions), then copied into the
// positions' ranges of the device's faces (copy_back). In the count pass
// only the records carry the counts.
struct HostFaces {
  FaceTensors part;   // by step, on the CPU
  at::Tensor bytes;   // part.outputs_on(CPU)
  at::Tensor global;  // (M,) int64: each face's index in the device's arrays

  // Where the device's faces are claimed, the host's cells are counted only
  // and the claims marked full: the caller lays the faces out from the counts.
  template <typename io_t>
  static HostFaces make(const FaceTensors& device, const at::Tensor& cells) {
    HostFaces host;
    const at::TensorOptions cpu = at::TensorOptions().device(at::kCPU);
    if (device.next_face.defined()) {
      if (cells.numel() > 0) device.next_face.fill_(device.neighbor.numel() + 1);
    } else if (device.offset.defined()) {
      const at::Tensor rows = cells.to(at::kLong);
      const at::Tensor counts = device.count.index_select(0, rows.to(device.count.device())).to(at::kCPU).to(at::kLong);
      const at::Tensor ends = counts.cumsum(0);
      host.part.offset = ends - counts;
      const int64_t m = counts.numel() > 0 ? ends[-1].item<int64_t>() : 0;
      const at::ScalarType dtype = c10::CppTypeToScalarType<io_t>::value;
      host.part.neighbor = at::empty({m}, cpu.dtype(at::kInt));
      host.part.area = at::empty({m}, cpu.dtype(dtype));
      host.part.centroid = at::empty({m, 3}, cpu.dtype(dtype));
      host.part.wall_area = at::zeros({cells.size(0), 6}, cpu.dtype(dtype));
      if (device.moments.defined()) host.part.moments = at::empty({m, 9}, cpu.dtype(dtype));
      const at::Tensor first = device.offset.index_select(0, rows.to(device.offset.device())).to(at::kCPU);
      host.global = at::repeat_interleave(first - host.part.offset, counts) + at::arange(m, cpu.dtype(at::kLong));
    }
    if (device.upstream.defined()) {  // the backward: every position's upstream (neighbours read theirs)
      host.part.upstream = device.upstream.to(at::kCPU).contiguous();
      host.part.gradient = at::zeros({cells.size(0), 3}, cpu.dtype(at::kDouble));
      host.part.gradient_moments = device.gradient_moments;
    }
    host.bytes = host.part.outputs_on<io_t>(at::kCPU);
    return host;
  }

  void copy_back(const FaceTensors& device, const at::Tensor& cells) const {
    if (device.gradient.defined()) {
      device.gradient.index_copy_(0, cells.to(at::kLong).to(device.gradient.device()),
                                  part.gradient.to(device.gradient.device()));
    }
    if (!device.offset.defined() || device.next_face.defined()) return;
    const at::Device to = device.wall_area.device();
    device.wall_area.index_copy_(0, cells.to(at::kLong).to(to), part.wall_area.to(to));
    if (global.numel() == 0) return;
    const at::Tensor at_faces = global.to(to);
    device.neighbor.index_copy_(0, at_faces, part.neighbor.to(to));
    device.area.index_copy_(0, at_faces, part.area.to(to));
    device.centroid.index_copy_(0, at_faces, part.centroid.to(to));
    if (device.moments.defined()) device.moments.index_copy_(0, at_faces, part.moments.to(to));
  }
};

template <typename io_t>
at::Tensor empty_records(int64_t n, const at::TensorOptions& options) {
  return at::empty({n, int64_t(sizeof(CellRecord<io_t>))}, options.dtype(at::kByte));
}

// The record of a cell that no pass wrote: "not computed" (NaN, status -1,
// 0 neighbours). Only the status bytes start so (poisoned_outputs); a pass
// writes the record of each of its cells, and after the passes the records
// of the cells still not computed are set to this (PoisonUnwrittenFunctor),
// which is cheaper than poisoning every record up front.
template <typename io_t>
TV_HD CellRecord<io_t> not_computed_record() {
  const io_t zero = io_t(0);
  const io_t nan = zero / zero;
  return {nan, {nan, nan, nan}, nan, NAN, 0, core::kNotComputed};
}

// The cells of `cells` whose status is still "not computed" get the record
// that says so.
template <typename io_t>
struct PoisonUnwrittenFunctor {
  const int32_t* cells;
  const int8_t* status;        // (N,) by position
  CellRecord<io_t>* records;   // (N,) by position

  TV_HD void operator()(int64_t i) const {
    const int32_t position = cells[i];
    if (status[position] == core::kNotComputed) records[position] = not_computed_record<io_t>();
  }
};

// The records of the exact copies set aside after the grid's points
// (set_copies_aside), positions first, first + 1, ...: DUPLICATE, volume 0,
// centroid the point, one neighbour (the point it copies, as a cell that
// finds its copy first among its neighbours).
template <typename io_t>
struct DuplicateRecordFunctor {
  const io_t* points;  // (N, 3) by position
  int64_t first;
  int8_t* status;             // (N,) by position
  CellRecord<io_t>* records;  // (N,) by position

  TV_HD void operator()(int64_t i) const {
    const int64_t p = first + i;
    records[p] = {io_t(0), {points[3 * p], points[3 * p + 1], points[3 * p + 2]}, io_t(0), 0.0f, 1, core::kDuplicate};
    status[p] = core::kDuplicate;
  }
};

// position_of_row[row_of_position[p]] = p for the rows in [first_row,
// end_row): the inverse of the grid order, over every position once per
// range of rows. The writes scatter, and a range that the GPU's L2 cache
// holds (Exec::cached_scatter_bytes) lets each sector fill there before it
// goes to memory.
struct InvertOrderFunctor {
  const int32_t* row_of_position;
  int32_t* position_of_row;
  int32_t first_row;
  int32_t end_row;

  TV_HD void operator()(int64_t p) const {
    const int32_t row = row_of_position[p];
    if (row >= first_row && row < end_row) position_of_row[row] = static_cast<int32_t>(p);
  }
};

// The inverse of the grid order (N,) int32 from `row_of_position`, in
// ranges of rows that fit the cache (InvertOrderFunctor): only the GPU
// splits large inputs. `test_range_bytes` > 0 (tests only) sets the bytes a
// range writes, so that small inputs take several ranges too.
template <typename Exec>
at::Tensor invert_order(const at::Tensor& row_of_position, int64_t test_range_bytes) {
  const int64_t n = row_of_position.size(0);
  const at::Tensor position_of_row = Exec::empty({n}, row_of_position.options());
  const int64_t range_bytes = test_range_bytes > 0 ? test_range_bytes : Exec::cached_scatter_bytes();
  const int64_t rows_per_range = std::max<int64_t>(1, range_bytes / int64_t(sizeof(int32_t)));
  for (int64_t first = 0; first < n; first += rows_per_range) {
    Exec::for_each(n, InvertOrderFunctor{row_of_position.data_ptr<int32_t>(), position_of_row.data_ptr<int32_t>(),
                                         static_cast<int32_t>(first),
                                         static_cast<int32_t>(std::min(n, first + rows_per_range))});
  }
  return position_of_row;
}

// The caller's row `row` of the five outputs from the record at its grid
// position, in one kernel. It gathers (scattered reads, rows written in
// order) rather than scatters: partial-sector writes of five arrays are slow
// once the outputs outgrow the L2 cache, and only InvertOrderFunctor
// scatters, a single int32 array. Without `position_of_row`, row p is
// position p (outputs in grid order).
template <typename io_t>
struct ToRowsFunctor {
  const int32_t* position_of_row;  // (N,), or nullptr: the identity
  const CellRecord<io_t>* records;
  io_t* volume;         // (N,)
  io_t* centroid;       // (N, 3)
  io_t* second_moment;  // (N,)
  int8_t* status;       // (N,)
  int32_t* num_neighbors;  // (N,)
  io_t* radius;         // (N,)

  TV_HD void operator()(int64_t row) const {
    const CellRecord<io_t> record = records[position_of_row ? position_of_row[row] : row];
    volume[row] = record.volume;
    centroid[3 * row] = record.centroid[0];
    centroid[3 * row + 1] = record.centroid[1];
    centroid[3 * row + 2] = record.centroid[2];
    second_moment[row] = record.second_moment;
    status[row] = record.status;
    num_neighbors[row] = record.num_neighbors;
    radius[row] = static_cast<io_t>(record.radius);
  }
};

using CallerOutputs = std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor>;
using GridOrderOutputs = std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor>;

// What the ops return: the six outputs (volume, centroid, second_moment,
// status, num_neighbors, radius), in the caller's rows, or (grid_order) by grid
// position with `order`, (N,) int64, the caller's row of each position.
struct VoronoiOutputs {
  CallerOutputs cells;
  at::Tensor order;          // undefined unless grid_order
  int64_t first_pass_k = 0;  // the caller's k or the pilot's, capped by the largest cloud; 0: no pass ran
  at::Tensor face_count;       // voronoi_graph: (N,) int32 by position (num_faces)
  at::Tensor row_of_position;  // voronoi_graph: (N,) int32
};

// Work that a call launches on its outputs before the op returns
// (torchvor::lloyd_step's move and sums, which the host then reads).
// voronoi_passes launches it before the first status read, the last one of
// most calls, so that the device runs it while the host waits for that read
// (no idle device, no second read); and once more after the passes if a
// later pass or the poison of unwritten cells changed the outputs since
// (that launch's results replace the first's).
using LaunchOnOutputs = std::function<void(const VoronoiOutputs&)>;

// The five outputs from the records by position: in the caller's rows (with
// `rows`, only those, in their order), or in grid order with the order
// (torchvor::voronoi_cells_grid_order, which saves the inverse order and the
// scattered gather: Lloyd keeps its points in grid order, and then the next
// call's grid order is nearly the identity).
template <typename Exec, typename io_t>
VoronoiOutputs finish_outputs(const PositionOutputs& in, const at::TensorOptions& options, bool grid_order,
                              const c10::optional<at::Tensor>& rows = c10::nullopt) {
  TORCH_INTERNAL_ASSERT(!(grid_order && rows.has_value()), "rows: caller's order only");
  const int64_t n = rows.has_value() ? rows->size(0) : in.records.size(0);
  const at::Tensor volume = Exec::empty({n}, options);
  const at::Tensor centroid = Exec::empty({n, 3}, options);
  const at::Tensor second_moment = Exec::empty({n}, options);
  const at::Tensor status = Exec::empty({n}, options.dtype(at::kChar));
  const at::Tensor num_neighbors = Exec::empty({n}, options.dtype(at::kInt));
  const at::Tensor radius = Exec::empty({n}, options);
  VoronoiOutputs out;
  if (grid_order) {
    out.order = n > 0 ? in.row_of_position.to(at::kLong) : Exec::empty({0}, options.dtype(at::kLong));
  }
  if (n > 0) {
    at::Tensor position_of_row;
    if (!grid_order) {
      TORCH_CHECK(in.position_of_row.defined(), "torchvor: internal error: the inverse order was not computed");
      position_of_row = rows.has_value() ? in.position_of_row.index_select(0, *rows) : in.position_of_row;
    }
    Exec::for_each(n, ToRowsFunctor<io_t>{grid_order ? nullptr : position_of_row.data_ptr<int32_t>(),
                                          in.data<io_t>(), volume.data_ptr<io_t>(), centroid.data_ptr<io_t>(),
                                          second_moment.data_ptr<io_t>(), status.data_ptr<int8_t>(),
                                          num_neighbors.data_ptr<int32_t>(), radius.data_ptr<io_t>()});
  }
  out.cells = {volume, centroid, second_moment, status, num_neighbors, radius};
  return out;
}

// The outputs by position, every status "not computed" (`status`, from
// not_computed_statuses); the records are written by the passes (and by
// PoisonUnwrittenFunctor for the cells that none wrote).
template <typename io_t>
PositionOutputs poisoned_outputs(const at::Tensor& status, const at::TensorOptions& options) {
  PositionOutputs out;
  out.records = empty_records<io_t>(status.size(0), options);
  out.status = status;
  return out;
}

inline at::Tensor not_computed_statuses(int64_t n, const at::TensorOptions& options) {
  return at::full({n}, int(core::kNotComputed), options.dtype(at::kChar));
}

}  // namespace ops
}  // namespace torchvor
