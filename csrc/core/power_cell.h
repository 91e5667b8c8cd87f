// One cell of a power (Laguerre) diagram: the points y with
// |y - x_i|^2 - w_i <= |y - x_j|^2 - w_j for every j, clipped to the box,
// by the same clip as a Voronoi cell (a ConvexCell with kWeighted) from the
// seed's nearest neighbours by distance, until the power radius of
// security (beyond_power_security_radius) proves the cell exact.
//
// Unlike a Voronoi cell, a power cell need not hold its seed, and it may be
// empty (kEmpty: volume 0, centroid the seed). A point at the seed's very
// position with a larger weight empties the cell (kEmpty); with the same
// weight the lower index keeps it (kDuplicate for the others).
#pragma once

#include <cstdint>

#include "convex_cell.h"
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

// `neighbors`: k global indices sorted by distance to the seed, -1 after the
// last point of its cloud (the seed itself may be among them). `box`: lo, hi.
// `weight_max`: no point outside the list that can cut the cell weighs more.
template <typename io_t, typename Cell, typename T = typename Cell::Scalar>
TV_HD CellIntegrals<T> compute_power_cell(Cell& cell, const io_t* points, const io_t* weights, int64_t seed_index,
                                          const int64_t* neighbors, int64_t k, const io_t* box, T weight_max,
                                          T relative_tolerance) {
  const Vec3<T> seed = {T(points[3 * seed_index]), T(points[3 * seed_index + 1]), T(points[3 * seed_index + 2])};
  const T seed_weight = T(weights[seed_index]);
  const Vec3<T> lo = {T(box[0]), T(box[1]), T(box[2])};
  const Vec3<T> hi = {T(box[3]), T(box[4]), T(box[5])};
  cell.init_box(lo - seed, hi - seed, relative_tolerance);
  cell.spread = max_of(weight_max - seed_weight, T(0));
  CellIntegrals<T> out;
  out.status = kSecurityRadiusNotReached;  // unless the loop proves otherwise
  out.neighbors = static_cast<int32_t>(k);
  Vec3<T> previous = {T(0), T(0), T(0)};
  T previous_shift = T(0);
  bool any_previous = false;
  for (int64_t n = 0; n < k; ++n) {
    const int64_t j = neighbors[n];
    if (j < 0) {  // every point of the cloud has been used
      out.status = kSuccess;
      out.neighbors = static_cast<int32_t>(n);
      break;
    }
    if (j == seed_index) continue;
    const Vec3<T> r = {T(points[3 * j]) - seed.x, T(points[3 * j + 1]) - seed.y, T(points[3 * j + 2]) - seed.z};
    const T r2 = squared_norm(r);
    if (cell.power_security_radius_reached(r2)) {
      out.status = kSuccess;
      out.neighbors = static_cast<int32_t>(n);
      break;
    }
    const T shift = seed_weight - T(weights[j]);
    if (r2 == T(0)) {  // a copy of the seed: the larger weight, then the lower index, keeps the cell
      if (shift < T(0) || (shift == T(0) && j < seed_index)) {
        out.status = shift < T(0) ? kEmpty : kDuplicate;
        out.neighbors = static_cast<int32_t>(n + 1);
        break;
      }
      continue;
    }
    // Copies among the neighbours (adjacent in the list) with equal weights
    // give the same plane twice: clip once.
    if (any_previous && r.x == previous.x && r.y == previous.y && r.z == previous.z && shift == previous_shift) {
      continue;
    }
    previous = r;
    previous_shift = shift;
    any_previous = true;
    if (power_plane_misses(r2, shift, cell.largest_radius2())) continue;
    if (!cell.clip_by_power_plane(r, shift, static_cast<int32_t>(j))) {
      out.status = cell.status;
      out.neighbors = static_cast<int32_t>(n + 1);
      break;
    }
  }
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
