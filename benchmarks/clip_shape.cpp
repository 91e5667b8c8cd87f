// The thread cell's work, clip by clip, on the development machine (no GPU).
// benchmarks/clip_shape.py writes the input and compiles and runs this file:
//   clip_shape DIR N K
// DIR holds points.bin (N x 3 float32, in the op's grid order) and
// neighbors.bin (N x K int32, each row sorted by distance). It runs
// core::compute_cell on every cell with the first pass's cell type and prints
// what the clips did, and a model of a warp of 32 consecutive cells
// (benchmarks/NOTES.md, twenty-eighth session).
#include <algorithm>
#include <cstdio>
#include <cstdlib>
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

struct Totals {
  long clips = 0, misses = 0, misses_a_box_certifies = 0, triangles_at_clips = 0, removed = 0;
  long removed_histogram[16] = {};
};

// FirstPassCell that counts what each clip does and records its modelled cost.
struct CountingCell : FirstPassCell {
  Totals* totals;
  std::vector<double>* step_costs;

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
    double cost = kReadCost + kClassifyCost * triangles_before;
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

// Lanes' useful work over the warp's time when 32 consecutive cells run in
// lockstep: each step costs the warp its slowest lane's step.
double lockstep_efficiency(const std::vector<CellWork>& cells) {
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
  return useful / (32 * warp_time);
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
  restart(all);  // the first cells' starts are not charged, as in lockstep_efficiency
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

  const float box[6] = {0, 0, 0, 1, 1, 1};
  Totals totals;
  std::vector<CellWork> cells(n);
  long neighbors_read = 0, failed = 0;
  for (long i = 0; i < n; ++i) {
    CountingCell cell;
    cell.totals = &totals;
    std::vector<double> clip_costs;
    cell.step_costs = &clip_costs;
    const CellIntegrals<float> out = compute_cell(cell, points.data(), int32_t(i), neighbors.data() + i * k, 1, k,
                                                  box, ClipTolerance<float>::value, 0);
    failed += out.status != kSuccess;
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
  std::printf("- lockstep: %.3f\n", lockstep_efficiency(cells));
  for (int threshold : {1, 8, 16, 24}) {
    std::printf("- a lane takes a new cell once %d lanes are done: %.3f\n", threshold,
                refill_efficiency(cells, threshold));
  }
  return 0;
}
