#include "checks.h"

#include <cmath>
#include <string>
#include <utility>
#include <vector>

namespace torchvor {
namespace ops {
namespace {

// "(20, 2)", the way Python prints a shape.
std::string shape_string(const at::Tensor& t) {
  std::string text = "(";
  for (int64_t d = 0; d < t.dim(); ++d) {
    if (d > 0) text += ", ";
    text += std::to_string(t.size(d));
  }
  return text + (t.dim() == 1 ? ",)" : ")");
}

void check_points(const at::Tensor& points, const char* name) {
  TORCH_CHECK_TYPE(points.scalar_type() == at::kFloat || points.scalar_type() == at::kDouble,
                   "torchvor: ", name, " must be float32 or float64, got ",
                   c10::toString(points.scalar_type()));
  TORCH_CHECK_VALUE(points.dim() == 2 && points.size(1) == 3, "torchvor: ", name,
                    " must have shape (N, 3), got ", shape_string(points));
  TORCH_CHECK_VALUE(points.size(0) < (int64_t(1) << 31) - 1, "torchvor: ", name,
                    " has too many points (at most 2^31 - 2)");
}

void check_same_device(const at::Tensor& a, const char* a_name, const at::Tensor& b,
                              const char* b_name) {
  TORCH_CHECK_VALUE(a.device() == b.device(), "torchvor: ", b_name, " is on ", b.device().str(),
                    " but ", a_name, " is on ", a.device().str());
}

// A batch vector (PyG convention): int64, shape (n,), sorted, non-negative.
// Returns the number of batch elements it implies (max + 1; 1 if undefined).
int64_t check_batch(const c10::optional<at::Tensor>& batch, int64_t n, const at::Tensor& like,
                           const char* name) {
  if (!batch.has_value()) return 1;
  const at::Tensor& b = *batch;
  TORCH_CHECK_TYPE(b.scalar_type() == at::kLong, "torchvor: ", name, " must be int64, got ",
                   c10::toString(b.scalar_type()));
  TORCH_CHECK_VALUE(b.dim() == 1 && b.size(0) == n, "torchvor: ", name, " must have shape (",
                    n, ",), got ", shape_string(b));
  check_same_device(like, "points", b, name);
  if (n == 0) return 1;
  TORCH_CHECK_VALUE(b.min().item<int64_t>() >= 0, "torchvor: ", name,
                    " must be non-negative");
  if (n > 1) {
    TORCH_CHECK_VALUE((b.slice(0, 1) >= b.slice(0, 0, n - 1)).all().item<bool>(), "torchvor: ",
                      name, " must be sorted in non-decreasing order");
  }
  return b[n - 1].item<int64_t>() + 1;
}

// `other` (a points-like tensor) must share the dtype and device of points.
void check_like_points(const at::Tensor& points, const at::Tensor& other, const char* name) {
  check_same_device(points, "points", other, name);
  TORCH_CHECK_TYPE(other.scalar_type() == points.scalar_type(), "torchvor: ", name,
                   " must have the dtype of points (", c10::toString(points.scalar_type()),
                   "), got ", c10::toString(other.scalar_type()));
}

}  // namespace

void ValueChecks::add(at::Tensor holds, std::string message) {
  conditions_.push_back(std::move(holds));
  messages_.push_back(std::move(message));
}

void ValueChecks::finite(const at::Tensor& values, const char* name) {
  add(at::isfinite(values).all(), std::string("torchvor: ") + name + " contains NaN or Inf coordinates");
}

void ValueChecks::verify(const double* holds) const {
  for (size_t c = 0; c < messages_.size(); ++c) TORCH_CHECK_VALUE(holds[c] != 0.0, messages_[c]);
}

void ValueChecks::run() const {
  if (conditions_.empty()) return;
  const at::Tensor holds = at::stack(conditions_).to(at::kDouble).to(at::kCPU).contiguous();
  verify(holds.data_ptr<double>());
}

int64_t check_knn_inputs(const at::Tensor& points, const at::Tensor& queries, int64_t k,
                         const c10::optional<at::Tensor>& points_batch,
                         const c10::optional<at::Tensor>& queries_batch, bool exclude_self) {
  check_points(points, "points");
  check_points(queries, "queries");
  check_like_points(points, queries, "queries");
  TORCH_CHECK_VALUE(k >= 1, "torchvor: k must be at least 1, got ", k);
  TORCH_CHECK_VALUE(k < (int64_t(1) << 31), "torchvor: k is too large: ", k);
  TORCH_CHECK_VALUE(points_batch.has_value() == queries_batch.has_value(),
                    "torchvor: give both batch and query_batch, or neither");
  const int64_t n = points.size(0), m = queries.size(0);
  if (exclude_self) {
    TORCH_CHECK_VALUE(n == m, "torchvor: exclude_self needs queries to be the points");
  }
  const int64_t points_batches = check_batch(points_batch, n, points, "batch");
  const int64_t query_batches = check_batch(queries_batch, m, points, "query_batch");
  return std::max(points_batches, query_batches);
}

ValueChecks knn_value_checks(const at::Tensor& points, const at::Tensor& queries) {
  ValueChecks values;
  values.finite(points, "points");
  values.finite(queries, "queries");
  return values;
}

int64_t check_voronoi_inputs(const at::Tensor& points, const at::Tensor& box,
                             const c10::optional<at::Tensor>& batch, c10::optional<int64_t> k,
                             int64_t memory_budget) {
  check_points(points, "points");
  check_like_points(points, box, "box");
  TORCH_CHECK_VALUE(box.dim() == 3 && box.size(1) == 2 && box.size(2) == 3,
                    "torchvor: box must have shape (B, 2, 3), got ", shape_string(box));
  if (k.has_value()) TORCH_CHECK_VALUE(*k >= 1, "torchvor: k must be at least 1, got ", *k);
  TORCH_CHECK_VALUE(memory_budget >= 1, "torchvor: memory_budget must be positive");
  const int64_t n = points.size(0);
  const int64_t num_boxes = box.size(0);
  const int64_t batches = check_batch(batch, n, points, "batch");
  TORCH_CHECK_VALUE(batch.has_value() || num_boxes == 1,
                    "torchvor: without a batch vector, box must have shape (1, 2, 3)");
  TORCH_CHECK_VALUE(num_boxes == 1 || batches <= num_boxes, "torchvor: batch refers to ", batches,
                    " point clouds but box holds ", num_boxes, " boxes (give one box for all, or one per cloud)");
  return batches;
}

void check_cell_rows(const c10::optional<at::Tensor>& rows, const at::Tensor& points, ValueChecks& values) {
  if (!rows.has_value()) return;
  const at::Tensor& r = *rows;
  TORCH_CHECK_TYPE(r.scalar_type() == at::kLong, "torchvor: rows must be int64, got ", c10::toString(r.scalar_type()));
  TORCH_CHECK_VALUE(r.dim() == 1, "torchvor: rows must have shape (M,), got ", shape_string(r));
  check_same_device(points, "points", r, "rows");
  if (r.size(0) > 0) {
    values.add(((r >= 0) & (r < points.size(0))).all(),
               "torchvor: rows must be indices of points, in [0, " + std::to_string(points.size(0)) + ")");
  }
}

void check_voronoi_values(const at::Tensor& bounds, const double* box, int64_t num_boxes) {
  // The points first: with box=None the box is their bounding box, and a
  // NaN point would otherwise be reported as a NaN box.
  const double* row = bounds.data_ptr<double>();
  for (int64_t b = 0; b < bounds.size(0); ++b) {
    if (row[7 * b + 6] == 0.0) continue;  // no points
    for (int v = 0; v < 6; ++v) {  // a NaN or Inf point makes its bounds NaN or Inf
      TORCH_CHECK_VALUE(std::isfinite(row[7 * b + v]), "torchvor: points contains NaN or Inf coordinates");
    }
  }
  for (int64_t v = 0; v < 6 * num_boxes; ++v) {
    TORCH_CHECK_VALUE(std::isfinite(box[v]), "torchvor: box contains NaN or Inf coordinates");
  }
  static const char* const kAxis[3] = {"x", "y", "z"};
  for (int64_t b = 0; b < num_boxes; ++b) {
    for (int a = 0; a < 3; ++a) {
      TORCH_CHECK_VALUE(box[6 * b + a] <= box[6 * b + 3 + a],
                        "torchvor: box must satisfy lo <= hi on every axis");
      // A flat box holds no volume: every cell would be empty. Only the
      // boxes of clouds with points matter (an empty cloud's box is unused).
      const bool has_points = b >= bounds.size(0) || row[7 * b + 6] != 0.0;
      TORCH_CHECK_VALUE(!has_points || box[6 * b + a] < box[6 * b + 3 + a], "torchvor: box",
                        num_boxes > 1 ? " " + std::to_string(b) : std::string(), " is flat along ", kAxis[a],
                        " (lo = hi = ", box[6 * b + a], "): Voronoi cells need a box of positive size on every "
                        "axis. With box=None the box is the points' bounding box, so the points are coplanar "
                        "there: give a box explicitly");
    }
  }
  // Inside the box: each batch element's bounding box inside its box (both
  // exact in double, so this is the comparison lo <= p <= hi itself).
  for (int64_t b = 0; b < bounds.size(0); ++b, row += 7) {
    if (row[6] == 0.0) continue;  // no points
    for (int a = 0; a < 3; ++a) {
      TORCH_CHECK_VALUE(row[a] >= box[6 * b + a] && row[3 + a] <= box[6 * b + 3 + a],
                        "torchvor: points must lie inside box (lo <= p <= hi)");
    }
  }
}

void check_lloyd_step_inputs(int64_t sample_stride, int64_t histogram_bins) {
  TORCH_CHECK_VALUE(sample_stride >= 1, "torchvor: sample_stride must be >= 1, got ", sample_stride);
  TORCH_CHECK_VALUE(histogram_bins >= 1 && histogram_bins <= (1 << 20),
                    "torchvor: histogram_bins must be in [1, 1048576], got ", histogram_bins);
}

}  // namespace ops
}  // namespace torchvor
