// The internal tuning choices of one op call, read once at the op's entry and
// passed down explicitly. Every field's default is the production choice; the
// environment variables exist for the tests (which compare the choices) and
// the benchmarks (which time them). docs/design.md lists them.
#pragma once

#include <cstdint>

namespace torchvor {
namespace ops {

// Which implementation runs a pass: the backend's choice, or one forced.
enum class Implementation { kBackend, kThread, kCooperative };

// Whether the pass runs a group of lanes per item: `forced`, or the backend's choice.
inline bool use_cooperative(Implementation forced, bool backend_default) {
  if (forced == Implementation::kCooperative) return true;
  if (forced == Implementation::kThread) return false;
  return backend_default;
}

struct Options {
  Implementation cells = Implementation::kBackend;  // TORCHVOR_CELLS=thread|cooperative
  Implementation knn = Implementation::kBackend;    // TORCHVOR_KNN=thread|cooperative
  bool tetrahedron_start = true;    // TORCHVOR_CELL_START=box: every cell starts from its box
  bool compact_triangles = true;    // TORCHVOR_THREAD_TRIANGLES=full: CUDA's float32 thread cells keep 16-byte triangles
  double pilot_quantile = 0.98;     // TORCHVOR_PILOT_QUANTILE in (0, 1]: the pilot's cells the first k covers
  int64_t vertex_balls_k = 256;     // TORCHVOR_VERTEX_BALLS_K >= 1: the most neighbours a retry asks for
  int64_t speculative_cells = 16384;  // TORCHVOR_SPECULATIVE_CELLS >= 0: the speculative retry's capacity
  double points_per_cell_scale = 1.0;  // TORCHVOR_POINTS_PER_CELL_SCALE > 0: multiplies the grid's density rule
  int64_t graph_claimed_faces = 20;  // TORCHVOR_GRAPH_CLAIMED_FACES >= 0: voronoi_graph's room a cell in its one
                                     // pass (0: a count pass, then the faces)
  // TORCHVOR_POWER_NEAREST_FIRST=0|all: which power cells offer the 27 cubes around
  // their seed's nearest first (core::NearestFirst): none, or the float32 cells too (by
  // default the float64 ones only: the float32 cells of white noise ran slower so).
  enum class NearestFirstCells { kNone, kFloat64, kAll };
  NearestFirstCells power_nearest_first = NearestFirstCells::kFloat64;
  double power_points_per_cube = 2.0;  // TORCHVOR_POWER_POINTS_PER_CUBE > 0: the power cells' walk grid's density (few
                                       // a cube: a cube's largest weight bounds few points)
  int64_t cell_blocks_per_sm = 0;   // TORCHVOR_CELL_BLOCKS_PER_SM >= 1: CUDA thread-cell residency (0: the rule)
  bool cpu_baseline_isa = false;    // TORCHVOR_CPU_ISA=baseline: the CPU clip loop without its AVX2+FMA copy
  int64_t stream_rows_bytes = int64_t(32) << 20;  // TORCHVOR_STREAM_ROWS_BYTES >= 0: the CPU kNN's results from
                                                   // this size are written by non-temporal stores

  // Fault injection and small-input coverage, for the tests only.
  struct Testing {
    int64_t scatter_bytes = 0;     // TORCHVOR_TEST_SCATTER_BYTES > 0: the inverse order's range size
    int64_t forget_position = -1;  // TORCHVOR_TEST_UNWRITTEN_CELL: drop this grid position's first result
    bool bounded_cells = false;    // TORCHVOR_TEST_BOUNDED_CELLS=1: no unbounded cells (a cell can overflow)
  } testing;

  // The options of a call: the defaults, overridden by the variables that are
  // set to valid values (others are ignored). The one reader of the environment.
  static Options from_environment();
};

}  // namespace ops
}  // namespace torchvor
