#include "options.h"

#include <cstdlib>
#include <cstring>

namespace torchvor {
namespace ops {
namespace {

const char* variable(const char* name) { return std::getenv(name); }

bool equals(const char* value, const char* expected) {
  return value != nullptr && std::strcmp(value, expected) == 0;
}

void read_implementation(const char* name, Implementation& out) {
  const char* value = variable(name);
  if (equals(value, "thread")) out = Implementation::kThread;
  if (equals(value, "cooperative")) out = Implementation::kCooperative;
}

// The whole value as an integer, or false.
bool read_integer(const char* name, long long& out) {
  const char* value = variable(name);
  if (value == nullptr) return false;
  char* end = nullptr;
  const long long parsed = std::strtoll(value, &end, 10);
  if (end == value || *end != '\0') return false;
  out = parsed;
  return true;
}

bool read_real(const char* name, double& out) {
  const char* value = variable(name);
  if (value == nullptr) return false;
  char* end = nullptr;
  const double parsed = std::strtod(value, &end);
  if (end == value || *end != '\0') return false;
  out = parsed;
  return true;
}

}  // namespace

Options Options::from_environment() {
  Options options;
  read_implementation("TORCHVOR_CELLS", options.cells);
  read_implementation("TORCHVOR_KNN", options.knn);
  if (equals(variable("TORCHVOR_CELL_START"), "box")) options.tetrahedron_start = false;
  if (equals(variable("TORCHVOR_THREAD_TRIANGLES"), "full")) options.compact_triangles = false;
  if (equals(variable("TORCHVOR_CPU_ISA"), "baseline")) options.cpu_baseline_isa = true;
  if (equals(variable("TORCHVOR_POWER_NEAREST_FIRST"), "0")) options.power_nearest_first = Options::NearestFirstCells::kNone;
  if (equals(variable("TORCHVOR_POWER_NEAREST_FIRST"), "all")) options.power_nearest_first = Options::NearestFirstCells::kAll;
  if (equals(variable("TORCHVOR_TEST_BOUNDED_CELLS"), "1")) options.testing.bounded_cells = true;
  double real = 0.0;
  if (read_real("TORCHVOR_PILOT_QUANTILE", real) && real > 0.0 && real <= 1.0) options.pilot_quantile = real;
  if (read_real("TORCHVOR_POINTS_PER_CELL_SCALE", real) && real > 0.0) options.points_per_cell_scale = real;
  if (read_real("TORCHVOR_POWER_POINTS_PER_CUBE", real) && real > 0.0) options.power_points_per_cube = real;
  long long integer = 0;
  if (read_integer("TORCHVOR_VERTEX_BALLS_K", integer) && integer >= 1) options.vertex_balls_k = integer;
  if (read_integer("TORCHVOR_SPECULATIVE_CELLS", integer) && integer >= 0) options.speculative_cells = integer;
  if (read_integer("TORCHVOR_GRAPH_CLAIMED_FACES", integer) && integer >= 0 && integer <= 4096) {
    options.graph_claimed_faces = integer;
  }
  if (read_integer("TORCHVOR_CELL_BLOCKS_PER_SM", integer) && integer >= 1) options.cell_blocks_per_sm = integer;
  if (read_integer("TORCHVOR_STREAM_ROWS_BYTES", integer) && integer >= 0) options.stream_rows_bytes = integer;
  if (read_integer("TORCHVOR_TEST_SCATTER_BYTES", integer) && integer > 0) options.testing.scatter_bytes = integer;
  if (read_integer("TORCHVOR_TEST_UNWRITTEN_CELL", integer) && integer >= 0) {
    options.testing.forget_position = integer;
  }
  return options;
}

}  // namespace ops
}  // namespace torchvor
