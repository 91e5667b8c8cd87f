// Argument checks of every op. They raise Python exceptions that name the
// argument: TORCH_CHECK_VALUE -> ValueError, TORCH_CHECK_TYPE -> TypeError.
//
// Defined once in checks.cpp, so both backends share one set of messages.
#pragma once

#include <ATen/ATen.h>

#include <cstdint>
#include <string>
#include <vector>

namespace torchvor {
namespace ops {

// Value checks that need the data: each is a 0-dim bool tensor on the data's
// device. They are read back to the host together (one device sync, not one
// each), by run() or along with other values (conditions() / verify()), and
// reported in the order they were added.
class ValueChecks {
 public:
  void add(at::Tensor holds, std::string message);
  void finite(const at::Tensor& values, const char* name);  // no NaN or Inf in values
  const std::vector<at::Tensor>& conditions() const { return conditions_; }
  void verify(const double* holds) const;  // one value per condition, as read back
  void run() const;

 private:
  std::vector<at::Tensor> conditions_;
  std::vector<std::string> messages_;
};

// Validates the arguments of torchvor::knn but the values of points and
// queries (knn_value_checks); returns the number of batch elements (max of
// both batch vectors + 1, or 1 without batches).
int64_t check_knn_inputs(const at::Tensor& points, const at::Tensor& queries, int64_t k,
                         const c10::optional<at::Tensor>& points_batch,
                         const c10::optional<at::Tensor>& queries_batch, bool exclude_self);

// Points and queries hold no NaN or Inf.
ValueChecks knn_value_checks(const at::Tensor& points, const at::Tensor& queries);

// Validates the arguments of torchvor::voronoi_cells but the values of points
// and box (check_voronoi_values). Returns the number of point clouds (1
// without a batch): a single box (1, 2, 3) applies to each of them.
int64_t check_voronoi_inputs(const at::Tensor& points, const at::Tensor& box,
                             const c10::optional<at::Tensor>& batch, c10::optional<int64_t> k,
                             int64_t memory_budget);

// Validates voronoi_cells' `rows` (the cells to compute, int64 (M,) on the
// points' device) but its values, which go to `values`: each in [0, N).
void check_cell_rows(const c10::optional<at::Tensor>& rows, const at::Tensor& points, ValueChecks& values);

// The points are finite (non-finite bounds), the box of every cloud that has
// points is finite with lo < hi on each axis, and every point lies inside
// its box, from what the host read: `bounds` (B, 7) rows of the points'
// bounding box and count per batch element (grid.h, point_bounds) and the
// box (B, 2, 3) values.
void check_voronoi_values(const at::Tensor& bounds, const double* box, int64_t num_boxes);

// Validates the arguments of torchvor::lloyd_step that voronoi_cells does not
// take (check_voronoi_inputs checks the rest): the histogram's sample stride
// and bins.
void check_lloyd_step_inputs(int64_t sample_stride, int64_t histogram_bins);

}  // namespace ops
}  // namespace torchvor
