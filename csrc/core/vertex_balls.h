// Finishing a cell whose neighbour list ran out before the radius of
// security: the empty-ball test of its vertices, on the grid.
//
// A point p cuts the cell only if some vertex v is nearer to p than to the
// seed (|p - v| < |v|, the seed at the origin): 2 p.v - |p|^2 is linear in
// v, so its largest value over the cell is taken at a vertex. Once every
// point in the balls B(v, |v|) has clipped the cell, no point can cut it.
// The radius of security asks for every point of the ball B(0, 2 max |v|),
// which holds all of those balls and can hold far more: where a cell reaches
// into empty space (a void between clusters, a box far wider than the
// points) its farthest vertex is far away, that ball holds whole clusters
// (up to the whole cloud), while the vertices' own balls are empty but for
// the points near the seed.
//
// Clipping only shrinks the cell, and with it the union of its balls (a
// point that cuts the smaller cell cuts the larger). So one sweep over the
// grid rows that meet the balls of the cell as the sweep found it, each row
// cut to the part that meets the balls of the cell as it is then, offers
// every point that can cut the final cell; a point that did not cut the cell
// when offered cannot cut it later. Rows go from the seed's outwards, so the
// nearer points clip first and the balls shrink early.
//
// The sweep clips in the grid's order, not by distance: the planes of a
// tight cluster seen from afar are nearly parallel, and in another order
// their rounded intersections can settle on another, wrong, cell (a float64
// cell 2e-7 off, caught by test_tight_clusters), and the last bits of any
// cell would follow the grid. So the cell is then recomputed from its list
// and the further neighbours that bound it, in increasing distance as the
// radius of security would have clipped them, and swept again until a sweep
// finds nothing to clip (finish_by_vertex_balls).
#pragma once

#include "common.h"
#include "convex_cell.h"
#include "grid_search.h"
#include "status.h"

namespace torchvor {
namespace core {

// The grid of a cell's batch element, where the sweep finds its points.
template <typename io_t>
struct VertexBallGrid {
  GridView<io_t> grid;  // voronoi's grid: points by position (no index array)
  int64_t batch;
};

// The id of the point of the cell's batch element at `r` from the seed, as
// the cell computed its offset (T(point) - seed, bit for bit), or -1: the
// point lies in the grid cell of seed + r or, rounded, next to it.
template <typename io_t, typename T>
TV_HD int32_t point_at_offset(const VertexBallGrid<io_t>& balls, Vec3<T> seed, Vec3<T> r) {
  const GridView<io_t>& grid = balls.grid;
  const int64_t b = balls.batch;
  const io_t h = grid.cell_size[b];
  const Vec3<T> at = seed + r;
  const T position[3] = {at.x, at.y, at.z};
  int32_t dim[3], cell[3];
  for (int a = 0; a < 3; ++a) {
    dim[a] = grid.dims[3 * b + a];
    cell[a] = grid_coordinate(io_t(position[a]), grid.origin[3 * b + a], h, dim[a]);
  }
  for (int32_t z = max_of(cell[2] - 1, 0); z <= min_of(cell[2] + 1, dim[2] - 1); ++z) {
    for (int32_t y = max_of(cell[1] - 1, 0); y <= min_of(cell[1] + 1, dim[1] - 1); ++y) {
      const int32_t row = grid.cell_offset[b] + (z * dim[1] + y) * dim[0];
      const int32_t end = grid.cell_start[row + min_of(cell[0] + 1, dim[0] - 1) + 1];
      for (int32_t s = grid.cell_start[row + max_of(cell[0] - 1, 0)]; s < end; ++s) {
        const Vec3<T> offset = {T(grid.sorted_points[3 * s]) - seed.x, T(grid.sorted_points[3 * s + 1]) - seed.y,
                                T(grid.sorted_points[3 * s + 2]) - seed.z};
        if (offset.x == r.x && offset.y == r.y && offset.z == r.z) return grid.original_index(s);
      }
    }
  }
  return -1;
}

// The kNN ranked a cell's list in the input's precision: a point a rounding
// away from the last listed one (at listed_dist2) may be missing from it.
// Points from this squared distance on are so taken as possibly unlisted.
template <typename T>
TV_HD T unlisted_from(T listed_dist2) {
  return listed_dist2 * (T(1) - T(1e-4));
}

// Whether the bisector of the neighbour at r (relative to the seed, r2 =
// |r|^2) may cut `cell`: whether a vertex v lies beyond it, r.v > r2 / 2.
// The clip's predicate (classify) removes a vertex only where r.v exceeds
// r2 (1/2 + band), the band at least the cell's tolerance; this test takes
// every vertex within that tolerance and a rounding margin of the near side
// too, so that it never turns away a point the clip would take. Any lane,
// for its own r (no collective). In S: double for double-double.
template <typename Cell, typename T>
TV_HD bool may_cut(const Cell& cell, Vec3<T> r, T r2) {
  using S = typename ChoiceScalar<T>::type;
  const Vec3<S> offset = {S(r.x), S(r.y), S(r.z)};
  const S offset2 = S(r2);
  // The rounding of r.v is a few units of S's precision times |r| |v|.
  const S slack = S(1e-4) * sqrt_of(offset2 * S(cell.radius2)) + S(cell.tolerance) * offset2;
  const S threshold = S(0.5) * offset2 - slack;
  for (int t = 0; t < cell.vertex_count(); ++t) {
    const Vec3<T> v = cell.vertex(t);
    if (dot(offset, Vec3<S>{S(v.x), S(v.y), S(v.z)}) > threshold) return true;
  }
  return false;
}

// Clips `cell` (relative to `seed`, point `seed_index` of the grid's
// points) by every point of the grid in its vertices' balls. Points nearer
// than `listed_dist2` were in the neighbour list that clipped the cell
// already and are skipped; a point at about that distance, or an exact copy
// of a point clipped by, is skipped where its bisector is a plane of the
// cell already (ConvexCell::has_bisector). Returns kSuccess, kDuplicate (an
// exact copy of the seed with a lower index), or the cell's status where a
// clip failed; `clipped`: whether any point cut the cell.
//
// The cell's lanes (a warp for a CooperativeCell on the GPU, one for a
// ConvexCell) share the work: each row's pass over the vertices, and the
// row's points, a point a lane, each tested against the cell as the batch
// found it (may_cut; a point that cannot cut the cell cannot cut it once
// smaller). The points that may cut are then clipped together, in the
// sweep's order, each tested again as it comes: the same clips, in the same
// order, as one lane makes.
//
// The rows run along the axis that makes them cheapest (each costs a pass
// over the vertices). A hull cell of points in a box 3x wider than them
// reaches the box's wall; along the wall's normal its balls span a cell or
// two of the grid, across it all of it, and rows along that normal would be
// ~100x as many as along the longest span.
template <typename Cell, typename io_t, typename T>
TV_HD int8_t sweep_vertex_balls(Cell& cell, const VertexBallGrid<io_t>& where, int32_t seed_index,
                                Vec3<T> seed, T listed_dist2, bool& clipped) {
  // Which rows and cells to visit is decided in S (double for double-double:
  // a margin covers its rounding); the clips run in T.
  using S = typename ChoiceScalar<T>::type;
  const auto lanes = cell.group();
  constexpr int kLanes = decltype(lanes)::kCount;
  const int lane = lanes.index();
  const S infinity = S(1) / S(0);
  // Component a of a vector, by selects: indexed by a run-time axis, an
  // array would live in local memory on the GPU.
  const auto along = [](auto v, int a) { return a == 0 ? v.x : (a == 1 ? v.y : v.z); };
  const auto to_s = [](Vec3<T> v) { return Vec3<S>{S(v.x), S(v.y), S(v.z)}; };
  const GridView<io_t>& grid = where.grid;
  const int64_t b = where.batch;
  const S h = S(grid.cell_size[b]);
  const S margin = cell_margin(h);
  const Vec3<S> seed_s = to_s(seed);
  // The grid's origin relative to the seed, as the vertices are.
  const Vec3<S> origin = Vec3<S>{S(grid.origin[3 * b]), S(grid.origin[3 * b + 1]), S(grid.origin[3 * b + 2])} - seed_s;
  const Vec3<int32_t> dim = {grid.dims[3 * b], grid.dims[3 * b + 1], grid.dims[3 * b + 2]};
  const Vec3<int32_t> stride = {1, dim.x, dim.x * dim.y};  // between neighbouring grid cells
  const int32_t first_cell = grid.cell_offset[b];
  const T skip_below = unlisted_from(listed_dist2);
  clipped = false;

  // The bounding box of the balls (each passes through the seed), as grid
  // coordinates [low, high] along each axis.
  Vec3<S> lo = {S(0), S(0), S(0)}, hi = {S(0), S(0), S(0)};
  for (int t = lane; t < cell.vertex_count(); t += kLanes) {
    const Vec3<S> v = to_s(cell.vertex(t));
    const S radius = sqrt_of(squared_norm(v)) + margin;
    lo = {min_of(lo.x, v.x - radius), min_of(lo.y, v.y - radius), min_of(lo.z, v.z - radius)};
    hi = {max_of(hi.x, v.x + radius), max_of(hi.y, v.y + radius), max_of(hi.z, v.z + radius)};
  }
  lo = {lanes.min(lo.x), lanes.min(lo.y), lanes.min(lo.z)};
  hi = {lanes.max(hi.x), lanes.max(hi.y), lanes.max(hi.z)};
  const Vec3<int32_t> low = {grid_coordinate(lo.x, origin.x, h, dim.x), grid_coordinate(lo.y, origin.y, h, dim.y),
                             grid_coordinate(lo.z, origin.z, h, dim.z)};
  const Vec3<int32_t> high = {grid_coordinate(hi.x, origin.x, h, dim.x), grid_coordinate(hi.y, origin.y, h, dim.y),
                              grid_coordinate(hi.z, origin.z, h, dim.z)};
  // The row axis, by the rows' cost: a pass over the vertices a row, plus a
  // range of sorted points a row along x (its cells are contiguous in the
  // grid's order) but a range a cell along y or z. The points visited are
  // about the same either way. Then the two axes across it, the outer last.
  const Vec3<int64_t> cells = {high.x - low.x + 1, high.y - low.y + 1, high.z - low.z + 1};
  const int64_t vertices = cell.vertex_count();
  const int64_t cost_x = cells.y * cells.z * (vertices + 1);
  const int64_t cost_y = cells.x * cells.z * (vertices + cells.y);
  const int64_t cost_z = cells.x * cells.y * (vertices + cells.z);
  const int row_axis = cost_x <= cost_y && cost_x <= cost_z ? 0 : (cost_y <= cost_z ? 1 : 2);
  const int inner = row_axis == 1 ? 0 : 1;
  const int outer = row_axis == 2 ? 0 : 2;
  // Each axis's numbers for the loops below, taken out once.
  struct Axis {
    S origin;
    int32_t dim, stride, seed_cell, low, high;
  };
  const auto axis = [&](int a) {
    const S o = along(origin, a);
    const int32_t d = along(dim, a);
    return Axis{o, d, along(stride, a), grid_coordinate(S(0), o, h, d), along(low, a), along(high, a)};
  };
  const Axis row = axis(row_axis), across = axis(inner), slab = axis(outer);
  const auto steps = [](const Axis& a) { return 2 * max_of(a.seed_cell - a.low, a.high - a.seed_cell) + 1; };

  for (int32_t slab_step = 0; slab_step < steps(slab); ++slab_step) {
    const int32_t c_slab = center_out(slab.seed_cell, slab_step);
    if (c_slab < slab.low || c_slab > slab.high) continue;
    for (int32_t across_step = 0; across_step < steps(across); ++across_step) {
      const int32_t c_across = center_out(across.seed_cell, across_step);
      if (c_across < across.low || c_across > across.high) continue;
      // The part of the row that meets a ball of the cell as it is now.
      S reach_lo = S(0), reach_hi = S(0);
      bool meets = false;
      for (int t = lane; t < cell.vertex_count(); t += kLanes) {
        const Vec3<S> v = to_s(cell.vertex(t));
        const S gap_slab = slab_gap(along(v, outer) - slab.origin, h, c_slab, margin);
        const S gap_across = slab_gap(along(v, inner) - across.origin, h, c_across, margin);
        const S reach2 = squared_norm(v) - gap_slab * gap_slab - gap_across * gap_across;
        if (!(reach2 > S(0))) continue;
        const S reach = sqrt_of(reach2) + margin;
        const S v_row = along(v, row_axis);
        reach_lo = meets ? min_of(reach_lo, v_row - reach) : v_row - reach;
        reach_hi = meets ? max_of(reach_hi, v_row + reach) : v_row + reach;
        meets = true;
      }
      if (!lanes.any(meets)) continue;
      reach_lo = lanes.min(meets ? reach_lo : infinity);
      reach_hi = lanes.max(meets ? reach_hi : -infinity);
      int32_t first = grid_coordinate(reach_lo, row.origin, h, row.dim);
      int32_t last = grid_coordinate(reach_hi, row.origin, h, row.dim);
      const int32_t row_start = first_cell + c_slab * slab.stride + c_across * across.stride;
      // The row's ends cut to the cells whose points' bounds meet a ball: a
      // dense layer fills a thin part of its cells, and the balls of a tall
      // cell above it meet those cells far wider than they meet the layer.
      if (grid.cell_bounds != nullptr) {
        const auto points_meet_a_ball = [&](int32_t c) {
          const int32_t id = row_start + c * row.stride;
          if (grid.cell_start[id + 1] == grid.cell_start[id]) return false;  // no points (the same on every lane)
          const io_t* bounds = grid.cell_bounds + 6 * int64_t(id);
          const Vec3<S> low = Vec3<S>{S(bounds[0]), S(bounds[1]), S(bounds[2])} - seed_s;
          const Vec3<S> high = Vec3<S>{S(bounds[3]), S(bounds[4]), S(bounds[5])} - seed_s;
          bool meets = false;
          for (int t = lane; t < cell.vertex_count() && !meets; t += kLanes) {
            const Vec3<S> v = to_s(cell.vertex(t));
            const Vec3<S> gap = {max_of(max_of(low.x - v.x, v.x - high.x), S(0)),
                                 max_of(max_of(low.y - v.y, v.y - high.y), S(0)),
                                 max_of(max_of(low.z - v.z, v.z - high.z), S(0))};
            const S radius = sqrt_of(squared_norm(v)) + margin;
            meets = squared_norm(gap) < radius * radius;  // false where the cell is empty (infinite gap)
          }
          return lanes.any(meets);
        };
        while (first <= last && !points_meet_a_ball(first)) ++first;
        while (last > first && !points_meet_a_ball(last)) --last;
        if (first > last) continue;
      }
      // Outward from the seed's cell: cells nearest..last, then nearest - 1
      // down to first. Far points first would each cut the cell a little
      // less than the last (a column from a wall, swept from the far wall
      // back to its seed, is cut by nearly every point of the row).
      const int32_t nearest = min_of(max_of(row.seed_cell, first), last);
      for (int side = 0; side < 2; ++side) {
        const int32_t count = side == 0 ? last - nearest + 1 : nearest - first;
        // Along x the side's cells are one range of the sorted points
        // (walked backwards on the near side); along y or z, a range a cell.
        const int32_t ranges = row_axis == 0 ? min_of(count, 1) : count;
        for (int32_t range = 0; range < ranges; ++range) {
          int32_t begin, end;
          if (row_axis == 0) {
            const int32_t low_cell = side == 0 ? nearest : first;
            const int32_t high_cell = side == 0 ? last : nearest - 1;
            begin = grid.cell_start[row_start + low_cell];
            end = grid.cell_start[row_start + high_cell + 1];
          } else {
            const int32_t c = side == 0 ? nearest + range : nearest - 1 - range;
            begin = grid.cell_start[row_start + c * row.stride];
            end = grid.cell_start[row_start + c * row.stride + 1];
          }
          const bool backwards = row_axis == 0 && side == 1;
          for (int32_t batch_start = 0; batch_start < end - begin; batch_start += kLanes) {
            const int32_t step = batch_start + lane;  // this lane's point
            const int32_t s = backwards ? end - 1 - step : begin + step;
            Vec3<T> r = {T(0), T(0), T(0)};
            T r2 = T(0);
            bool copy_kept_elsewhere = false, candidate = false;
            if (step < end - begin) {
              const int32_t j = grid.original_index(s);
              const Vec3<T> p = {T(grid.sorted_points[3 * s]), T(grid.sorted_points[3 * s + 1]),
                                 T(grid.sorted_points[3 * s + 2])};
              r = p - seed;
              r2 = squared_norm(r);
              // An exact copy of the seed: the lowest index keeps the cell.
              copy_kept_elsewhere = r2 == T(0) && j < seed_index;
              candidate = j != seed_index && !(r2 == T(0)) && !(r2 < skip_below) &&
                          !cell.security_radius_reached(r2) && may_cut(cell, r, r2) && !cell.has_bisector(r);
            }
            if (lanes.any(copy_kept_elsewhere)) return kDuplicate;
            uint32_t pending = lanes.ballot(candidate);
            if (pending == 0u) continue;
            lanes.sync();  // the lanes' reads of the cell before the clips write it
            for (; pending != 0u; pending &= pending - 1u) {
              const int from = lowest_bit(pending);
              const Vec3<T> offer = {lanes.broadcast(r.x, from), lanes.broadcast(r.y, from),
                                     lanes.broadcast(r.z, from)};
              // As one lane would test it now: earlier clips of the batch may have settled it.
              if (cell.security_radius_reached(squared_norm(offer)) || cell.has_bisector(offer)) continue;
              if (!cell.clip_by_bisector(offer)) return cell.status;
              clipped = clipped || cell.has_bisector(offer);  // a plane is added where it cuts
            }
          }
        }
      }
    }
  }
  return kSuccess;
}

// Finishes `cell`, clipped by its list (the nearest neighbours up to
// `listed_dist2`), on the grid: sweep; if the sweep clipped, recompute the
// cell (`restart()` clips the list again from the start) and clip it by the
// further neighbours whose bisectors bounded the swept cell, nearest first;
// sweep again; up to kRounds sweeps. Returns kSuccess once a sweep finds
// nothing to clip, kDuplicate, the status of a failed clip, or
// kBoundaryError where the sweeps keep finding planes (rounding that does
// not settle: the caller retries in wider arithmetic). `further` counts the
// further neighbours of the final cell.
template <typename Cell, typename io_t, typename T, typename Restart>
TV_HD int8_t finish_by_vertex_balls(Cell& cell, const VertexBallGrid<io_t>& where, int32_t seed_index,
                                    Vec3<T> seed, T listed_dist2, const Restart& restart, int32_t& further) {
  constexpr int kRounds = 3;
  Vec3<T> offset[Cell::kMaxBisectors];
  T offset2[Cell::kMaxBisectors];
  further = 0;
  for (int round = 0; round < kRounds; ++round) {
    bool clipped = false;
    const int8_t status = sweep_vertex_balls(cell, where, seed_index, seed, listed_dist2, clipped);
    if (status != kSuccess || !clipped) return status;
    // The listed neighbours' bisectors come back with the list (a few at
    // about the last one's distance are also collected; has_bisector skips them).
    const int count = cell.bounding_neighbors(unlisted_from(listed_dist2), offset, offset2);
    cell.group().sync();  // every lane has read the cell before restart() writes it
    restart();
    further = 0;
    for (int i = 0; i < count; ++i) {
      if (cell.security_radius_reached(offset2[i])) break;  // and every later one
      if (i > 0 && nearly_coincident_bisectors(offset[i - 1], offset[i], offset2[i], cell.largest_radius2())) {
        return kIllConditioned;
      }
      if (cell.has_bisector(offset[i])) continue;
      if (!cell.clip_by_bisector(offset[i])) return cell.status;
      further += int32_t(cell.has_bisector(offset[i]));
    }
  }
  return kBoundaryError;
}

}  // namespace core
}  // namespace torchvor
