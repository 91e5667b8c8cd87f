// ops::finish_giant_cells (ops/giant_cells.h), for both backends: the cells
// run on the host.
#include "../ops/giant_cells.h"

#include <ATen/Parallel.h>

#include <algorithm>
#include <utility>
#include <vector>

#include "../core/cell_faces.h"
#include "../core/unbounded_cell.h"
#include "../core/voronoi_cell.h"

namespace torchvor {
namespace ops {
namespace {

constexpr int64_t kFirstNeighbors = 65536;  // then 4x more, until the radius of security

// The faces of a computed giant cell (ClipFunctor::emit_faces): a
// bisector's point is found in the cell's list by its offset.
template <typename io_t>
int emit_faces(const core::UnboundedCell& unbounded, const io_t* points, int32_t cell, const std::vector<int32_t>& list,
               const io_t* box, const FaceOutputs<io_t>& to, int64_t step) {
  using T = core::DoubleDouble;
  const core::Vec3<T> seed = {T(points[3 * cell]), T(points[3 * cell + 1]), T(points[3 * cell + 2])};
  const core::Vec3<T> lo = core::Vec3<T>{T(box[0]), T(box[1]), T(box[2])} - seed;
  const core::Vec3<T> hi = core::Vec3<T>{T(box[3]), T(box[4]), T(box[5])} - seed;
  const auto target_of = [&](int, const core::Plane<T>& p) -> int32_t {
    const int wall = core::wall_of(p, lo, hi);
    if (wall >= 0) return core::wall_target(wall);
    const core::Vec3<T> r = {-p.normal.x, -p.normal.y, -p.normal.z};
    for (const int32_t j : list) {
      if (j < 0) break;
      if (T(points[3 * j]) - seed.x == r.x && T(points[3 * j + 1]) - seed.y == r.y &&
          T(points[3 * j + 2]) - seed.z == r.z) {
        return j;
      }
    }
    return core::kNoFace;
  };
  return emit_cell_faces(to, unbounded, target_of, step, cell, points, seed);
}

// Cell `cell` (a position) against its cloud's points, nearest first.
// With `faces`, its faces go to step `step`'s offset (ClipFunctor::emit_faces).
template <typename io_t>
CellRecord<io_t> giant_cell(const io_t* points, int64_t n, const int64_t* batch, const io_t* box, int32_t cell,
                            const FaceOutputs<io_t>* faces, int64_t step) {
  const int64_t b = batch != nullptr ? batch[cell] : 0;
  std::vector<std::pair<double, int32_t>> by_distance;  // (squared distance, position), the others of the cloud
  const double seed[3] = {double(points[3 * cell]), double(points[3 * cell + 1]), double(points[3 * cell + 2])};
  for (int64_t j = 0; j < n; ++j) {
    if (j == cell || (batch != nullptr && batch[j] != b)) continue;
    const double dx = double(points[3 * j]) - seed[0], dy = double(points[3 * j + 1]) - seed[1],
                 dz = double(points[3 * j + 2]) - seed[2];
    by_distance.push_back({dx * dx + dy * dy + dz * dz, int32_t(j)});
  }
  const int64_t others = int64_t(by_distance.size());
  std::vector<int32_t> list;
  core::UnboundedCell unbounded;
  core::CellIntegrals<core::DoubleDouble> result;
  for (int64_t listed = std::min(kFirstNeighbors, others);; listed = std::min(4 * listed, others)) {
    std::partial_sort(by_distance.begin(), by_distance.begin() + listed, by_distance.end());
    list.resize(listed);
    for (int64_t i = 0; i < listed; ++i) list[i] = by_distance[i].second;
    if (listed == others) list.push_back(-1);  // the whole cloud: its end
    result = core::compute_cell(unbounded, points, cell, list.data(), 1, int32_t(list.size()), box + 6 * b,
                                core::DoubleDouble(core::ClipTolerance<core::DoubleDouble>::value),
                                /*tetrahedron_start=*/false);
    if (result.status != core::kSecurityRadiusNotReached || listed == others) break;
  }
  int num_faces = 0;
  if (faces != nullptr && result.status == core::kSuccess) num_faces = emit_faces(unbounded, points, cell, list, box + 6 * b, *faces, step);
  TORCH_CHECK(num_faces <= 0xffff, "torchvor: voronoi_graph: cell ", cell, " has ", num_faces,
              " faces, more than the 65535 a cell may have");
  return {static_cast<io_t>(result.volume),
          {static_cast<io_t>(result.centroid.x), static_cast<io_t>(result.centroid.y),
           static_cast<io_t>(result.centroid.z)},
          static_cast<io_t>(result.second_moment), result.radius, result.neighbors, result.status,
          static_cast<uint16_t>(num_faces)};
}

}  // namespace

int64_t finish_giant_cells(const at::Tensor& points, const at::Tensor& box, const c10::optional<at::Tensor>& batch,
                           const at::Tensor& cells, PositionOutputs& out) {
  const at::Tensor status = out.status.index_select(0, cells.to(at::kLong)).to(at::kCPU);
  const at::Tensor cells_cpu = cells.to(at::kCPU);
  std::vector<int32_t> giant;
  for (int64_t i = 0; i < cells_cpu.size(0); ++i) {
    const int8_t code = status.data_ptr<int8_t>()[i];
    if (code == core::kTooManyPlanes || code == core::kTooManyVertices) giant.push_back(cells_cpu.data_ptr<int32_t>()[i]);
  }
  const int64_t m = int64_t(giant.size());
  if (m == 0) return 0;
  const at::Tensor points_cpu = points.to(at::kCPU).contiguous();
  const at::Tensor box_cpu = box.to(at::kCPU).contiguous();
  const at::Tensor batch_cpu = batch.has_value() ? batch->to(at::kCPU).contiguous() : at::Tensor();
  const at::Tensor rows = at::from_blob(giant.data(), {m}, at::kInt).to(at::kLong);
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "torchvor::finish_giant_cells", [&] {
    const at::Tensor records = empty_records<scalar_t>(m, points_cpu.options());
    CellRecord<scalar_t>* record = reinterpret_cast<CellRecord<scalar_t>*>(records.data_ptr<uint8_t>());
    const int64_t n = points_cpu.size(0);
    // A cell holds a list of its cloud (16 bytes a point): at most ~2 GiB of
    // lists at once (at::parallel_for runs at most m / grain chunks at once).
    const int64_t at_once = std::max<int64_t>(1, (int64_t(1) << 31) / std::max<int64_t>(1, 16 * n));
    const int64_t grain = (m + at_once - 1) / at_once;
    HostFaces host_faces;
    if (out.face_tensors != nullptr) host_faces = HostFaces::make<scalar_t>(*out.face_tensors, rows);
    const FaceOutputs<scalar_t>* faces =
        out.face_tensors != nullptr ? reinterpret_cast<const FaceOutputs<scalar_t>*>(host_faces.bytes.data_ptr<uint8_t>())
                                    : nullptr;
    at::parallel_for(0, m, grain, [&](int64_t begin, int64_t end) {
      for (int64_t i = begin; i < end; ++i) {
        record[i] = giant_cell(points_cpu.data_ptr<scalar_t>(), n,
                               batch.has_value() ? batch_cpu.data_ptr<int64_t>() : nullptr,
                               box_cpu.data_ptr<scalar_t>(), giant[i], faces, i);
      }
    });
    if (out.face_tensors != nullptr) host_faces.copy_back(*out.face_tensors, rows);
    at::Tensor codes = at::empty({m}, at::kChar);
    for (int64_t i = 0; i < m; ++i) codes.data_ptr<int8_t>()[i] = record[i].status;
    const at::Tensor device_rows = rows.to(out.records.device());
    out.records.index_copy_(0, device_rows, records.to(out.records.device()));
    out.status.index_copy_(0, device_rows, codes.to(out.status.device()));
  });
  return m;
}

}  // namespace ops
}  // namespace torchvor
