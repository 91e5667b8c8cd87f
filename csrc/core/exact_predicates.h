// The exact sign of the clip predicate, for the last-resort pass (double-
// double cells, on the host only).
//
// A vertex of a cell is where three planes a, b, c meet; plane q cuts it
// away when f = n_q . v + o_q < 0. With the planes as rows (n, o) of a 4x4
// matrix M (rows a, b, c, q), M (v, 1) = (0, 0, 0, f), and Cramer's rule for
// the last unknown gives det(M) = f det(n_a, n_b, n_c): the sign of f is the
// product of two determinants' signs, polynomials in the planes' entries.
// The entries of a double-double cell are exact: a bisector's normal is
// -(p - seed) (the difference of two doubles, held exactly by a double-
// double) and its offset |normal|^2 / 2; a box face's normal is a unit axis
// and its offset the wall's exact distance from the seed. So the signs can
// be computed exactly, with expansions (exact sums of doubles: Shewchuk,
// "Adaptive precision floating-point arithmetic and fast robust geometric
// predicates", 1997). Every vertex then falls on the same side of a plane
// from every triangle that names it, and a clip's removed region is always
// a disc: the predicates cannot be inconsistent. A vertex exactly on the
// plane is kept, as the rounded predicates keep it.
//
// Most signs are decided by a filter: each vertex keeps its homogeneous
// coordinates in double-double with bounds on their errors, and a sign is
// a dot product with the plane's row, in double, then in double-double,
// wherever the bound cannot flip it; only near-degenerate ones (cospherical
// points, near-parallel planes) are expanded exactly.
#pragma once

#include <cmath>
#include <vector>

#include "common.h"
#include "double_double.h"

namespace torchvor {
namespace core {
namespace exact {

// An exact sum of doubles, nonoverlapping, in increasing magnitude, without
// zeros: its sign is its last term's.
using Expansion = std::vector<double>;

inline void two_sum(double a, double b, double& sum, double& error) {
  sum = a + b;
  const double b_virtual = sum - a;
  const double a_virtual = sum - b_virtual;
  error = (a - a_virtual) + (b - b_virtual);
}

inline void two_product(double a, double b, double& product, double& error) {
  product = a * b;
  error = std::fma(a, b, -product);
}

// e + b (Shewchuk's Grow-Expansion, zeros dropped).
inline Expansion grow(const Expansion& e, double b) {
  Expansion out;
  out.reserve(e.size() + 1);
  double carry = b;
  for (const double term : e) {
    double sum, error;
    two_sum(carry, term, sum, error);
    if (error != 0.0) out.push_back(error);
    carry = sum;
  }
  if (carry != 0.0) out.push_back(carry);
  return out;
}

inline Expansion add(Expansion e, const Expansion& f) {
  for (const double term : f) e = grow(e, term);
  return e;
}

inline Expansion negate(Expansion e) {
  for (double& term : e) term = -term;
  return e;
}

inline Expansion scale(const Expansion& e, double b) {
  Expansion out;
  for (const double term : e) {
    double product, error;
    two_product(term, b, product, error);
    out = grow(grow(out, error), product);
  }
  return out;
}

inline Expansion multiply(const Expansion& e, const Expansion& f) {
  Expansion out;
  for (const double term : f) out = add(std::move(out), scale(e, term));
  return out;
}

inline int sign(const Expansion& e) { return e.empty() ? 0 : (e.back() > 0.0 ? 1 : -1); }

// A double-double as an expansion (normalised: |lo| at most half an ulp of hi).
inline Expansion from(DoubleDouble x) {
  Expansion out;
  if (x.lo != 0.0) out.push_back(x.lo);
  if (x.hi != 0.0) out.push_back(x.hi);
  return out;
}

// det(a, b, c) = a . (b x c).
inline Expansion det3(const Expansion (&a)[3], const Expansion (&b)[3], const Expansion (&c)[3]) {
  const auto minor = [&](int i, int j) {  // b_i c_j - b_j c_i
    return add(multiply(b[i], c[j]), negate(multiply(b[j], c[i])));
  };
  return add(add(multiply(a[0], minor(1, 2)), multiply(a[1], minor(2, 0))), multiply(a[2], minor(0, 1)));
}

// One plane of a double-double cell as exact rows: `bisector` when its
// offset is (|normal|^2 + shift) / 2 (a bisector of the seed; a power
// bisector with shift = w_seed - w_j, exact in double-double as the
// difference of two doubles, else 0), else a box face whose offset is exact
// as stored.
struct Row {
  Expansion normal[3];
  Expansion offset;
  Row(const Plane<DoubleDouble>& p, bool bisector, DoubleDouble shift = DoubleDouble(0.0)) {
    normal[0] = from(p.normal.x);
    normal[1] = from(p.normal.y);
    normal[2] = from(p.normal.z);
    if (bisector) {
      offset = add(add(add(multiply(normal[0], normal[0]), multiply(normal[1], normal[1])),
                       multiply(normal[2], normal[2])),
                   from(shift));
      for (double& term : offset) term *= 0.5;  // exact but for underflow
    } else {
      offset = from(p.offset);
    }
  }
};

// A vertex's homogeneous coordinates, from its planes' rows a, b, c:
// det(M) = n_q . c + o_q d for any plane q (M's expansion along row q), so
// v = c / d. Computed once a vertex in double-double, with bounds on their
// errors (a small multiple of 2^-104 times `bound`: the permanents, the
// same sums of products of absolute values), so that each predicate costs a
// dot product.
struct HomogeneousVertex {
  DoubleDouble c[3], d;
  double c_bound[3], d_bound;
};

// det of the 3x3 matrix with columns u, v, w (one entry a row) and its permanent.
inline DoubleDouble det3_columns(const DoubleDouble (&u)[3], const DoubleDouble (&v)[3], const DoubleDouble (&w)[3],
                                 double& permanent) {
  const auto m = [](DoubleDouble x) { return std::fabs(x.hi); };
  permanent = m(u[0]) * (m(v[1]) * m(w[2]) + m(v[2]) * m(w[1])) + m(u[1]) * (m(v[2]) * m(w[0]) + m(v[0]) * m(w[2])) +
              m(u[2]) * (m(v[0]) * m(w[1]) + m(v[1]) * m(w[0]));
  return (u[0] * (v[1] * w[2] - v[2] * w[1]) + u[1] * (v[2] * w[0] - v[0] * w[2])) + u[2] * (v[0] * w[1] - v[1] * w[0]);
}

inline HomogeneousVertex homogeneous(const Plane<DoubleDouble>& a, const Plane<DoubleDouble>& b,
                                     const Plane<DoubleDouble>& c) {
  const DoubleDouble x[3] = {a.normal.x, b.normal.x, c.normal.x};
  const DoubleDouble y[3] = {a.normal.y, b.normal.y, c.normal.y};
  const DoubleDouble z[3] = {a.normal.z, b.normal.z, c.normal.z};
  const DoubleDouble o[3] = {a.offset, b.offset, c.offset};
  HomogeneousVertex h;
  // The cofactors of row q's entries (n_x, n_y, n_z, o): signs -, +, -, +.
  h.c[0] = -det3_columns(y, z, o, h.c_bound[0]);
  h.c[1] = det3_columns(x, z, o, h.c_bound[1]);
  h.c[2] = -det3_columns(x, y, o, h.c_bound[2]);
  h.d = det3_columns(x, y, z, h.d_bound);
  return h;
}

// The sign of f at vertex h for plane q, decided in double and then in
// double-double where the rounding error cannot flip it; 2 where it might.
// The rows' entries are within 2^-104 (relative) of the exact ones, as are
// h's within a few 2^-104 of their bounds; a double is within 2^-53 of its
// double-double; the sums of products below add a few units more. The
// factors 64 leave a wide margin. Near under- or overflow, undecided.
inline int filtered_side(const HomogeneousVertex& h, const Plane<DoubleDouble>& q) {
  const double n[3] = {q.normal.x.hi, q.normal.y.hi, q.normal.z.hi};
  const double bound = std::fabs(n[0]) * h.c_bound[0] + std::fabs(n[1]) * h.c_bound[1] +
                       std::fabs(n[2]) * h.c_bound[2] + std::fabs(q.offset.hi) * h.d_bound;
  if (!(h.d_bound > 1e-250 && bound > 1e-250 && bound < 1e250)) return 2;
  if (!(std::fabs(h.d.hi) > 64.0 * 0x1p-100 * h.d_bound)) return 2;
  const bool d_positive = h.d.hi > 0.0;
  const double det_double = n[0] * h.c[0].hi + n[1] * h.c[1].hi + n[2] * h.c[2].hi + q.offset.hi * h.d.hi;
  if (std::fabs(det_double) > 64.0 * 0x1p-53 * bound) return (det_double > 0.0) == d_positive ? 1 : -1;
  const DoubleDouble det = (q.normal.x * h.c[0] + q.normal.y * h.c[1]) + (q.normal.z * h.c[2] + q.offset * h.d);
  if (std::fabs(det.hi) > 64.0 * 0x1p-100 * bound) return (det.hi > 0.0) == d_positive ? 1 : -1;
  return 2;
}

// The exact sign of f = n_q . v + o_q at the vertex v where planes a, b, c
// meet (rows[0..2]; rows[3] is q): -1 outside q, 0 on it, +1 inside.
// bisector[i]: whether rows[i] is a bisector (Row), shift[i] its power
// shift (Row). 0 also where a, b, c do not meet in a point (no vertex to cut).
// (filtered_side first: this is its slow path.)
inline int exact_side(const Plane<DoubleDouble>* const (&rows)[4], const bool (&bisector)[4],
                      const DoubleDouble (&shift)[4]) {
  const Row a(*rows[0], bisector[0], shift[0]), b(*rows[1], bisector[1], shift[1]), c(*rows[2], bisector[2], shift[2]),
      q(*rows[3], bisector[3], shift[3]);
  const Expansion minor_a = det3(b.normal, c.normal, q.normal);
  const Expansion minor_b = det3(a.normal, c.normal, q.normal);
  const Expansion minor_c = det3(a.normal, b.normal, q.normal);
  const Expansion minor_q = det3(a.normal, b.normal, c.normal);
  const Expansion det4 = add(add(negate(multiply(a.offset, minor_a)), multiply(b.offset, minor_b)),
                             add(negate(multiply(c.offset, minor_c)), multiply(q.offset, minor_q)));
  return sign(det4) * sign(minor_q);
}

}  // namespace exact
}  // namespace core
}  // namespace torchvor
