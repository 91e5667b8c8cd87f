// The thread cell's work, clip by clip, on the development machine (no GPU).
// benchmarks/clip_shape.py writes the input and compiles and runs this file:
//   clip_shape DIR N K
// DIR holds points.bin (N x 3 float32, in the op's grid order) and
// neighbors.bin (N x K int32, each row sorted by distance). It runs
// core::compute_cell on every cell with the first pass's cell type and prints
// what the clips did, and a model of a warp of 32 consecutive cells
// (benchmarks/NOTES.md, twenty-eighth session), then
// - that model on warps of alike cells (windows of cells sorted by a key);
// - the clips in grid-shell order: candidates from the grid, not the kNN list.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <limits>
#include <numeric>
#include <string>
#include <vector>

#include "core/voronoi_cell.h"

using namespace torchvor::core;

// The first pass's cell at tier 0 (ops/voronoi.h: 32 planes, 64 triangles).
using FirstPassCell = ConvexCell<float, 32, 64>;

// Cost units of the warp model: a neighbour read and its tests, and per
// triangle of a clip's classify, per removed triangle gathered, per pair of
// removed triangles searched, per new triangle of the fan; a cell's start
// and, per final vertex, its integrals. Rough instruction counts: the model
// compares schedules, it does not predict times.
constexpr double kReadCost = 20, kClassifyCost = 6, kGatherCost = 4, kSearchCost = 15, kFanCost = 30;
constexpr double kStartCost = 600, kIntegralCost = 150;
// The grid-shell run's own work: per candidate point scanned (its read and
// the test against the radius of security), per grid cell visited.
constexpr double kScanCost = 12, kGridCellCost = 10;

constexpr float kBox[6] = {0, 0, 0, 1, 1, 1};  // the unit box: lo, hi
constexpr Vec3<float> kLo = {kBox[0], kBox[1], kBox[2]}, kHi = {kBox[3], kBox[4], kBox[5]};

struct Totals {
  long clips = 0, misses = 0, misses_a_box_certifies = 0, triangles_at_clips = 0, removed = 0;
  long removed_histogram[16] = {};
};

// FirstPassCell that counts what each clip does and records its modelled cost.
struct CountingCell : FirstPassCell {
  Totals* totals;
  std::vector<double>* step_costs;
  // Work since the previous clip that the warp waits on with this clip (the
  // grid-shell run's scans): charged to the next clip's step.
  double pending_cost = 0;

  bool clip_by_bisector(Vec3<float> r) {
    const float r2 = squared_norm(r);
    const float threshold = r2 * (0.5f + tolerance);  // classify's band: dot(r, v) beyond it is clipped
    // The vertices' bounding box, and the vertices the plane will remove.
    Vec3<float> low = {1e30f, 1e30f, 1e30f}, high = {-1e30f, -1e30f, -1e30f};
    int removed = 0;
    for (int t = 0; t < num_triangles; ++t) {
      const Vec3<float> v = triangle[t].position;
      low = {std::min(low.x, v.x), std::min(low.y, v.y), std::min(low.z, v.z)};
      high = {std::max(high.x, v.x), std::max(high.y, v.y), std::max(high.z, v.z)};
      removed += dot(r, v) > threshold;
    }
    const float box_bound = std::max(r.x * low.x, r.x * high.x) + std::max(r.y * low.y, r.y * high.y) +
                            std::max(r.z * low.z, r.z * high.z);
    const int triangles_before = num_triangles, planes_before = num_planes;
    const bool ok = FirstPassCell::clip_by_bisector(r);
    ++totals->clips;
    totals->triangles_at_clips += triangles_before;
    double cost = pending_cost + kReadCost + kClassifyCost * triangles_before;
    pending_cost = 0;
    if (ok && num_planes == planes_before) {  // the plane missed the cell
      ++totals->misses;
      totals->misses_a_box_certifies += box_bound <= threshold;
    } else {
      totals->removed += removed;
      ++totals->removed_histogram[std::min(removed, 15)];
      cost += kGatherCost * removed + kSearchCost * removed * removed + kFanCost * (removed + 2);
    }
    step_costs->push_back(cost);
    return ok;
  }
};

// A cell's modelled work: its steps (neighbour reads, clips) and what it
// costs to start and integrate.
struct CellWork {
  std::vector<double> steps;
  double start_and_integrals;
};

// 32 consecutive cells run in lockstep: each step costs the warp its slowest
// lane's step.
struct Lockstep {
  double efficiency;  // lanes' useful work over the warp's time
  double warp_time;   // summed over the warps
};

Lockstep lockstep(const std::vector<CellWork>& cells) {
  double useful = 0, warp_time = 0;
  for (size_t first = 0; first < cells.size(); first += 32) {
    const size_t end = std::min(cells.size(), first + 32);
    size_t longest = 0;
    double slowest_ends = 0;
    for (size_t i = first; i < end; ++i) {
      longest = std::max(longest, cells[i].steps.size());
      slowest_ends = std::max(slowest_ends, cells[i].start_and_integrals);
      for (double c : cells[i].steps) useful += c;
      useful += cells[i].start_and_integrals;
    }
    for (size_t s = 0; s < longest; ++s) {
      double slowest = 0;
      for (size_t i = first; i < end; ++i) {
        if (s < cells[i].steps.size()) slowest = std::max(slowest, cells[i].steps[s]);
      }
      warp_time += slowest;
    }
    warp_time += slowest_ends;
  }
  return {useful / (32 * warp_time), warp_time};
}

// The same when a lane takes its next cell as soon as `threshold` lanes of
// the warp have finished theirs (they start and integrate together).
double refill_efficiency(const std::vector<CellWork>& cells, int threshold) {
  double useful = 0, warp_time = 0;
  for (const CellWork& cell : cells) {
    for (double c : cell.steps) useful += c;
    useful += cell.start_and_integrals;
  }
  std::vector<long> cell_of(32, -1);  // -1: idle, the queue is empty
  std::vector<size_t> step(32, 0);
  size_t next_cell = 0;
  const auto restart = [&](const std::vector<int>& lanes) {
    double slowest = 0;
    for (int lane : lanes) {
      if (cell_of[lane] >= 0) slowest = std::max(slowest, cells[cell_of[lane]].start_and_integrals);
      cell_of[lane] = next_cell < cells.size() ? long(next_cell++) : -1;
      step[lane] = 0;
    }
    warp_time += slowest;
  };
  std::vector<int> all(32);
  for (int lane = 0; lane < 32; ++lane) all[lane] = lane;
  restart(all);  // the first cells' starts are not charged, as in lockstep
  for (;;) {
    std::vector<int> finished;
    int running = 0;
    for (int lane = 0; lane < 32; ++lane) {
      if (cell_of[lane] < 0) continue;
      if (step[lane] < cells[cell_of[lane]].steps.size()) ++running;
      else finished.push_back(lane);
    }
    if (int(finished.size()) >= threshold || (running == 0 && !finished.empty())) {
      restart(finished);
      continue;
    }
    if (running == 0) break;
    double slowest = 0;
    for (int lane = 0; lane < 32; ++lane) {
      if (cell_of[lane] >= 0 && step[lane] < cells[cell_of[lane]].steps.size()) {
        slowest = std::max(slowest, cells[cell_of[lane]].steps[step[lane]++]);
      }
    }
    warp_time += slowest;
  }
  return useful / (32 * warp_time);
}

Vec3<float> point_at(const std::vector<float>& points, int32_t i) {
  return {points[3 * i], points[3 * i + 1], points[3 * i + 2]};
}

// Cell i's start as compute_cell chooses it (voronoi_cell.h): the
// tetrahedron of four of its first kStartCandidates neighbours where they
// surround the seed inside the box, else the box (tetrahedron.found false).
struct CellStart {
  StartTetrahedron<float> tetrahedron;
  int32_t bounding[4];  // the four neighbours' indices; -1: the box
};

CellStart start_of(const std::vector<float>& points, const int32_t* list, int k, Vec3<float> seed) {
  CellStart start{};  // tetrahedron.found false: the box
  std::fill(start.bounding, start.bounding + 4, -1);
  if (k < kStartCandidates) return start;
  Vec3<float> unit[kStartCandidates];
  for (int n = 0; n < kStartCandidates; ++n) {
    if (list[n] < 0) return start;
    const Vec3<float> r = point_at(points, list[n]) - seed;
    const float length2 = squared_norm(r);
    if (length2 == 0) return start;  // a duplicate of the seed
    unit[n] = (1.0f / sqrt_of(length2)) * r;
  }
  const StartChoice choice = start_choice(unit);
  if (!choice.found) return start;
  const int32_t chosen[4] = {list[0], list[choice.b], list[choice.c], list[choice.d]};
  Vec3<float> offset[4];
  for (int t = 0; t < 4; ++t) offset[t] = point_at(points, chosen[t]) - seed;
  start.tetrahedron = start_tetrahedron(offset, choice.positive, kLo - seed, kHi - seed);
  if (start.tetrahedron.found) std::copy(chosen, chosen + 4, start.bounding);
  return start;
}

// The cells with each window of `window` consecutive ones sorted (stably)
// by `key`, so that a warp's 32 cells do alike work.
std::vector<CellWork> sorted_within_windows(const std::vector<CellWork>& cells, const std::vector<double>& key,
                                            size_t window) {
  std::vector<size_t> order(cells.size());
  std::iota(order.begin(), order.end(), size_t(0));
  for (size_t first = 0; first < order.size(); first += window) {
    std::stable_sort(order.begin() + first, order.begin() + std::min(order.size(), first + window),
                     [&](size_t a, size_t b) { return key[a] < key[b]; });
  }
  std::vector<CellWork> sorted;
  sorted.reserve(cells.size());
  for (size_t i : order) sorted.push_back(cells[i]);
  return sorted;
}

// Lockstep on warps of alike cells, sorted by what the start tetrahedron
// tells before any clip: its largest |vertex|^2 (a wide start has more to
// carve). (Sorting by the cells' own step counts does no better in this
// model: a box start reads fewer plain steps and clips more.)
void print_alike_warps(const std::vector<float>& points, const std::vector<int32_t>& neighbors, long n, int k,
                       const std::vector<CellWork>& cells, double grid_order_time) {
  std::vector<double> start_radius2(n);
  for (long i = 0; i < n; ++i) {
    const StartTetrahedron<float> start =
        start_of(points, neighbors.data() + i * k, k, point_at(points, int32_t(i))).tetrahedron;
    double radius2 = 0;
    for (const Vec3<float>& v : start.vertex) radius2 = std::max(radius2, double(squared_norm(v)));
    start_radius2[i] = start.found ? radius2 : std::numeric_limits<double>::infinity();  // box starts last
  }
  std::printf("\nWarps of alike cells (lockstep; each window of W consecutive cells sorted by its start's radius, "
              "the largest |vertex|^2 of the start tetrahedron, box starts last; warp time against grid order's):\n");
  std::printf("| W | lockstep | warp time |\n|---|---|---|\n");
  for (size_t window : {64, 256, 1024}) {
    const Lockstep by_start = lockstep(sorted_within_windows(cells, start_radius2, window));
    std::printf("| %zu | %.3f | %.3f of grid order |\n", window, by_start.efficiency,
                by_start.warp_time / grid_order_time);
  }
}

constexpr int kBlockReach = 2;  // the grid-shell run's block: (2 * kBlockReach + 1)^3 grid cells

// Clips in grid-shell order, one row of the table: each cell starts as
// compute_cell starts it (from the kNN's nearest), then clips by the points
// of the block of grid cells around its own, the nearest grid cell first,
// skipping points beyond the radius of security and stopping at the first
// grid cell beyond it. The grid: side^3 cells over the unit box, about
// `points_per_cell` points each. Warp time against the sorted list's
// (`list_time`), volumes against compute_cell's (`list_volume`, NaN where it failed).
void print_grid_shell_run(const std::vector<float>& points, const std::vector<int32_t>& neighbors, long n, int k,
                          double points_per_cell, const std::vector<float>& list_volume, double list_time) {
  const int side = std::max(1, int(std::lround(std::cbrt(n / points_per_cell))));
  const auto grid_cell_of = [&](float x) { return std::min(side - 1, std::max(0, int(x * side))); };
  const auto grid_cell_id = [&](const int (&at)[3]) { return (size_t(at[2]) * side + at[1]) * side + at[0]; };
  std::vector<std::vector<int32_t>> members(size_t(side) * side * side);
  for (int32_t i = 0; i < n; ++i) {
    const int at[3] = {grid_cell_of(points[3 * i]), grid_cell_of(points[3 * i + 1]), grid_cell_of(points[3 * i + 2])};
    members[grid_cell_id(at)].push_back(i);
  }
  constexpr int kWidth = 2 * kBlockReach + 1;
  struct GridCellAt {
    float gap2;  // its squared distance from the seed
    size_t id;
  };
  std::vector<GridCellAt> block;
  Totals totals;
  std::vector<CellWork> cells(n);
  long failed = 0, scanned = 0, visited = 0, reaching_past_block = 0;
  double largest_difference = 0;
  for (int32_t i = 0; i < n; ++i) {
    const Vec3<float> seed = point_at(points, i);
    const float s[3] = {seed.x, seed.y, seed.z};
    CountingCell cell;
    cell.totals = &totals;
    cell.step_costs = &cells[i].steps;
    const CellStart start = start_of(points, neighbors.data() + size_t(i) * k, k, seed);
    if (start.tetrahedron.found) cell.init_tetrahedron(start.tetrahedron, ClipTolerance<float>::value, 0);
    else cell.init_box(kLo - seed, kHi - seed, ClipTolerance<float>::value, 0);

    // The block's grid cells inside the box, nearest first (ties in z, y, x order).
    const int own[3] = {grid_cell_of(s[0]), grid_cell_of(s[1]), grid_cell_of(s[2])};
    block.clear();
    for (int b = 0; b < kWidth * kWidth * kWidth; ++b) {
      const int at[3] = {own[0] + b % kWidth - kBlockReach, own[1] + b / kWidth % kWidth - kBlockReach,
                         own[2] + b / (kWidth * kWidth) - kBlockReach};
      bool inside = true;
      float gap2 = 0;
      for (int a = 0; a < 3; ++a) {
        inside = inside && 0 <= at[a] && at[a] < side;
        const float low = float(at[a]) / side, high = float(at[a] + 1) / side;
        const float gap = s[a] < low ? low - s[a] : (s[a] > high ? s[a] - high : 0.0f);
        gap2 += gap * gap;
      }
      if (inside) block.push_back({gap2, grid_cell_id(at)});
    }
    std::stable_sort(block.begin(), block.end(),
                     [](const GridCellAt& a, const GridCellAt& b) { return a.gap2 < b.gap2; });
    const auto clip_by_block = [&]() {
      for (const GridCellAt& grid_cell : block) {
        if (cell.security_radius_reached(grid_cell.gap2)) return true;
        ++visited;
        cell.pending_cost += kGridCellCost;
        for (int32_t j : members[grid_cell.id]) {
          // The seed, and the start's four (their planes bound the cell already): not candidates.
          if (j == i || std::count(start.bounding, start.bounding + 4, j) > 0) continue;
          ++scanned;
          cell.pending_cost += kScanCost;
          // A grid cell's points come in no order: one beyond the radius of security ends nothing.
          const Vec3<float> r = point_at(points, j) - seed;
          if (!cell.security_radius_reached(squared_norm(r)) && !cell.clip_by_bisector(r)) return false;
        }
      }
      return true;
    };
    const bool ok = clip_by_block();
    failed += !ok;
    // Whether points beyond the block could still cut the cell: the nearest
    // side of the block that has grid cells behind it.
    float edge = std::numeric_limits<float>::infinity();
    for (int a = 0; a < 3; ++a) {
      if (own[a] - kBlockReach > 0) edge = std::min(edge, s[a] - float(own[a] - kBlockReach) / side);
      if (own[a] + kBlockReach < side - 1) edge = std::min(edge, float(own[a] + kBlockReach + 1) / side - s[a]);
    }
    reaching_past_block += ok && !cell.security_radius_reached(edge * edge);
    // The last step: the scans since the last clip, and the test that ends
    // the cell at a read's cost, as the list's last read.
    cells[i].steps.push_back(cell.pending_cost + kReadCost);
    cells[i].start_and_integrals = kStartCost + kIntegralCost * cell.num_triangles;
    if (ok && !std::isnan(list_volume[i])) {
      float volume, second_moment, unsigned_volume;
      Vec3<float> first_moment;
      cell.integrate(volume, first_moment, second_moment, unsigned_volume);
      largest_difference = std::max(largest_difference, std::fabs(double(volume) - list_volume[i]) / list_volume[i]);
    }
  }
  std::printf("| %.2f | %d^3 | %ld | %.2f | %.2f | %.2f | %.2f | %ld | %.3f of the list's | %.2e |\n",
              double(n) / side / side / side, side, failed, double(totals.clips) / n, double(totals.misses) / n,
              double(scanned) / n, double(visited) / n, reaching_past_block, lockstep(cells).warp_time / list_time,
              largest_difference);
}

int main(int argc, char** argv) {
  if (argc != 4) {
    std::fprintf(stderr, "usage: clip_shape DIR N K\n");
    return 2;
  }
  const std::string dir = argv[1];
  const long n = std::atol(argv[2]);
  const int k = std::atoi(argv[3]);
  std::vector<float> points(3 * n);
  std::vector<int32_t> neighbors(n * k);
  const auto read = [&](const std::string& name, void* data, size_t bytes) {
    FILE* file = std::fopen((dir + "/" + name).c_str(), "rb");
    if (file == nullptr || std::fread(data, 1, bytes, file) != bytes) {
      std::fprintf(stderr, "clip_shape: cannot read %s\n", name.c_str());
      std::exit(1);
    }
    std::fclose(file);
  };
  read("points.bin", points.data(), points.size() * sizeof(float));
  read("neighbors.bin", neighbors.data(), neighbors.size() * sizeof(int32_t));

  Totals totals;
  std::vector<CellWork> cells(n);
  std::vector<float> list_volume(n, std::numeric_limits<float>::quiet_NaN());  // NaN: the cell failed
  long neighbors_read = 0, failed = 0;
  for (long i = 0; i < n; ++i) {
    CountingCell cell;
    cell.totals = &totals;
    std::vector<double> clip_costs;
    cell.step_costs = &clip_costs;
    const CellIntegrals<float> out = compute_cell(cell, points.data(), int32_t(i), neighbors.data() + i * k, 1, k,
                                                  kBox, ClipTolerance<float>::value, 0);
    failed += out.status != kSuccess;
    if (out.status == kSuccess) list_volume[i] = out.volume;
    neighbors_read += out.neighbors;
    // Reads that clip nothing (the start's neighbours, the one past the
    // radius of security) first and last; the clips in between.
    const int reads = std::min(out.neighbors + 1, k);
    const int plain_reads = std::max(0, reads - int(clip_costs.size()));
    CellWork& work = cells[i];
    work.steps.assign(std::max(0, plain_reads - 1), kReadCost);
    work.steps.insert(work.steps.end(), clip_costs.begin(), clip_costs.end());
    if (plain_reads > 0) work.steps.push_back(kReadCost);
    work.start_and_integrals = kStartCost + kIntegralCost * cell.num_triangles;
  }

  std::printf("| cells | k | failed | neighbours a cell | clips a cell | misses a cell | misses a bounding box certifies "
              "| triangles at a clip | removed by a cutting clip |\n|---|---|---|---|---|---|---|---|---|\n");
  const double cutting = double(totals.clips - totals.misses);
  std::printf("| %ld | %d | %ld | %.2f | %.2f | %.2f | %.3f | %.2f | %.2f |\n\n", n, k, failed,
              double(neighbors_read) / n, double(totals.clips) / n, double(totals.misses) / n,
              double(totals.misses_a_box_certifies) / n, double(totals.triangles_at_clips) / totals.clips,
              totals.removed / cutting);
  std::printf("Triangles removed by a cutting clip (share of clips):");
  for (int r = 1; r < 16; ++r) {
    if (totals.removed_histogram[r] > 0) {
      std::printf(" %d%s: %.1f%%", r, r == 15 ? "+" : "", 100.0 * totals.removed_histogram[r] / cutting);
    }
  }
  std::printf("\n\nWarp model (32 consecutive cells; lanes' useful work over the warp's time):\n");
  const Lockstep grid_order = lockstep(cells);
  std::printf("- lockstep: %.3f\n", grid_order.efficiency);
  for (int threshold : {1, 8, 16, 24}) {
    std::printf("- a lane takes a new cell once %d lanes are done: %.3f\n", threshold,
                refill_efficiency(cells, threshold));
  }

  print_alike_warps(points, neighbors, n, k, cells, grid_order.warp_time);

  std::printf("\nClips in grid-shell order (no kNN): each cell starts from the tetrahedron of its %d nearest (as "
              "compute_cell), then clips by the points of the %d^3 grid cells around its own, the nearest grid cell "
              "first, to the radius of security; a candidate scanned costs %g, a grid cell visited %g, on the next "
              "clip's step; lockstep warp time against the sorted list's:\n",
              kStartCandidates, 2 * kBlockReach + 1, kScanCost, kGridCellCost);
  std::printf("| points a grid cell | grid | failed | clips a cell | misses a cell | candidates scanned a cell "
              "| grid cells visited a cell | cells whose security radius reaches past the block | warp time "
              "| largest relative volume difference from compute_cell |\n|---|---|---|---|---|---|---|---|---|---|\n");
  for (double points_per_cell : {2.0, 1.0, 0.5}) {
    print_grid_shell_run(points, neighbors, n, k, points_per_cell, list_volume, grid_order.warp_time);
  }
  return 0;
}
