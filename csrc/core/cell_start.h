// The first cell of a clip: a tetrahedron of four bisectors, or the box
// (convex_cell.h's init_tetrahedron and init_box start from these).
#pragma once

#include <cstdint>

#include "cell_planes.h"
#include "common.h"
#include "double_double.h"

namespace torchvor {
namespace core {

// ---- The first cell: a tetrahedron of four bisectors, or the box ----------
//
// Starting from the box, the first neighbours carve away its 8 corners and
// 6 faces: on blue noise the first five clips removed 4-5 triangles each
// (the warp's largest region 6-9) where later clips remove 2, and the
// reverse-edge search costs the warp's largest region squared. Four
// bisectors whose neighbours surround the seed bound a tetrahedron that
// already holds the cell: 4 vertices, every face a bisector, nothing to
// carve: the clips then remove smaller regions, and fewer of them cut.
//
// The four: the nearest neighbour and the triple of the next six whose
// tetrahedron surrounds the seed best. With unit directions u_i, the
// determinants mu_i of the other three satisfy sum mu_i u_i = 0 (Cramer), so
// the directions surround the origin (the tetrahedron is bounded) iff all
// mu_i have one sign; the smallest |mu_i| measures by how much (0: the four
// are flat, or the origin is on a face). Triples below kStartMinSurround, and
// tetrahedra not strictly inside the box (whose faces would then cut the
// cell), start from the box. The choice is computed with separately rounded
// products (det_rn), so that the CPU and the GPU take the same.
//
// Only the thread cell starts so (ConvexCell::kTetrahedronStart): the warp
// cell (CooperativeCell) clips at a cost per clip that hardly depends on the
// removed region, and the start's own cost made it slower
// (docs/performance.md).
constexpr int kStartCandidates = 7;   // the nearest neighbour and the next six
constexpr double kStartMinSurround = 0.05;

// The scalar the choice is computed in (double-double chooses in double).
template <typename T> struct ChoiceScalar { using type = T; };
template <> struct ChoiceScalar<DoubleDouble> { using type = double; };

// The four neighbours chosen (start_choice): 0, b, c, d.
struct StartChoice {
  bool found;
  bool positive;  // the sign of the mu_i
  int b, c, d;
  TV_HD uint32_t used() const { return found ? (1u | 1u << b | 1u << c | 1u << d) : 0u; }
};

template <typename T>
struct StartTetrahedron {
  bool found;
  Vec3<T> offset[4];    // neighbours 0, b, c, d relative to the seed
  Vec3<T> vertex[4];    // where the planes of corners[t] meet
  uint32_t corners[4];  // the oriented triangles, indices into offset packed a | b << 8 | c << 16
};

// det(a, b, c) = a . (b x c), each product rounded on its own.
template <typename S>
TV_HD S det_rn(Vec3<S> a, Vec3<S> b, Vec3<S> c) {
  return (mul_rn(a.x, mul_rn(b.y, c.z) - mul_rn(b.z, c.y)) + mul_rn(a.y, mul_rn(b.z, c.x) - mul_rn(b.x, c.z))) +
         mul_rn(a.z, mul_rn(b.x, c.y) - mul_rn(b.y, c.x));
}

// unit[i] for a run-time i, by selects (no dynamically indexed array: on
// the GPU it would go to local memory).
template <typename V>
TV_HD V pick(const V (&unit)[kStartCandidates], int i) {
  V out = unit[0];
  TV_UNROLL
  for (int j = 1; j < kStartCandidates; ++j) out = i == j ? unit[j] : out;
  return out;
}

// How well directions 0, b, c, d surround the seed: min |mu_i| if all mu_i
// have one sign (see above), else -1; `positive`: their sign.
template <typename S>
TV_HD S surround(Vec3<S> u0, Vec3<S> ub, Vec3<S> uc, Vec3<S> ud, bool& positive) {
  const S mu[4] = {det_rn(ub, uc, ud), -det_rn(u0, uc, ud), det_rn(u0, ub, ud), -det_rn(u0, ub, uc)};
  positive = mu[0] > S(0);
  S smallest = positive ? mu[0] : -mu[0];
  bool one_sign = mu[0] != S(0);
  TV_UNROLL
  for (int i = 1; i < 4; ++i) {
    one_sign = one_sign && (mu[i] > S(0)) == positive && mu[i] != S(0);
    smallest = min_of(smallest, mu[i] > S(0) ? mu[i] : -mu[i]);
  }
  return one_sign ? smallest : S(-1);
}

// Which three of neighbours 1..6 (unit directions from the seed, none of
// length 0) surround the seed best with neighbour 0: the first best triple
// in lexicographic order, if any reaches kStartMinSurround. The loop over b
// is not unrolled: unrolled, the twenty triples took 184 registers a thread
// (71 so), which would halve the clip kernel's resident blocks.
template <typename S>
TV_HD StartChoice start_choice(const Vec3<S> (&unit)[kStartCandidates]) {
  StartChoice choice;
  choice.found = false;
  choice.positive = false;
  choice.b = 1, choice.c = 2, choice.d = 3;
  S best = S(kStartMinSurround);
  TV_NO_UNROLL
  for (int b = 1; b <= 4; ++b) {
    const Vec3<S> ub = pick(unit, b);
    TV_UNROLL
    for (int c = 2; c <= 5; ++c) {
      TV_UNROLL
      for (int d = c + 1; d <= 6; ++d) {
        if (c <= b) continue;  // the same b in every thread: no divergence
        bool positive;
        const S quality = surround(unit[0], ub, unit[c], unit[d], positive);
        if (quality > best) {
          best = quality;
          choice = {true, positive, b, c, d};
        }
      }
    }
  }
  return choice;
}

// The tetrahedron of the bisectors of neighbours 0, b, c, d (`offset`,
// relative to the seed) of `choice`; `found` false where a vertex is not
// strictly inside the box [lo, hi] (relative to the seed): start from the box.
template <typename T>
TV_HD StartTetrahedron<T> start_tetrahedron(const Vec3<T> (&offset)[4], bool positive, Vec3<T> lo, Vec3<T> hi) {
  StartTetrahedron<T> start;
  Plane<T> planes[4];
  TV_UNROLL
  for (int i = 0; i < 4; ++i) {
    start.offset[i] = offset[i];
    planes[i] = bisector_plane(offset[i], squared_norm(offset[i]));
  }
  // Vertex t is opposite offset 3 - t. With all mu_i > 0, det(r0, r1, r2) < 0,
  // det(r0, r1, r3) > 0, det(r0, r2, r3) < 0, det(r1, r2, r3) > 0; a triangle
  // (a, b, c) is oriented as the box's when det(r_a, r_b, r_c) > 0 (the
  // normals are -r), so the orders below, a and b swapped when the mu_i are
  // negative.
  const uint32_t oriented[4] = {0x020001u, 0x030100u, 0x030002u, 0x030201u};
  bool inside = true;
  TV_UNROLL
  for (int t = 0; t < 4; ++t) {
    // Compile-time indices into `planes` once unrolled; the swap by selects.
    const uint32_t corners = oriented[t];
    const Plane<T>& pa = planes[corners & 0xffu];
    const Plane<T>& pb = planes[corners >> 8 & 0xffu];
    start.corners[t] = positive ? corners : (corners >> 8 & 0xffu) | (corners & 0xffu) << 8 | (corners & 0xff0000u);
    const Vec3<T> v = intersect_planes(positive ? pa : pb, positive ? pb : pa, planes[corners >> 16]);
    start.vertex[t] = v;
    inside = inside && lo.x < v.x && v.x < hi.x && lo.y < v.y && v.y < hi.y && lo.z < v.z && v.z < hi.z;
  }
  start.found = inside;
  return start;
}

}  // namespace core
}  // namespace torchvor
