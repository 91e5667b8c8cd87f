// One cell of a power (Laguerre) diagram: the points y with
// |y - x_i|^2 - w_i <= |y - x_j|^2 - w_j for every j, clipped to the box,
// by the same clip as a Voronoi cell (a ConvexCell with kWeighted) from the
// points of the grid cubes around the seed, nearest shells first, until the
// power radius of security (power_reach2) proves the cell exact. No
// neighbour list: the weights make the reach of a cell, and so a list's
// length, vary by hundreds of points, and a cube holding no weight that can
// reach the cell is skipped at a few operations.
//
// Unlike a Voronoi cell, a power cell need not hold its seed, and it may be
// empty (kEmpty: volume 0, centroid the seed). A point at the seed's very
// position with a larger weight empties the cell (kEmpty); with the same
// weight the lower index keeps it (kDuplicate for the others).
#pragma once

#include <cstdint>

#include "convex_cell.h"
#include "grid_search.h"
#include "voronoi_cell.h"

namespace torchvor {
namespace core {

// Whether the power plane of a neighbour at squared distance r2 (shift =
// w_seed - w_j) keeps every point within sqrt(radius2) of the seed, so that
// its clip would remove nothing: the plane's value there is at least
// (r2 + shift) / 2 - sqrt(r2 radius2). Decided in double with a margin far
// above its rounding; a plane it does not rule out goes to the clip. Most of
// a long list (the radius of security reaches as far as the largest weight
// asks) is ruled out here at a few operations each.
template <typename T>
TV_HD bool power_plane_misses(T r2, T shift, T radius2) {
  const double d2 = static_cast<double>(r2), s = static_cast<double>(shift);
  const double reach = sqrt_of(d2 * static_cast<double>(radius2));
  const double lowest = 0.5 * (d2 + s) - reach;
  return lowest > 1e-12 * (d2 + (s < 0.0 ? -s : s) + reach);
}

// Whether no point at squared distance `gap2` or more from the seed, of
// weight at most `weight`, can cut a cell within sqrt(radius2) of it:
// power_plane_misses at the nearest such point (past the radius its bound
// grows with the distance), squared instead of a root, with room for the
// rounding. Skips a whole cube.
TV_HD bool power_region_misses(double gap2, double shift, double radius2) {
  const double half = 0.5 * (gap2 + shift);
  return gap2 >= radius2 && half > 0.0 && half * half > (1.0 + 1e-9) * gap2 * radius2 + 1e-300;
}

// The radius of security of a power cell (the 2021 successor of the paper),
// squared, a little wide: a point at distance d cuts a cell within
// sqrt(radius2) of the seed only if d^2 - 2 R d < w_j - w_seed, so none
// farther than R + sqrt(R^2 + spread) can, spread = (the largest weight that
// can cut) - w_seed >= 0. Equal weights: 2 R.
TV_HD double power_reach2(double radius2, double spread) {
  const double reach = sqrt_of(radius2) + sqrt_of(radius2 + spread);
  return (1.0 + 1e-9) * reach * reach;
}

// The walk of one power cell over the grid of the points (grid_search.h):
// Chebyshev shells of cubes around the seed's own, and in each the slabs,
// rows and cubes from the seed's outwards (center_out: nearer planes first
// leave fewer vertices for the farther ones to cut), visiting only those
// within the cell's current reach (power_reach2, which shrinks with the
// cell) and skipping a cube whose nearest point cannot cut the cell even at
// the largest weight it holds. A resumable iterator: next() gives one point
// at a time, so that the threads of a warp clip in step whatever the cubes
// each met (nested loops over them would run each thread's clips apart).
template <typename io_t>
struct PowerWalk {
  const GridView<io_t>& grid;
  const io_t* cube_weight_max;  // (cubes,), -inf where empty
  Rings<io_t> rings;
  double seed_weight, spread;   // spread: the largest weight that can cut, less the seed's (>= 0)
  int32_t shell = 0, step_z = -1, step_y = 0, step_x = 0, last_x = 0;
  int32_t z = 0, xa = 0, xb = -1, row_start = 0, s = 0, end = 0;
  double gap_z2 = 0.0, gap_yz2 = 0.0;
  bool z_face = false, face = false, in_slab = false, in_row = false;

  TV_HD PowerWalk(const GridView<io_t>& g, const io_t* weight_max_of_cubes, int64_t batch, Vec3<io_t> seed,
                  double seed_w, double spread_)
      : grid(g), cube_weight_max(weight_max_of_cubes), rings(g, batch, seed), seed_weight(seed_w), spread(spread_) {}

  // Passes over shells 0 and 1 (the 27 cubes around the seed's, offered
  // already): next() goes on from shell 2, once shell 1 proves not to
  // finish the cell.
  TV_HD void pass_first_shells() {
    shell = 1;
    step_z = rings.last_step(2, 1);
  }

  // The next sorted point to offer the cell of squared radius `radius2`, or
  // -1: no point left that can cut it.
  TV_HD int32_t next(double radius2) {
    for (;;) {
      if (s < end) return s++;
      if (in_row) {  // the row's next cube
        if (++step_x > last_x) {
          in_row = false;
          continue;
        }
        const int32_t x = face ? center_out(rings.cell[0], step_x) : rings.cell[0] + (step_x == 0 ? -shell : shell);
        if (x < xa || x > xb) continue;
        const double weight = static_cast<double>(cube_weight_max[row_start + x]);
        if (!(weight > -1e308)) continue;  // an empty cube
        const double gap_x = static_cast<double>(slab_gap(rings.local.x, rings.h, x, rings.margin));
        if (power_region_misses(gap_yz2 + gap_x * gap_x, seed_weight - weight, radius2)) continue;
        s = grid.cell_start[row_start + x];
        end = grid.cell_start[row_start + x + 1];
        continue;
      }
      if (in_slab) {  // the slab's next row
        if (++step_y > rings.last_step(1, shell)) {
          in_slab = false;
          continue;
        }
        const int32_t y = center_out(rings.cell[1], step_y);
        if (y < rings.low(1, shell) || y > rings.high(1, shell)) continue;
        const double gap_y = static_cast<double>(slab_gap(rings.local.y, rings.h, y, rings.margin));
        gap_yz2 = gap_z2 + gap_y * gap_y;
        const double left2 = power_reach2(radius2, spread) - gap_yz2;  // the row's reach along x, squared
        if (left2 < 0.0) continue;
        const io_t left = io_t(sqrt_of(left2)) + rings.margin;
        // On a face of the shell, the row's cubes within reach; inside it, its two end cubes.
        face = z_face || y == rings.cell[1] - shell || y == rings.cell[1] + shell;
        xa = max_of(rings.low(0, shell), rings.row_cell(rings.local.x - left, -1));
        xb = min_of(rings.high(0, shell), rings.row_cell(rings.local.x + left, 1));
        row_start = rings.offset + (z * rings.dim[1] + y) * rings.dim[0];
        last_x = face ? rings.last_step(0, shell) : 1;
        step_x = -1;
        in_row = true;
        continue;
      }
      if (++step_z <= rings.last_step(2, shell)) {  // the shell's next slab
        z = center_out(rings.cell[2], step_z);
        if (z < rings.low(2, shell) || z > rings.high(2, shell)) continue;
        const double gap_z = static_cast<double>(rings.gap_z(z));
        gap_z2 = gap_z * gap_z;
        if (gap_z2 > power_reach2(radius2, spread)) continue;
        z_face = z == rings.cell[2] - shell || z == rings.cell[2] + shell;
        step_y = -1;
        in_slab = true;
        continue;
      }
      if (finished(radius2)) return -1;
      ++shell;
      step_z = -1;
    }
  }

  // Whether, shell `shell` walked, no point outside it can cut the cell:
  // the shells cover the grid, or the nearest cube outside lies beyond the
  // cell's reach.
  TV_HD bool finished(double radius2) const {
    const io_t u[3] = {rings.local.x, rings.local.y, rings.local.z};
    double bound = 1e308;  // the distance from the seed to the nearest cube outside the shells
    bool covers_grid = true;
    for (int a = 0; a < 3; ++a) {
      if (rings.cell[a] - shell > 0) {
        covers_grid = false;
        bound = min_of(bound, static_cast<double>(u[a] - io_t(rings.cell[a] - shell) * rings.h));
      }
      if (rings.cell[a] + shell < rings.dim[a] - 1) {
        covers_grid = false;
        bound = min_of(bound, static_cast<double>(io_t(rings.cell[a] + shell + 1) * rings.h - u[a]));
      }
    }
    bound -= static_cast<double>(rings.margin);
    return covers_grid || (bound > 0.0 && bound * bound > power_reach2(radius2, spread));
  }
};

// The points of the 27 cubes around the seed's (the walk's shells 0 and 1),
// sorted by the distance of their power planes from the seed (negative
// behind it): clipped nearest first, most of them make the cell's faces at
// once and the rest miss it, where the walk's order would clip a plane that
// a nearer one then removes. Keeps the kCapacity nearest; past that,
// `overflow`, and every point dropped lies at least as far as the farthest
// kept (`last()`).
template <int kCapacity>
struct NearestFirst {
  float distance[kCapacity];
  int32_t point[kCapacity];
  int count = 0;
  bool overflow = false;

  TV_HD void add(int32_t s, float d) {
    if (count == kCapacity) {
      overflow = true;
      if (!(d < distance[kCapacity - 1])) return;
      --count;  // the farthest makes room
    }
    int i = count++;
    for (; i > 0 && distance[i - 1] > d; --i) {
      distance[i] = distance[i - 1];
      point[i] = point[i - 1];
    }
    distance[i] = d;
    point[i] = s;
  }
  TV_HD float last() const { return distance[count - 1]; }
};

// The points NearestFirst keeps: the 27 cubes of about 2 points each hold
// more in clustered clouds and a few percent of white noise's cells, where
// the walk offers the farther ones.
constexpr int kNearestFirstPoints = 64;

// The distance from the seed of the power plane of sorted point s, in float
// (an order, not a predicate): (|r|^2 + w_seed - w_s) / |r|, twice the
// plane's; -inf at the seed's position (copies first). `scale`: the sum's
// magnitude, (|r|^2 + |w_seed - w_s|) / |r|, on which it is rounded.
template <typename io_t>
TV_HD float nearest_first_distance(const GridView<io_t>& grid, const io_t* sorted_weights, int32_t s,
                                   Vec3<io_t> seed, io_t seed_weight, float& scale) {
  const float x = float(grid.sorted_points[3 * s] - seed.x), y = float(grid.sorted_points[3 * s + 1] - seed.y),
              z = float(grid.sorted_points[3 * s + 2] - seed.z);
  const float r2 = x * x + y * y + z * z, shift = float(seed_weight - sorted_weights[s]);
  if (!(r2 > 0.0f)) {
    scale = 0.0f;
    return -INFINITY;
  }
  const float length = sqrt_of(r2);
  scale = (r2 + (shift < 0.0f ? -shift : shift)) / length;
  return (r2 + shift) / length;
}

// The power cell of the point `seed_index`: clipped by every point of its
// walk (PowerWalk) until none is left that can cut it (the power radius of
// security, with `weight_max` the largest weight that can cut, or the whole
// grid). `sorted_weights`: the weights in the grid's order. `box`: lo, hi.
// `batch`: the seed's grid. `nearest_first`: the 27 cubes around the seed's
// first, nearest first (NearestFirst). out.neighbors: the points examined.
template <typename io_t, typename Cell, typename T = typename Cell::Scalar>
TV_HD CellIntegrals<T> compute_power_cell(Cell& cell, const io_t* points, const io_t* weights, int64_t seed_index,
                                          const GridView<io_t>& grid, const io_t* sorted_weights,
                                          const io_t* cube_weight_max, int64_t batch,
                                          const io_t* box, double weight_max, T relative_tolerance,
                                          bool nearest_first) {
  const Vec3<io_t> seed_io = load_vec3(points + 3 * seed_index);
  const Vec3<T> seed = {T(seed_io.x), T(seed_io.y), T(seed_io.z)};
  const T seed_weight = T(weights[seed_index]);
  const Vec3<T> lo = {T(box[0]), T(box[1]), T(box[2])};
  const Vec3<T> hi = {T(box[3]), T(box[4]), T(box[5])};
  cell.init_box(lo - seed, hi - seed, relative_tolerance);
  // The reach and the planes' misses take the cell's radius as wide as the
  // security radius does (beyond_security_radius): its vertices are rounded.
  const T slack = T(1) + T(64) * relative_tolerance;
  const auto reach_radius2 = [&]() { return static_cast<double>(slack * cell.largest_radius2()); };
  CellIntegrals<T> out;
  out.status = kSuccess;
  int32_t examined = 0;
  // The clip by sorted point s: false once the cell is decided (EMPTY,
  // DUPLICATE, or a failure: out.status). The point is read from the grid's
  // copies (a cube's points side by side); its index is loaded only for a
  // clip or a copy of the seed.
  const auto offer = [&](int32_t s) -> bool {
    const Vec3<T> r = {T(grid.sorted_points[3 * s]) - seed.x, T(grid.sorted_points[3 * s + 1]) - seed.y,
                       T(grid.sorted_points[3 * s + 2]) - seed.z};
    const T r2 = squared_norm(r);
    const T shift = seed_weight - T(sorted_weights[s]);
    const int64_t j = r2 == T(0) ? grid.original_index(s) : -1;
    if (j == seed_index) return true;
    ++examined;
    if (r2 == T(0)) {  // a copy of the seed: the larger weight, then the lower index, keeps the cell
      if (shift < T(0) || (shift == T(0) && j < seed_index)) {
        out.status = shift < T(0) ? kEmpty : kDuplicate;
        return false;
      }
      return true;
    }
    // A copy of a point already clipped gives the same plane again, which
    // then misses the cell (its vertices lie within the clip's tolerance).
    if (power_plane_misses(r2, shift, T(reach_radius2()))) return true;
    if (!cell.clip_by_power_plane(r, shift, grid.original_index(s))) {
      out.status = cell.status;
      return false;
    }
    return true;
  };
  const double seed_weight_exact = static_cast<double>(weights[seed_index]);
  PowerWalk<io_t> walk(grid, cube_weight_max, batch, seed_io, seed_weight_exact,
                       max_of(weight_max - seed_weight_exact, 0.0));
  // The 27 cubes around the seed's nearest first, then the walk from shell
  // 2 on (from the start, past the points already offered, where the cubes
  // held more than NearestFirst keeps).
  NearestFirst<kNearestFirstPoints> nearest;
  const Rings<io_t>& rings = walk.rings;
  const io_t seed_weight_io = weights[seed_index];
  float scale = 0.0f;
  for (int32_t z = rings.low(2, 1); nearest_first && z <= rings.high(2, 1); ++z) {
    for (int32_t y = rings.low(1, 1); y <= rings.high(1, 1); ++y) {
      const int32_t row = rings.offset + (z * rings.dim[1] + y) * rings.dim[0];
      const int32_t last = grid.cell_start[row + rings.high(0, 1) + 1];
      for (int32_t s = grid.cell_start[row + rings.low(0, 1)]; s < last; ++s) {
        nearest.add(s, nearest_first_distance(grid, sorted_weights, s, seed_io, seed_weight_io, scale));
      }
    }
  }
  bool going = true;
  for (int i = 0; i < nearest.count && going; ++i) going = offer(nearest.point[i]);
  if (nearest_first && !nearest.overflow) walk.pass_first_shells();
  // Past an overflow, shells 0 and 1 offer the points not kept: those at
  // least as far as the last kept, less a margin far above the distance's
  // rounding (which may differ where it is inlined). A point kept and
  // offered again gives the same plane, which then misses the cell.
  const float kept = nearest.overflow ? nearest.last() : -INFINITY;
  for (int32_t s = going ? walk.next(reach_radius2()) : -1; s >= 0; s = walk.next(reach_radius2())) {
    if (nearest.overflow && walk.shell <= 1) {
      const float d = nearest_first_distance(grid, sorted_weights, s, seed_io, seed_weight_io, scale);
      if (d + 1e-4f * scale < kept) continue;
    }
    if (!offer(s)) break;
  }
  out.neighbors = examined;
  if (out.status == kDuplicate || out.status == kEmpty) {
    out.radius = 0.0f;
    out.volume = T(0);
    out.centroid = seed;
    out.second_moment = T(0);
    return out;
  }
  integrate_cell<io_t>(cell, seed, out);
  return out;
}

}  // namespace core
}  // namespace torchvor
