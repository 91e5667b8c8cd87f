// One cell of a power (Laguerre) diagram: the points y with
// |y - x_i|^2 - w_i <= |y - x_j|^2 - w_j for every j, clipped to the box,
// by the same clip as a Voronoi cell (a ConvexCell with kWeighted) from the
// points of the grid cubes around the seed, nearest shells first, until the
// power radius of security (beyond_power_security_radius) proves the cell
// exact. No neighbour list: the weights make the reach of a cell, and so a
// list's length, vary by hundreds of points, and a cube holding no weight
// that can reach the cell is skipped at a few operations.
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

// The distance beyond which no point of weight at most `weight_max` can cut
// a power cell within sqrt(radius2) of its seed (beyond_power_security_radius's
// reach), squared, a little wide.
TV_HD double power_reach2(double radius2, double spread) {
  const double reach = sqrt_of(radius2) + sqrt_of(radius2 + spread);
  return (1.0 + 1e-9) * reach * reach;
}

// The power cell of the point `seed_index`, walking the grid of the points
// (grid_search.h) in Chebyshev shells of cubes around the seed's own: every
// point of a cube that may cut the cell goes to the clip, nearest shells
// first, until no point outside the shells walked can (the power radius of
// security, with `weight_max` the largest weight that can cut) or the shells
// cover the grid. Only the slabs, rows and cubes within that reach are
// visited, and a cube whose nearest point cannot cut the cell even at the
// largest weight it holds (`cube_weight_max`, (cubes,), -inf where empty)
// is skipped whole.
// `sorted_weights`: the weights in the grid's order. `box`: lo, hi. `batch`:
// the seed's grid. out.neighbors: the points examined.
template <typename io_t, typename Cell, typename T = typename Cell::Scalar>
TV_HD CellIntegrals<T> compute_power_cell(Cell& cell, const io_t* points, const io_t* weights, int64_t seed_index,
                                          const GridView<io_t>& grid, const io_t* sorted_weights,
                                          const io_t* cube_weight_max, int64_t batch,
                                          const io_t* box, T weight_max, T relative_tolerance) {
  const Vec3<io_t> seed_io = load_vec3(points + 3 * seed_index);
  const Vec3<T> seed = {T(seed_io.x), T(seed_io.y), T(seed_io.z)};
  const T seed_weight = T(weights[seed_index]);
  const Vec3<T> lo = {T(box[0]), T(box[1]), T(box[2])};
  const Vec3<T> hi = {T(box[3]), T(box[4]), T(box[5])};
  cell.init_box(lo - seed, hi - seed, relative_tolerance);
  cell.spread = max_of(weight_max - seed_weight, T(0));
  CellIntegrals<T> out;
  out.status = kSuccess;
  int32_t examined = 0;
  const Rings<io_t> rings(grid, batch, seed_io);
  // The clip of one point: false once the cell is decided (EMPTY, DUPLICATE,
  // or a failure: out.status).
  // Sorted point s, read from the grid's copies (a cube's points side by
  // side); its index is loaded only for a clip or a copy of the seed.
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
    if (power_plane_misses(r2, shift, cell.largest_radius2())) return true;
    if (!cell.clip_by_power_plane(r, shift, grid.original_index(s))) {
      out.status = cell.status;
      return false;
    }
    return true;
  };
  const io_t h = rings.h;
  const double spread = static_cast<double>(cell.spread);
  bool open = true;
  for (int32_t shell = 0; open; ++shell) {
    // Slabs, rows and cubes from the seed's outwards (center_out): nearer
    // planes first leave fewer vertices for the farther ones to cut. Only
    // those within the current reach, which shrinks with the cell.
    for (int32_t step_z = 0; step_z <= rings.last_step(2, shell) && open; ++step_z) {
      const int32_t z = center_out(rings.cell[2], step_z);
      if (z < rings.low(2, shell) || z > rings.high(2, shell)) continue;
      const double gap_z = static_cast<double>(rings.gap_z(z));
      if (gap_z * gap_z > power_reach2(static_cast<double>(cell.largest_radius2()), spread)) continue;
      const bool z_face = z == rings.cell[2] - shell || z == rings.cell[2] + shell;
      for (int32_t step_y = 0; step_y <= rings.last_step(1, shell) && open; ++step_y) {
        const int32_t y = center_out(rings.cell[1], step_y);
        if (y < rings.low(1, shell) || y > rings.high(1, shell)) continue;
        const double gap_y = static_cast<double>(slab_gap(rings.local.y, h, y, rings.margin));
        const double gap_yz2 = gap_z * gap_z + gap_y * gap_y;
        const double radius2 = static_cast<double>(cell.largest_radius2());
        const double left2 = power_reach2(radius2, spread) - gap_yz2;  // the row's reach along x, squared
        if (left2 < 0.0) continue;
        const io_t left = io_t(sqrt_of(left2)) + rings.margin;
        // On a face of the shell, the row's cubes within reach; inside it, its two end cubes.
        const bool face = z_face || y == rings.cell[1] - shell || y == rings.cell[1] + shell;
        const int32_t xa = max_of(rings.low(0, shell), rings.row_cell(rings.local.x - left, -1));
        const int32_t xb = min_of(rings.high(0, shell), rings.row_cell(rings.local.x + left, 1));
        const int32_t row_start = rings.offset + (z * rings.dim[1] + y) * rings.dim[0];
        const int32_t last_x = face ? rings.last_step(0, shell) : 1;
        for (int32_t step_x = 0; step_x <= last_x && open; ++step_x) {
          const int32_t x = face ? center_out(rings.cell[0], step_x)
                                 : rings.cell[0] + (step_x == 0 ? -shell : shell);
          if (x < xa || x > xb) continue;
          const double weight = static_cast<double>(cube_weight_max[row_start + x]);
          if (!(weight > -1e308)) continue;  // an empty cube
          const double gap_x = static_cast<double>(slab_gap(rings.local.x, h, x, rings.margin));
          if (power_region_misses(gap_yz2 + gap_x * gap_x, static_cast<double>(seed_weight) - weight,
                                  static_cast<double>(cell.largest_radius2()))) {
            continue;
          }
          const int32_t end = grid.cell_start[row_start + x + 1];
          for (int32_t s = grid.cell_start[row_start + x]; s < end && open; ++s) open = offer(s);
        }
      }
    }
    if (!open) break;
    // The distance from the seed to the nearest cube outside the shells walked.
    const io_t u[3] = {rings.local.x, rings.local.y, rings.local.z};
    double bound = 1e308;
    bool covers_grid = true;
    for (int a = 0; a < 3; ++a) {
      if (rings.cell[a] - shell > 0) {
        covers_grid = false;
        bound = min_of(bound, static_cast<double>(u[a] - io_t(rings.cell[a] - shell) * h));
      }
      if (rings.cell[a] + shell < rings.dim[a] - 1) {
        covers_grid = false;
        bound = min_of(bound, static_cast<double>(io_t(rings.cell[a] + shell + 1) * h - u[a]));
      }
    }
    bound -= static_cast<double>(rings.margin);
    if (covers_grid || (bound > 0.0 && cell.power_security_radius_reached(T(bound * bound)))) break;
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
