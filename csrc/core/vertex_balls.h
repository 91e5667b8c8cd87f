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
// cut to the x range that meets the balls of the cell as it is then, offers
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

// Clips `cell` (relative to `seed`, point `seed_index` of the grid's
// points) by every point of the grid in its vertices' balls. Points nearer
// than `listed_dist2` were in the neighbour list that clipped the cell
// already and are skipped; a point at about that distance, or an exact copy
// of a point clipped by, is skipped where its bisector is a plane of the
// cell already (ConvexCell::has_bisector). Returns kSuccess, kDuplicate (an
// exact copy of the seed with a lower index), or the cell's status where a
// clip failed; `clipped`: whether any point cut the cell.
template <typename Cell, typename io_t, typename T>
TV_HD int8_t sweep_vertex_balls(Cell& cell, const VertexBallGrid<io_t>& where, int32_t seed_index,
                                Vec3<T> seed, T listed_dist2, bool& clipped) {
  // Which rows and cells to visit is decided in S (double for double-double:
  // a margin covers its rounding); the clips run in T.
  using S = typename ChoiceScalar<T>::type;
  const auto to_s = [](Vec3<T> v) { return Vec3<S>{S(v.x), S(v.y), S(v.z)}; };
  const GridView<io_t>& grid = where.grid;
  const int64_t b = where.batch;
  const S h = S(grid.cell_size[b]);
  const S margin = h * S(1e-3);  // points go to cells by a rounded division (Rings::margin)
  const Vec3<S> origin = {S(grid.origin[3 * b]), S(grid.origin[3 * b + 1]), S(grid.origin[3 * b + 2])};
  const Vec3<S> seed_s = to_s(seed);
  const int32_t dim[3] = {grid.dims[3 * b], grid.dims[3 * b + 1], grid.dims[3 * b + 2]};
  const int32_t first_cell = grid.cell_offset[b];
  // The kNN ranked the list in the input's precision: a point a rounding
  // away from the last listed one may be missing from it, so it is offered.
  const T skip_below = listed_dist2 * (T(1) - T(1e-4));
  clipped = false;

  // The bounding box of the balls (each passes through the seed), as grid
  // coordinates along z and y.
  Vec3<S> lo = {S(0), S(0), S(0)}, hi = {S(0), S(0), S(0)};
  for (int t = 0; t < cell.vertex_count(); ++t) {
    const Vec3<S> v = to_s(cell.vertex(t));
    const S radius = sqrt_of(squared_norm(v)) + margin;
    lo = {min_of(lo.x, v.x - radius), min_of(lo.y, v.y - radius), min_of(lo.z, v.z - radius)};
    hi = {max_of(hi.x, v.x + radius), max_of(hi.y, v.y + radius), max_of(hi.z, v.z + radius)};
  }
  const int32_t seed_cell_y = grid_coordinate(seed_s.y, origin.y, h, dim[1]);
  const int32_t seed_cell_z = grid_coordinate(seed_s.z, origin.z, h, dim[2]);
  const int32_t y_lo = grid_coordinate(seed_s.y + lo.y, origin.y, h, dim[1]);
  const int32_t y_hi = grid_coordinate(seed_s.y + hi.y, origin.y, h, dim[1]);
  const int32_t z_lo = grid_coordinate(seed_s.z + lo.z, origin.z, h, dim[2]);
  const int32_t z_hi = grid_coordinate(seed_s.z + hi.z, origin.z, h, dim[2]);
  const int32_t z_steps = 2 * max_of(seed_cell_z - z_lo, z_hi - seed_cell_z) + 1;
  const int32_t y_steps = 2 * max_of(seed_cell_y - y_lo, y_hi - seed_cell_y) + 1;
  // The i-th coordinate from c outwards: c, c - 1, c + 1, c - 2, ...
  const auto center_out = [](int32_t c, int32_t i) { return c + ((i & 1) ? -((i + 1) >> 1) : (i >> 1)); };
  // Distance from x to the slab [low, low + h] (relative to the seed), less the margin.
  const auto gap = [&](S x, S low) { return max_of(max_of(low - x, x - (low + h)) - margin, S(0)); };

  for (int32_t step_z = 0; step_z < z_steps; ++step_z) {
    const int32_t z = center_out(seed_cell_z, step_z);
    if (z < z_lo || z > z_hi) continue;
    const S z_low = origin.z + S(z) * h - seed_s.z;
    for (int32_t step_y = 0; step_y < y_steps; ++step_y) {
      const int32_t y = center_out(seed_cell_y, step_y);
      if (y < y_lo || y > y_hi) continue;
      const S y_low = origin.y + S(y) * h - seed_s.y;
      // The x range of the row that meets a ball of the cell as it is now.
      S x_lo = S(0), x_hi = S(0);
      bool meets = false;
      for (int t = 0; t < cell.vertex_count(); ++t) {
        const Vec3<S> v = to_s(cell.vertex(t));
        const S gap_y = gap(v.y, y_low), gap_z = gap(v.z, z_low);
        const S reach2 = squared_norm(v) - gap_y * gap_y - gap_z * gap_z;
        if (!(reach2 > S(0))) continue;
        const S reach = sqrt_of(reach2) + margin;
        x_lo = meets ? min_of(x_lo, v.x - reach) : v.x - reach;
        x_hi = meets ? max_of(x_hi, v.x + reach) : v.x + reach;
        meets = true;
      }
      if (!meets) continue;
      const int32_t xa = grid_coordinate(seed_s.x + x_lo, origin.x, h, dim[0]);
      const int32_t xb = grid_coordinate(seed_s.x + x_hi, origin.x, h, dim[0]);
      const int32_t row_start = first_cell + (z * dim[1] + y) * dim[0];
      const int32_t end = grid.cell_start[row_start + xb + 1];
      for (int32_t s = grid.cell_start[row_start + xa]; s < end; ++s) {
        const int32_t j = grid.original_index(s);
        if (j == seed_index) continue;
        const Vec3<T> p = {T(grid.sorted_points[3 * s]), T(grid.sorted_points[3 * s + 1]),
                           T(grid.sorted_points[3 * s + 2])};
        const Vec3<T> r = p - seed;
        const T r2 = squared_norm(r);
        if (r2 == T(0)) {  // an exact copy: the lowest index keeps the cell
          if (j < seed_index) return kDuplicate;
          continue;
        }
        if (r2 < skip_below || cell.security_radius_reached(r2) || cell.has_bisector(r)) continue;
        if (!cell.clip_by_bisector(r)) return cell.status;
        clipped = clipped || cell.has_bisector(r);  // a plane is added where it cuts
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
    const int count = cell.bounding_neighbors(listed_dist2 * (T(1) - T(1e-4)), offset, offset2);
    restart();
    further = 0;
    for (int i = 0; i < count; ++i) {
      if (cell.security_radius_reached(offset2[i])) break;  // and every later one
      if (cell.has_bisector(offset[i])) continue;
      if (!cell.clip_by_bisector(offset[i])) return cell.status;
      further += int32_t(cell.has_bisector(offset[i]));
    }
  }
  return kBoundaryError;
}

}  // namespace core
}  // namespace torchvor
