// The planes of a cell in dual form (convex_cell.h): the box's faces and
// the bisectors, where three meet (the vertices), and the predicates the
// clip decides by (paper §3.2-3.3). Coordinates are local to the seed.
#pragma once

#include <cstdint>
#include <type_traits>

#include "common.h"
#include "double_double.h"

namespace torchvor {
namespace core {

// Relative tolerance of the clipping predicate: a vertex is clipped only if it
// lies more than tolerance * |r|^2 outside the bisector of a neighbour at r.
// Points on a plane are kept, so cospherical configurations (lattices) and
// near-coincident vertices resolve the same way from every triangle.
template <typename T> struct ClipTolerance;
template <> struct ClipTolerance<float> { static constexpr float value = 2e-6f; };
template <> struct ClipTolerance<double> { static constexpr double value = 1e-13; };
template <> struct ClipTolerance<DoubleDouble> { static constexpr double value = 1e-28; };

// Planes 0-5 of every cell are the box's faces (box_plane); the bisectors
// follow.
constexpr int kBoxPlanes = 6;

// The box [lo, hi] (relative to the seed): plane q of kBoxPlanes, and the corners
// (plane ids packed as a | b << 8 | c << 16) of its dual triangle t of 8.
// (No local arrays: indexed by a lane number they would go to local memory.)
template <typename T>
TV_HD Plane<T> box_plane(int q, Vec3<T> lo, Vec3<T> hi) {
  const int axis = q >> 1;
  const bool upper = (q & 1) != 0;  // the face at hi, facing -axis
  const T sign = upper ? T(-1) : T(1);
  const T low = axis == 0 ? lo.x : (axis == 1 ? lo.y : lo.z);
  const T high = axis == 0 ? hi.x : (axis == 1 ? hi.y : hi.z);
  return {{axis == 0 ? sign : T(0), axis == 1 ? sign : T(0), axis == 2 ? sign : T(0)},
          upper ? high : -low};
}
TV_HD uint32_t box_triangle(int t) {
  switch (t) {  // planes (a, b, c), one byte each, a lowest
    case 0: return 0x000502u;
    case 1: return 0x000305u;
    case 2: return 0x020501u;
    case 3: return 0x030105u;
    case 4: return 0x000204u;
    case 5: return 0x030004u;
    case 6: return 0x010402u;
    default: return 0x010304u;
  }
}

// Intersection point of three planes (Cramer's rule).
template <typename T>
TV_HD Vec3<T> cramer_point(const Plane<T>& pa, const Plane<T>& pb, const Plane<T>& pc) {
  const Vec3<T> bc = cross(pb.normal, pc.normal);
  const Vec3<T> ca = cross(pc.normal, pa.normal);
  const Vec3<T> ab = cross(pa.normal, pb.normal);
  const T det = dot(pa.normal, bc);
  const T scale = T(-1) / det;
  return scale * (pa.offset * bc + pb.offset * ca + pc.offset * ab);
}

// Intersection point of three planes. Three nearly parallel planes
// (bisectors of a tight cluster seen from afar) have a determinant of their
// normals of about |n|^3 angle^2, and its rounding, a few eps |n|^3, scales
// the vertex by up to eps / angle^2: off its own planes and across others
// that nearly meet there, so that the cell's faces join wrongly (float64
// cells of tight clusters off in volume). Where b and c are within |n_a| / 2 of
// a, they are taken relative to a (normals and offsets minus a's: the same
// point, the same determinant), whose differences from nearly equal normals
// are exact. Not otherwise: a normal much shorter than a's (a nearer
// neighbour's) would lose its digits in the difference. In double only: the
// float kernels (the speed targets, whose tolerances allow for such
// vertices) keep the plain rule, as does double-double, whose precision
// resolves them.
template <typename T>
TV_HD Vec3<T> intersect_planes(const Plane<T>& pa, const Plane<T>& pb, const Plane<T>& pc) {
  if constexpr (std::is_same<T, double>::value) {
    const Vec3<T> eb = pb.normal - pa.normal, ec = pc.normal - pa.normal;
    const T near2 = T(0.25) * squared_norm(pa.normal);
    const bool relative = squared_norm(eb) < near2 && squared_norm(ec) < near2;
    const Plane<T> qb = relative ? Plane<T>{eb, pb.offset - pa.offset} : pb;
    const Plane<T> qc = relative ? Plane<T>{ec, pc.offset - pa.offset} : pc;
    return cramer_point(pa, qb, qc);
  } else {
    return cramer_point(pa, pb, pc);
  }
}

// The same in double-double (the last-resort pass), whose bisectors' normals
// are exact (-(p - seed)): of a pair of nearly parallel planes (normals
// within half the first's length), the second is taken relative to the
// first, and for two bisectors the difference's offset, (|n_b|^2 -
// |n_a|^2) / 2, is computed as (n_b - n_a) . (n_b + n_a) / 2, which keeps
// its digits where the offsets' own difference would cancel. Any pair, not
// only b and c against a: close pairs of points (a few ulps apart) make a
// nearly parallel pair beside a plane at any angle. `bisector`: which of
// a, b, c are bisectors (the others are box faces); `shift`: their power
// shifts (power_plane; 0 for Voronoi cells), whose difference joins the
// offsets' for a pair of power bisectors.
TV_HD Vec3<DoubleDouble> intersect_planes(const Plane<DoubleDouble>& pa, const Plane<DoubleDouble>& pb,
                                          const Plane<DoubleDouble>& pc, const bool (&bisector)[3],
                                          const DoubleDouble (&shift)[3]) {
  using P = Plane<DoubleDouble>;
  const auto near = [](const P& first, const P& second) {
    return squared_norm(second.normal - first.normal) < DoubleDouble(0.25) * squared_norm(first.normal);
  };
  const auto relative = [&](int f, const P& first, int s, const P& second) -> P {
    const Vec3<DoubleDouble> e = second.normal - first.normal;
    if (!(bisector[f] && bisector[s])) return {e, second.offset - first.offset};
    return {e, DoubleDouble(0.5) * (dot(e, second.normal + first.normal) + (shift[s] - shift[f]))};
  };
  const bool ab = near(pa, pb), ac = near(pa, pc);
  if (ab || ac) {
    return cramer_point(pa, ab ? relative(0, pa, 1, pb) : pb, ac ? relative(0, pa, 2, pc) : pc);
  }
  if (near(pb, pc)) return cramer_point(pa, pb, relative(1, pb, 2, pc));
  return cramer_point(pa, pb, pc);
}

// The bisector of the seed (origin) and a neighbour at r (|r|^2 = r2), the
// seed's side inside.
template <typename T>
TV_HD Plane<T> bisector_plane(Vec3<T> r, T r2) {
  return {{-r.x, -r.y, -r.z}, T(0.5) * r2};
}

// The power bisector of the seed (origin, weight w_seed) and a neighbour at r
// (weight w_j): {y : |y|^2 - w_seed <= |y - r|^2 - w_j}, i.e. the bisector
// moved by shift = w_seed - w_j along r. A shift below -r2 puts the seed
// outside it (the seed then lies outside its own cell).
template <typename T>
TV_HD Plane<T> power_plane(Vec3<T> r, T r2, T shift) {
  return {{-r.x, -r.y, -r.z}, T(0.5) * (r2 + shift)};
}

// Radius of security (paper §3.1): a neighbour farther than twice the cell's
// radius cannot cut it, nor can any later (farther) neighbour.
template <typename T>
TV_HD bool beyond_security_radius(T neighbor_dist2, T cell_radius2, T tolerance) {
  const T slack = T(1) + T(64) * tolerance;
  return neighbor_dist2 > T(4) * slack * cell_radius2;
}

// A cell's vertices are rounded to about eps times their distance from the
// seed. While they lie far beyond a bisector (a box start, or a long wedge,
// cut by neighbours a few ulps away), that rounding is not small beside the
// bisector's distance, and wrong sides or wrong lines where nearly parallel
// bisectors meet make a wrong cell. It is then recomputed wider
// (kIllConditioned). float: beyond 4096 times the bisector's distance, and
// only where a vertex lies within 8 roundings of it (rounding_could_cut;
// not more: axis-aligned planes, as anisotropic lattices have, round far
// less than this bound on the Euclidean radius assumes). double, whose
// rounding is 2^29 times finer: beyond 2^32 times, whatever the vertices
// (the line where two bisectors of points a few ulps apart meet slides by
// eps |v| / sine, across the cell: no vertex need come near the plane).
template <typename T>
TV_HD bool far_beside_bisector(T r2, T radius2) {
  if constexpr (std::is_same<T, float>::value) return r2 * T(16777216) < radius2;  // |r| < 2^-12 sqrt(radius2)
  if constexpr (std::is_same<T, double>::value) return r2 * T(18446744073709551616.0) < radius2;  // |r| < 2^-32
  return false;
}
// `value`: the plane's at a vertex (n . v + o, |n| = |r|); band2: r2 * radius2
// (0: never).
template <typename T>
TV_HD bool rounding_could_cut(T value, T band2) {
  if constexpr (!std::is_same<T, float>::value) return band2 > T(0);
  const T scaled = value * T(2097152);  // |value| < 2^-21 |r| sqrt(radius2)
  return scaled * scaled < band2;
}

// Bisectors of two neighbours in nearly the same direction at nearly the
// same distance (a close pair, a few ulps apart, beside the seed) meet at a
// small sine s along a line through the cell. The tolerance band around
// each (ClipTolerance: tol |r|) then spans about tol |r| / s along that line,
// and the cell can keep a needle of no volume that far past its exact end:
// a float cell beside two such pairs reached 31% past its exact radius, its
// volume within 3e-7. float: s under 1e-3 (a needle under 4e-3 of the
// radius), where the planes cross within twice the cell's radius, makes the
// cell recomputed wider (kIllConditioned); exactly parallel planes never
// cross. a, b: neighbours relative to the seed, consecutive in the sorted
// list (a close pair's two points are), |a| <= |b|, b2 = |b|^2; radius2:
// the cell's before b clips it.
template <typename T>
TV_HD bool nearly_coincident_bisectors(Vec3<T> a, Vec3<T> b, T b2, T radius2) {
  if constexpr (std::is_same<T, float>::value) {
    // Crossing within 2 R at a sine s under 1e-3 needs |b| - |a| <= 4 s R
    // (below), so |b - a|^2 <= 16 s^2 R^2 + s^2 |b|^2: a test without a root
    // (with a margin) that almost every pair fails, the same way each time.
    const Vec3<T> apart = b - a;
    if (dot(apart, apart) > T(2e-5) * radius2 + T(1.1e-6) * b2) return false;
    const T a2 = dot(a, a);
    if (!(a2 > T(0)) || !(dot(a, b) > T(0))) return false;
    // From b - a (exact for such a pair: Sterbenz), not b: a x b = a x (b - a)
    // and |b|^2 - |a|^2 = (b - a) . (a + b), without the cancellation that
    // would drown a sine or a gap near float's resolution.
    const T unit = rsqrt_of(a2);  // lengths in units of |a|: no underflow for tiny cells
    const Vec3<T> c = cross(unit * a, unit * apart);
    const T c2 = dot(c, c);        // s^2 |b|^2 / |a|^2
    const T w2 = b2 * unit * unit;  // |b|^2 / |a|^2
    constexpr T kSine = T(1e-3);
    if (!(c2 > T(0) && c2 < kSine * kSine * w2)) return false;
    // The planes lie (|b| - |a|) / 2 <= d / 4 apart (d = w2 - 1), so they
    // cross within 2 R where d^2 / 16 <= 4 s^2 R^2, in units of |a|.
    const T d = dot(apart, a + b) * unit * unit;
    return d * d * w2 <= T(64) * c2 * (radius2 * unit * unit);
  }
  return false;
}

// A new vertex lies on an edge of the cell it cuts, so within that cell's
// radius. One beyond it (by more than rounding: a thousandth) was put on a
// line where two planes meet only at a point of the cell: a vertex where
// four or more planes meet (cospherical points), whose triangles' rounded
// copies fell on both sides of the plane. The cell is then recomputed wider
// (kIllConditioned); left, the vertex stays outside the exact cell as a
// spike of no volume that a later plane may never reach.
// (Not for double-double cells: their exact predicates are never inconsistent.)
template <typename T>
TV_HD bool beyond_the_cell(T vertex_radius2, T cell_radius2) {
  if constexpr (std::is_same<T, float>::value || std::is_same<T, double>::value) {
    return vertex_radius2 > cell_radius2 * T(1.001);
  }
  return false;
}

}  // namespace core
}  // namespace torchvor
