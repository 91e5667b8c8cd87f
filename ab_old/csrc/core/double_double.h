// Double-double arithmetic (an unevaluated sum hi + lo of two doubles, about
// 106 bits of mantissa) for the last-resort recovery pass: cells whose
// predicates stay inconsistent in float64 (e.g. bisectors of a tight cluster
// seen from afar, meeting at angles near 1e-6) are recomputed with it.
// Built from the classic error-free transformations (Knuth's two-sum, Dekker's
// product); only what ConvexCell needs.
#pragma once

#include <cmath>

#include "common.h"

namespace torchvor {
namespace core {

struct DoubleDouble {
  double hi, lo;

  DoubleDouble() = default;
  TV_HD constexpr DoubleDouble(double x) : hi(x), lo(0.0) {}
  TV_HD constexpr DoubleDouble(double h, double l) : hi(h), lo(l) {}
  TV_HD explicit operator double() const { return hi + lo; }
  TV_HD explicit operator float() const { return static_cast<float>(hi + lo); }
};

namespace dd_detail {

TV_HD DoubleDouble two_sum(double a, double b) {
  const double s = a + b;
  const double v = s - a;
  return {s, (a - (s - v)) + (b - v)};
}

TV_HD DoubleDouble quick_two_sum(double a, double b) {  // |a| >= |b|
  const double s = a + b;
  return {s, b - (s - a)};
}

TV_HD DoubleDouble two_prod(double a, double b) {
  const double p = a * b;
#if defined(__CUDA_ARCH__)
  return {p, fma(a, b, -p)};
#else
  // Dekker's split: exact without a hardware FMA.
  const double split = 134217729.0;  // 2^27 + 1
  const double ta = split * a, tb = split * b;
  const double a_hi = ta - (ta - a), a_lo = a - a_hi;
  const double b_hi = tb - (tb - b), b_lo = b - b_hi;
  return {p, ((a_hi * b_hi - p) + a_hi * b_lo + a_lo * b_hi) + a_lo * b_lo};
#endif
}

}  // namespace dd_detail

TV_HD DoubleDouble operator-(DoubleDouble a) { return {-a.hi, -a.lo}; }

TV_HD DoubleDouble operator+(DoubleDouble a, DoubleDouble b) {
  DoubleDouble s = dd_detail::two_sum(a.hi, b.hi);
  const DoubleDouble t = dd_detail::two_sum(a.lo, b.lo);
  s.lo += t.hi;
  s = dd_detail::quick_two_sum(s.hi, s.lo);
  s.lo += t.lo;
  return dd_detail::quick_two_sum(s.hi, s.lo);
}

TV_HD DoubleDouble operator-(DoubleDouble a, DoubleDouble b) { return a + (-b); }

TV_HD DoubleDouble operator*(DoubleDouble a, DoubleDouble b) {
  DoubleDouble p = dd_detail::two_prod(a.hi, b.hi);
  p.lo += a.hi * b.lo + a.lo * b.hi;
  return dd_detail::quick_two_sum(p.hi, p.lo);
}

TV_HD DoubleDouble operator/(DoubleDouble a, DoubleDouble b) {
  const double q1 = a.hi / b.hi;
  const DoubleDouble r1 = a - DoubleDouble(q1) * b;
  const double q2 = r1.hi / b.hi;
  const DoubleDouble r2 = r1 - DoubleDouble(q2) * b;
  const double q3 = r2.hi / b.hi;
  return dd_detail::quick_two_sum(q1, q2) + DoubleDouble(q3);
}

TV_HD DoubleDouble& operator+=(DoubleDouble& a, DoubleDouble b) { return a = a + b; }

TV_HD bool operator<(DoubleDouble a, DoubleDouble b) {
  return a.hi < b.hi || (a.hi == b.hi && a.lo < b.lo);
}
TV_HD bool operator>(DoubleDouble a, DoubleDouble b) { return b < a; }
TV_HD bool operator==(DoubleDouble a, DoubleDouble b) { return a.hi == b.hi && a.lo == b.lo; }

// Finite test used by the cell code for every scalar type.
TV_HD bool is_finite_value(float x) { return x - x == 0.0f; }
TV_HD bool is_finite_value(double x) { return x - x == 0.0; }
TV_HD bool is_finite_value(DoubleDouble x) { return x.hi - x.hi == 0.0 && x.lo - x.lo == 0.0; }

}  // namespace core
}  // namespace torchvor
