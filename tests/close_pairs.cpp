// core::nearly_coincident_bisectors (csrc/core/cell_planes.h) against the
// geometry it stands for, in double: the bisectors of the seed (origin) and
// two float32 neighbours a, b meet along a line; the test must flag the pair
// where their sine is under 1e-3 and that line passes within twice the
// cell's radius R (a needle can hang there), and may flag it only where the
// sine is under 1e-3 and the line passes within 2.5 R; a few percent from
// those limits rounding decides. Pairs are drawn near the limits, with sines
// down to float's resolution, at scales from 1e-15 to 1e4. Exit status 0:
// every pair agreed, and enough were required.
// With "double": core::nearly_parallel_bisectors (csrc/core/cell_faces.h,
// voronoi_graph's float64 faces) the same way, on double neighbours, its
// sine limit 1e-7, against the geometry in long double.
// Built and run by tests/test_voronoi_tight_clusters.py:
//   close_pairs SEED PAIRS [float|double]
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <random>

#include "core/cell_faces.h"

namespace core = torchvor::core;

struct Geometry {
  double sine;      // of the angle between a and b
  double distance;  // from the origin to the line where the bisectors meet (inf: parallel)
};

static Geometry geometry(const double a[3], const double b[3]) {
  const double a2 = a[0] * a[0] + a[1] * a[1] + a[2] * a[2];
  const double b2 = b[0] * b[0] + b[1] * b[1] + b[2] * b[2];
  const double ab = a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
  const double c[3] = {a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]};
  const double c2 = c[0] * c[0] + c[1] * c[1] + c[2] * c[2];
  Geometry g{std::sqrt(c2 / (a2 * b2)), INFINITY};
  if (c2 == 0.0) return g;
  // The line's point nearest the origin is y = alpha a + beta b with
  // a . y = a2 / 2 and b . y = b2 / 2.
  const double det = a2 * b2 - ab * ab;
  const double alpha = (0.5 * a2 * b2 - 0.5 * b2 * ab) / det;
  const double beta = (0.5 * b2 * a2 - 0.5 * a2 * ab) / det;
  const double y2 = alpha * alpha * a2 + 2.0 * alpha * beta * ab + beta * beta * b2;
  g.distance = std::sqrt(std::fabs(y2));
  return g;
}

// Pairs of neighbours near a test's limits: a, a random direction at a
// length log-uniform in [length_lo, length_hi]; b, a turned by an angle
// log-uniform in [angle_lo, angle_hi] about a random axis, set so that the
// line where their bisectors meet lies near the cell's radius R (returned):
// bisectors at distances h and h + delta meet about delta / sin from the
// foot, delta = sin * (a multiple of R around 1), or exactly at the foot.
class PairSampler {
 public:
  explicit PairSampler(unsigned seed) : rng_(seed) {}

  double draw(double length_lo, double length_hi, double angle_lo, double angle_hi, double a[3], double b[3]) {
    double u[3] = {normal_(rng_), normal_(rng_), normal_(rng_)};
    const double un = std::sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2]);
    for (double& x : u) x /= un;
    double v[3] = {normal_(rng_), normal_(rng_), normal_(rng_)};
    const double uv = v[0] * u[0] + v[1] * u[1] + v[2] * u[2];
    for (int e = 0; e < 3; ++e) v[e] -= uv * u[e];
    const double vn = std::sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
    for (double& x : v) x /= vn;
    const double length = log_uniform(length_lo, length_hi);
    const double radius = length * log_uniform(0.5, 1.0) * (uniform() < 0.8 ? 1.0 : log_uniform(1.0, 50.0));
    const double angle = log_uniform(angle_lo, angle_hi);
    const double delta = std::sin(angle) * radius * log_uniform(0.05, 6.0) * (uniform() < 0.5 ? 1.0 : 0.0);
    const double b_length = length + 2.0 * delta;
    for (int e = 0; e < 3; ++e) {
      a[e] = length * u[e];
      b[e] = b_length * (std::cos(angle) * u[e] + std::sin(angle) * v[e]);
    }
    return radius;
  }

 private:
  double uniform() { return uniform_(rng_); }
  double log_uniform(double lo, double hi) { return lo * std::pow(hi / lo, uniform()); }
  std::mt19937_64 rng_;
  std::uniform_real_distribution<double> uniform_{0.0, 1.0};
  std::normal_distribution<double> normal_{0.0, 1.0};
};

// The same for two double neighbours, in long double: the cross product
// and the line's foot from b - a (no cancellation at sines near 1e-9).
static Geometry geometry_wide(const double a_in[3], const double b_in[3]) {
  using W = long double;
  const W a[3] = {a_in[0], a_in[1], a_in[2]};
  const W d[3] = {W(b_in[0]) - a[0], W(b_in[1]) - a[1], W(b_in[2]) - a[2]};
  const W b[3] = {b_in[0], b_in[1], b_in[2]};
  const W a2 = a[0] * a[0] + a[1] * a[1] + a[2] * a[2];
  const W b2 = b[0] * b[0] + b[1] * b[1] + b[2] * b[2];
  const W c[3] = {a[1] * d[2] - a[2] * d[1], a[2] * d[0] - a[0] * d[2], a[0] * d[1] - a[1] * d[0]};
  const W c2 = c[0] * c[0] + c[1] * c[1] + c[2] * c[2];
  Geometry g{double(std::sqrt(c2 / (a2 * b2))), INFINITY};
  if (c2 == 0) return g;
  // y = alpha a + beta b, a . y = a2 / 2, b . y = b2 / 2: with det = c2,
  // alpha = -b2 (a . d) / (2 c2), beta = a2 (b . d) / (2 c2).
  const W ad = a[0] * d[0] + a[1] * d[1] + a[2] * d[2], bd = b[0] * d[0] + b[1] * d[1] + b[2] * d[2];
  const W alpha = -b2 * ad / (2 * c2), beta = a2 * bd / (2 * c2);
  W y2 = 0;
  for (int e = 0; e < 3; ++e) y2 += (alpha * a[e] + beta * b[e]) * (alpha * a[e] + beta * b[e]);
  g.distance = double(std::sqrt(y2));
  return g;
}

static int run_double(unsigned seed, long pairs) {
  PairSampler sampler(seed);
  constexpr double kSine = torchvor::core::FaceSineLimit<double, double>::value;
  long missed = 0, spurious = 0, flagged = 0, required = 0;
  for (long p = 0; p < pairs; ++p) {
    double a[3], b[3];
    const double radius = sampler.draw(1e-100, 1e100, 1e-11, 4e-7, a, b);
    const double length = std::sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2]);
    const Geometry g = geometry_wide(a, b);
    const bool flag = core::nearly_parallel_bisectors(core::Vec3<double>{a[0], a[1], a[2]},
                                                      core::Vec3<double>{b[0], b[1], b[2]}, radius * radius, kSine);
    const bool must = g.sine < 0.97 * kSine && g.distance < 1.9 * radius;
    const bool may = g.sine < 1.03 * kSine && g.distance < 2.5 * radius;
    flagged += flag;
    required += must;
    if ((must && !flag && ++missed <= 10) || (flag && !may && ++spurious <= 10)) {
      std::printf("%s: |a| %.3g sine %.3g line at %.3g R (R %.3g)\n", flag ? "spurious" : "missed", length, g.sine,
                  g.distance / radius, radius);
    }
  }
  std::printf("%ld double pairs: %ld flagged, %ld required, %ld missed, %ld spurious\n", pairs, flagged, required,
              missed, spurious);
  return missed == 0 && spurious == 0 && required > pairs / 20 ? 0 : 1;
}

int main(int argc, char** argv) {
  const unsigned seed = argc > 1 ? unsigned(std::atoi(argv[1])) : 0u;
  const long pairs = argc > 2 ? std::atol(argv[2]) : 200000;
  if (argc > 3 && std::strcmp(argv[3], "double") == 0) return run_double(seed, pairs);
  PairSampler sampler(seed);
  long missed = 0, spurious = 0, flagged = 0, required = 0;
  for (long p = 0; p < pairs; ++p) {
    double ad[3], bd[3];
    const double radius = sampler.draw(1e-15, 1e4, 1e-7, 4e-3, ad, bd);
    const float af[3] = {float(ad[0]), float(ad[1]), float(ad[2])};
    const float bf[3] = {float(bd[0]), float(bd[1]), float(bd[2])};
    double a[3] = {af[0], af[1], af[2]}, b[3] = {bf[0], bf[1], bf[2]};
    const double a2 = a[0] * a[0] + a[1] * a[1] + a[2] * a[2];
    const double b2 = b[0] * b[0] + b[1] * b[1] + b[2] * b[2];
    if (!(a2 <= b2)) continue;  // the list's order: a no farther than b
    const Geometry g = geometry(a, b);
    const float r2 = float(radius * radius);
    const float bf2 = bf[0] * bf[0] + bf[1] * bf[1] + bf[2] * bf[2];
    const bool flag = core::nearly_coincident_bisectors(core::Vec3<float>{af[0], af[1], af[2]},
                                                        core::Vec3<float>{bf[0], bf[1], bf[2]}, bf2, r2);
    const bool must = g.sine < 0.97e-3 && g.distance < 1.9 * radius;
    const bool may = g.sine < 1.03e-3 && g.distance < 2.5 * radius;
    flagged += flag;
    required += must;
    if (must && !flag) {
      if (++missed <= 10) {
        std::printf("missed: |a| %.3g sine %.3g line at %.3g R (R %.3g)\n", std::sqrt(a2), g.sine,
                    g.distance / radius, radius);
      }
    }
    if (flag && !may) {
      if (++spurious <= 10) {
        std::printf("spurious: |a| %.3g sine %.3g line at %.3g R (R %.3g)\n", std::sqrt(a2), g.sine,
                    g.distance / radius, radius);
      }
    }
  }
  std::printf("%ld pairs: %ld flagged, %ld required, %ld missed, %ld spurious\n", pairs, flagged, required, missed,
              spurious);
  return missed == 0 && spurious == 0 && required > pairs / 20 ? 0 : 1;
}
