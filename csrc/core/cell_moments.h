// The integrals of a cell over its dual triangles (paper §3.5): volume,
// first and second moments, and what bounds their rounding.
#pragma once

#include <type_traits>

#include "common.h"
#include "double_double.h"
#include "host_packs.h"

namespace torchvor {
namespace core {

// A vertex position and its squared distance to the seed, 16-byte aligned
// (one vector load on the GPU for float).
template <typename T>
struct alignas(16) CachedVertex {
  Vec3<T> position;
  T radius2;
};

// What bounds the rounding error of a cell's integrals (CellMoments).
template <typename T>
struct CellRounding {
  T unsigned_volume;     // the tetrahedra's absolute volumes: the cancellation
  T conditioned_volume;  // float, double: the same weighted by how far rounding moves them (add_vertex)
  T unsigned_second_moment;  // the tetrahedra's absolute second moments: the second moment's cancellation
};

// Volume, first moment and second moment (integral of |x|^2) of a cell,
// relative to the seed, summed over six signed tetrahedra per vertex (§3.5):
// seed, foot of the seed on a plane, foot on an edge line, the vertex.
// `unsigned_six_volume` sums the tetrahedra's absolute volumes: its ratio to
// the volume measures the cancellation, hence the rounding error. The feet
// of a face far from the seed can lie far outside it (a needle cell reaching
// a box face): large tetrahedra then cancel (ratio 3e6 on a 1e-11 needle,
// against at most ~7 on white noise).
// kGeneralPlanes: the cell's planes are any (power_plane), not only
// bisectors and box faces; the feet and the weights then take a division.
template <typename T, bool kGeneralPlanes = false>
struct CellMoments {
  T six_volume;              // 6 * volume
  T unsigned_six_volume;     // 6 * sum of |tetrahedron volume|
  T conditioned_six_volume;  // float, double: the same, weighted by how far rounding moves them (add_vertex)
  Vec3<T> m1;                // 24 * first moment
  T m2;                      // 120 * second moment
  T unsigned_m2;             // 120 * sum of |tetrahedron second moment|: m2's cancellation, which
                             // far feet (weighted by their |x|^2) make worse than the volume's

  // Whether the cell weighs its tetrahedra by their vertices' rounding
  // (float and double; not double-double, the last resort).
  static constexpr bool kConditioned =
      std::is_same<T, float>::value || std::is_same<T, double>::value || IsPack<T>::value;
  // The rounding weights' type (add_vertex): float for a scalar cell, the
  // pack's own lanes for a pack of vertices.
  using Weight = typename std::conditional<IsPack<T>::value, T, float>::type;

  TV_HD static CellMoments zero() { return {T(0), T(0), T(0), {T(0), T(0), T(0)}, T(0), T(0)}; }

  // The six tetrahedra of vertex v, where planes a, b, c (in the triangle's
  // orientation) meet. Each foot is used by two tetrahedra: its |x|^2, and
  // the edge foot's cross product with v (the determinant of f, e, v is
  // f . (e x v)), are computed once for both.
  // In float and double, each tetrahedron also counts into conditioned_six_volume times
  // (1 / sine) |v| / h: the vertex is off by about eps |v| / sine (sine: the
  // |det| of its planes' unit normals), which moves the boundary of the
  // tetrahedron's face (at distance h from the seed) by as much, and the
  // volume by the face's share, the tetrahedron's volume over h. It is what
  // makes a needle cell, hundreds of times longer than wide, ill-conditioned.
  TV_HD void add_vertex(const Plane<T> (&planes)[3], const CachedVertex<T>& vertex) {
    add_vertex(planes, vertex, vertex.radius2);
  }
  // The same where rounding moves the vertex by eps times sqrt(rounding2)
  // rather than |v| (a power cell: its vertices are computed about the seed,
  // not about the origin of these integrals).
  TV_HD void add_vertex(const Plane<T> (&planes)[3], const CachedVertex<T>& vertex, T rounding2) {
    const Vec3<T> v = vertex.position;
    Vec3<T> feet[3];
    T feet2[3];
    TV_UNROLL
    for (int e = 0; e < 3; ++e) {
      feet[e] = plane_foot(planes[e]);
      feet2[e] = dot(feet[e], feet[e]);
    }
    // The weights before the tetrahedra (three values to keep across them,
    // not the normals), from one reciprocal root a face and one a vertex: a
    // face's 1 / h is 2 / |n| for a bisector (offset |n|^2 / 2), and |n| is 1
    // for a box face. A face through the seed (h = 0, a box face) has no
    // volume to move; a vertex at the seed, no rounding to move it.
    // The weights are ratios of lengths (|v| / (sine h) >= 1), kept in float:
    // in double they are three more register pairs across the tetrahedra.
    Weight weight[3] = {Weight(0), Weight(0), Weight(0)};
    if constexpr (kConditioned) {
      T inverse_h[3], inverse_norms = T(1);
      TV_UNROLL
      for (int e = 0; e < 3; ++e) {
        inverse_h[e] = select(feet2[e] > T(0), rsqrt_of(feet2[e]), T(0));
        if constexpr (kGeneralPlanes) {
          inverse_norms *= rsqrt_of(dot(planes[e].normal, planes[e].normal));
        } else {
          inverse_norms *= select(dot(planes[e].normal, planes[e].normal) == T(1), T(1), T(0.5) * inverse_h[e]);
        }
      }
      const T det = dot(cross(planes[0].normal, planes[1].normal), planes[2].normal);
      const T sine = select(det < T(0), -det, det) * inverse_norms;
      // |v| / sine; Inf or NaN where the planes are degenerate
      const T length = select(rounding2 > T(0), rounding2 * rsqrt_of(rounding2 * sine * sine), T(0));
      TV_UNROLL
      for (int e = 0; e < 3; ++e) weight[e] = static_cast<Weight>(length * inverse_h[e]);
    }
    TV_UNROLL
    for (int e = 0; e < 3; ++e) {
      const int f = (e + 1) % 3;
      const Vec3<T> edge_foot = line_foot(planes[e], planes[f], v);
      const Vec3<T> edge_cross_v = cross(edge_foot, v);
      const Vec3<T> edge_plus_v = edge_foot + v;
      const T edge_v2 = dot(edge_foot, edge_foot) + vertex.radius2;
      const T on_e = add_tetrahedron(feet[e], feet2[e], edge_cross_v, edge_plus_v, edge_v2, T(1));
      const T on_f = add_tetrahedron(feet[f], feet2[f], edge_cross_v, edge_plus_v, edge_v2, T(-1));
      if constexpr (kConditioned) conditioned_six_volume += on_e * T(weight[e]) + on_f * T(weight[f]);
    }
  }

  TV_HD void finish(T& volume, Vec3<T>& first_moment, T& second_moment, CellRounding<T>& rounding) const {
    volume = six_volume / T(6);
    rounding.unsigned_volume = unsigned_six_volume / T(6);
    rounding.conditioned_volume = conditioned_six_volume / T(6);
    rounding.unsigned_second_moment = unsigned_m2 / T(120);
    first_moment = (T(1) / T(24)) * m1;
    second_moment = m2 / T(120);
  }

  // Orthogonal projection of the seed (origin) onto a plane, for the two
  // kinds of plane a cell has, without a division: a bisector
  // (bisector_plane: offset |normal|^2 / 2, so the foot is -normal / 2) or a
  // box face (box_plane: a unit normal, so the foot is -offset * normal).
  // A bisector with |normal| = 1 has offset 1/2: either formula holds. (No
  // branch to a division for planes of neither kind: it slows the warp cell.)
  TV_HD static Vec3<T> plane_foot(const Plane<T>& p) {
    if constexpr (kGeneralPlanes) return (-p.offset / dot(p.normal, p.normal)) * p.normal;
    return select(dot(p.normal, p.normal) == T(1), -p.offset, T(-0.5)) * p.normal;
  }

  // Orthogonal projection of the seed onto the line where planes a, b meet,
  // from a point v on it (the vertex): v minus its component along the line.
  // The edge's two vertices compute it apart, equal up to rounding: the
  // tetrahedra then cancel up to rounding, as they do anyway.
  TV_HD static Vec3<T> line_foot(const Plane<T>& pa, const Plane<T>& pb, Vec3<T> v) {
    const Vec3<T> direction = cross(pa.normal, pb.normal);
    return v - (dot(v, direction) / dot(direction, direction)) * direction;
  }

  // Signed tetrahedron (seed, f, e, v), given |f|^2, e x v, e + v and
  // |e|^2 + |v|^2. Integral of |x|^2 over a tetrahedron with a vertex at the
  // origin: vol / 20 * (sum |p_i|^2 + |sum p_i|^2).
  // Adds one tetrahedron; returns its absolute six volume.
  TV_HD T add_tetrahedron(Vec3<T> f, T f2, Vec3<T> edge_cross_v, Vec3<T> edge_plus_v, T edge_v2, T sign) {
    const T six_vol = sign * dot(f, edge_cross_v);
    const Vec3<T> sum = f + edge_plus_v;
    const T absolute = select(six_vol < T(0), -six_vol, six_vol);
    six_volume += six_vol;
    unsigned_six_volume += absolute;
    m1 = m1 + six_vol * sum;
    const T sum_of_squares = f2 + edge_v2 + dot(sum, sum);
    m2 += six_vol * sum_of_squares;
    unsigned_m2 += absolute * sum_of_squares;
    return absolute;
  }
};

}  // namespace core
}  // namespace torchvor
