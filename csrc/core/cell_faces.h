// The faces of a computed cell: each plane's area and centroid, from the
// cell's vertices alone (no walk around the face), for voronoi_graph.
//
// A vertex v where planes a, b, c meet (a triangle) gives each of its three
// planes two signed triangles, as CellMoments' tetrahedra without the seed:
// for plane e, (apex, a point of the edge line of e and the next plane, v)
// counted +1 and (apex, a point of the edge line of the previous plane and
// e, v) counted -1, the apex a vertex of the face. Over all the vertices on
// a plane they sum to its face, whatever the face's shape.
#pragma once

#include <cstdint>

#include "convex_cell.h"
#include "double_double.h"

namespace torchvor {
namespace core {

// A face whose area is below this fraction of the squared distance of its
// farthest vertex from the seed is rounding noise on a face that exact
// arithmetic makes an edge or a vertex (four or more cospherical points),
// not a face.
template <typename T> struct FaceAreaFloor;
template <> struct FaceAreaFloor<float> { static constexpr double value = 1e-10; };
template <> struct FaceAreaFloor<double> { static constexpr double value = 1e-20; };
template <> struct FaceAreaFloor<DoubleDouble> { static constexpr double value = 1e-30; };

template <typename T>
struct Face {
  T area;
  Vec3<T> centroid;  // relative to the seed
  // With kMoments (face_of_plane): about the centroid (u = y - centroid),
  // the integrals over the face of u u^T (xx, yy, zz, xy, xz, yz) and of
  // |u|^2 u: the gradients' terms (GRADIENTS.md).
  T second[6];
  Vec3<T> third;
};

// What a face's plane is to the caller (for_each_face's target_of): a
// neighbour's id (>= 0), a wall (wall_target), or no face (kNoFace: the
// plane was not recognised).
constexpr int32_t kNoFace = INT32_MIN;
TV_HD constexpr int32_t wall_target(int wall) { return -1 - wall; }
TV_HD constexpr int wall_of_target(int32_t target) { return -1 - target; }

// The box wall (0-5: -x, +x, -y, +y, -z, +z, as box_plane) that plane `p`
// is, or -1 for a bisector. Bit for bit: the cells build their box planes
// with box_plane, and no bisector of points inside the box is a wall.
template <typename T>
TV_HD int wall_of(const Plane<T>& p, Vec3<T> lo, Vec3<T> hi) {
  for (int q = 0; q < kBoxPlanes; ++q) {
    const Plane<T> wall = box_plane(q, lo, hi);
    if (p.normal.x == wall.normal.x && p.normal.y == wall.normal.y && p.normal.z == wall.normal.z &&
        p.offset == wall.offset) {
      return q;
    }
  }
  return -1;
}

TV_HD float inverse_length(float length2) { return rsqrt_of(length2); }
TV_HD double inverse_length(double length2) { return rsqrt_of(length2); }
TV_HD DoubleDouble inverse_length(DoubleDouble length2) {
  return DoubleDouble(rsqrt_of(static_cast<double>(length2)));
}

// The smallest sine of a vertex's planes (|det| of their unit normals) at
// which a cell computed in T for outputs of io_t has faces the arithmetic
// resolves. Below it the vertex is off by about eps |v| / sine along the
// line where two of its planes nearly meet: the volume barely moves, but
// the face between those two planes is split wrongly (the cell of a point
// beside two copies of another a few ulps apart: each copy's face takes a
// share only exact arithmetic tells). Such cells go to wider arithmetic in
// voronoi_graph's passes. 0: no limit (double-double, the last resort).
// (voronoi_graph computes float32 points as float64.)
template <typename io_t, typename T> struct FaceSineLimit { static constexpr double value = 0.0; };
template <> struct FaceSineLimit<double, double> { static constexpr double value = 1e-7; };

// Whether every vertex of `cell` meets FaceSineLimit (NaN sines do not).
template <typename io_t, typename Cell, typename T = typename Cell::Scalar>
TV_HD bool faces_resolved(const Cell& cell) {
  constexpr double limit = FaceSineLimit<io_t, T>::value;
  if constexpr (limit > 0.0) {
    const int vertices = cell.vertex_count();
    for (int t = 0; t < vertices; ++t) {
      int ids[3];
      if (!cell.vertex_planes(t, ids)) continue;
      const Vec3<T> a = cell.plane(ids[0]).normal, b = cell.plane(ids[1]).normal, c = cell.plane(ids[2]).normal;
      const T det = dot(cross(a, b), c);
      const T lengths2 = dot(a, a) * dot(b, b) * dot(c, c);
      if (lengths2 > T(1e-280) && lengths2 < T(1e280)) {  // sine^2 = det^2 / lengths2, no roots
        if (!(det * det >= T(limit * limit) * lengths2)) return false;
      } else {  // normals too short or long to square thrice (NaN too)
        const T sine = (det < T(0) ? -det : det) * rsqrt_of(dot(a, a)) * rsqrt_of(dot(b, b)) * rsqrt_of(dot(c, c));
        if (!(sine >= T(limit))) return false;
      }
    }
  }
  return true;
}

// Two neighbours j and q closer to each other than this fraction of q's
// distance from the seed have nearly coincident bisectors. Where they cross
// the cell, j's face is a sliver of width about tolerance |r|^2 / |r_j - r_q|
// which a clip in T keeps within its tolerance band (core::ClipTolerance):
// the plane is dropped and q takes both faces. The volume is right; the
// faces are not. A cell whose face neighbour q has such a j that is no face
// but comes within FaceBandMargin bands of a vertex, or whose bisector
// meets q's nearly parallel within the cell's reach (face or not:
// nearly_parallel_bisectors with FaceSineLimit), goes to wider arithmetic
// in voronoi_graph's passes. 0: no check (double-double).
template <typename io_t, typename T> struct FaceSeparationLimit { static constexpr double value = 0.0; };
template <> struct FaceSeparationLimit<double, double> { static constexpr double value = 1e-3; };
constexpr double FaceBandMargin = 16.0;

// Whether the bisectors of neighbours a and b (relative to the seed) meet at
// a sine under `sine` along a line within twice the cell's radius
// (radius2 = R^2) of the seed. Where such a line crosses the cell, the
// faces of a and b split there, and a vertex on it is off by about
// eps |v| / sine: rounding can also make the two faces meet at a sliver of
// a third plane, so no vertex names both (faces_resolved sees no small
// sine). The crossing within 2 R needs (|b| - |a|) / 2 <= 2 R s, i.e.
// (|b|^2 - |a|^2)^2 |a|^2 <= 64 s^2 R^2 |a|^2 |b|^2 (|a| + |b| <= 2 |b|);
// lengths in units of |a| (no underflow for tiny cells).
template <typename T>
TV_HD bool nearly_parallel_bisectors(Vec3<T> a, Vec3<T> b, T radius2, T sine) {
  const T a2 = dot(a, a);
  if (!(a2 > T(0))) return false;
  const T unit = rsqrt_of(a2);
  const Vec3<T> ua = unit * a, apart = unit * (b - a);  // b - a: no cancellation in the cross product
  const Vec3<T> c = cross(ua, apart);
  const T c2 = dot(c, c);  // s^2 |b|^2 / |a|^2
  const Vec3<T> ub = ua + apart;
  const T b2 = dot(ub, ub);
  if (!(c2 > T(0) && c2 < sine * sine * b2)) return false;  // exactly parallel planes never cross
  const T gap = dot(apart, ua + ub);                         // (|b|^2 - |a|^2) / |a|^2
  return gap * gap <= T(64) * c2 * (radius2 * unit * unit);
}

// A signed triangle (the apex at the origin, p and q) of weight s (twice
// its area, times |normal|, signed): s (p p^T + q q^T + (p + q)(p + q)^T)
// into `second` (xx, yy, zz, xy, xz, yz; 12 x the integral of y y^T over
// 2 A) and s (3|p|^2 p + 3|q|^2 q + |p|^2 q + |q|^2 p + 2 (p.q)(p + q))
// into `third` (30 x the integral of |y|^2 y over 2 A).
template <typename T>
TV_HD void add_triangle_moments(T s, Vec3<T> p, Vec3<T> q, T (&second)[6], Vec3<T>& third) {
  const Vec3<T> sum = p + q;
  second[0] += s * (p.x * p.x + q.x * q.x + sum.x * sum.x);
  second[1] += s * (p.y * p.y + q.y * q.y + sum.y * sum.y);
  second[2] += s * (p.z * p.z + q.z * q.z + sum.z * sum.z);
  second[3] += s * (p.x * p.y + q.x * q.y + sum.x * sum.y);
  second[4] += s * (p.x * p.z + q.x * q.z + sum.x * sum.z);
  second[5] += s * (p.y * p.z + q.y * q.z + sum.y * sum.z);
  const T pp = dot(p, p), qq = dot(q, q), pq = dot(p, q);
  third = third + s * ((T(3) * pp + qq + T(2) * pq) * p + (T(3) * qq + pp + T(2) * pq) * q);
}

// Each plane's vertices of a cell with at most kVertices vertices (and
// fewer than 256 planes), as lists in ascending vertex order: link 3 t + e
// names vertex t, its plane e; for_each_face then visits each face's
// vertices alone rather than every vertex for every plane.
template <int kPlanes, int kVertices>
struct VerticesByPlane {
  static constexpr uint16_t kEnd = 0xffff;
  static_assert(3 * kVertices < kEnd, "links are 16 bits");
  uint16_t first[kPlanes];
  uint16_t next[3 * kVertices];

  template <typename Cell>
  TV_HD explicit VerticesByPlane(const Cell& cell) {
    const int planes = cell.plane_count();
    for (int q = 0; q < planes; ++q) first[q] = kEnd;
    for (int t = cell.vertex_count() - 1; t >= 0; --t) {  // pushed in front: ascending
      int ids[3];
      if (!cell.vertex_planes(t, ids)) continue;
      for (int e = 0; e < 3; ++e) {
        next[3 * t + e] = first[ids[e]];
        first[ids[e]] = static_cast<uint16_t>(3 * t + e);
      }
    }
  }
  // visit(t, e) for each vertex t on plane q, in ascending order.
  template <typename Visit>
  TV_HD void on_plane(int q, Visit&& visit) const {
    for (uint16_t link = first[q]; link != kEnd; link = next[link]) visit(link / 3, link % 3);
  }
};

// A cell's vertices on plane q by a scan of them all (any cell).
struct ScanVertices {
  template <typename Cell, typename Visit>
  TV_HD static void on_plane(const Cell& cell, int q, Visit&& visit) {
    const int vertices = cell.vertex_count();
    for (int t = 0; t < vertices; ++t) {
      int ids[3];
      if (!cell.vertex_planes(t, ids)) continue;
      const int e = ids[0] == q ? 0 : (ids[1] == q ? 1 : (ids[2] == q ? 2 : -1));
      if (e >= 0) visit(t, e);
    }
  }
};

// The face of plane q of `cell`, if some vertex lies on it and its area is
// above the floor (FaceAreaFloor). `Cell` gives plane_count(), plane(q),
// vertex_count(), vertex(t) and vertex_planes(t, ids) (false: a free slot);
// on_plane(q, visit) calls visit(t, e) for the vertices t on plane q (its
// e-th plane), in ascending order.
template <bool kMoments, typename Cell, typename OnPlane, typename T = typename Cell::Scalar>
TV_HD bool face_of_plane(const Cell& cell, int q, OnPlane&& on_plane, Face<T>& face) {
  Plane<T> p;       // loaded at the face's first vertex: a plane no vertex names may be unwritten
  Vec3<T> apex;     // the face's first vertex: the triangles' common corner
  Vec3<T> outward;  // planes keep the seed's side
  T twice_area = T(0);  // along `outward`: |normal| times twice the area
  Vec3<T> moment = {T(0), T(0), T(0)};  // the same times 3 x the triangles' centroids, relative to the apex
  T reach2 = T(0);      // the largest |v|^2 on the face
  // kMoments: the triangles' sums of add_triangle_moments (the integrals of
  // y y^T and |y|^2 y relative to the apex, up to their scales)
  T second[6] = {T(0), T(0), T(0), T(0), T(0), T(0)};
  Vec3<T> third = {T(0), T(0), T(0)};
  bool on_face = false;
  on_plane(q, [&](int t, int e) {
    int ids[3];
    cell.vertex_planes(t, ids);
    const Vec3<T> v = cell.vertex(t);
    if (!on_face) {
      p = cell.plane(q);
      apex = v;
      outward = {-p.normal.x, -p.normal.y, -p.normal.z};
      on_face = true;
    }
    reach2 = max_of(reach2, dot(v, v));
    const Vec3<T> to_v = v - apex;
    // The apex's foot on each edge line through v, relative to the apex: the
    // edge's other vertex computes the same point up to rounding, so the two
    // triangles make (apex, edge), and all of them stay near the face. One
    // division for both feet where the product of the lines' squared
    // directions stays well inside the exponent's range.
    const Vec3<T> next_direction = cross(p.normal, cell.plane(ids[(e + 1) % 3]).normal);
    const Vec3<T> previous_direction = cross(p.normal, cell.plane(ids[(e + 2) % 3]).normal);
    const T next2 = dot(next_direction, next_direction), previous2 = dot(previous_direction, previous_direction);
    const T both2 = next2 * previous2;
    T next_step = dot(to_v, next_direction), previous_step = dot(to_v, previous_direction);
    if (both2 > T(1e-280) && both2 < T(1e280)) {
      const T inverse = T(1) / both2;
      next_step = next_step * (previous2 * inverse);
      previous_step = previous_step * (next2 * inverse);
    } else {
      next_step = next_step / next2;
      previous_step = previous_step / previous2;
    }
    const Vec3<T> next_foot = to_v - next_step * next_direction;
    const Vec3<T> previous_foot = to_v - previous_step * previous_direction;
    const T a = dot(outward, cross(next_foot, to_v));
    const T b = dot(outward, cross(previous_foot, to_v));
    twice_area += a - b;
    moment = moment + a * (next_foot + to_v) - b * (previous_foot + to_v);
    if constexpr (kMoments) {
      add_triangle_moments(a, next_foot, to_v, second, third);
      add_triangle_moments(-b, previous_foot, to_v, second, third);
    }
  });
  if (!on_face) return false;
  face.area = T(0.5) * twice_area * inverse_length(dot(p.normal, p.normal));
  if (!(face.area > T(FaceAreaFloor<T>::value) * reach2)) return false;  // NaN too
  const Vec3<T> shift = (T(1) / (T(3) * twice_area)) * moment;  // the centroid from the apex
  face.centroid = apex + shift;
  if constexpr (kMoments) {
    // From the apex to the centroid w: u u^T = y y^T - a w w^T;
    // |u|^2 u = |y|^2 y - tr(Y) w - 2 Y w + 2 a |w|^2 w (Y = y y^T integrated).
    const T unit = T(0.5) * inverse_length(dot(p.normal, p.normal));  // twice_area x unit = the area
    T y2[6];
    for (int m = 0; m < 6; ++m) y2[m] = second[m] * (unit / T(12));
    const Vec3<T> y3 = (unit / T(30)) * third;
    const Vec3<T> w = shift;
    const T a = face.area;
    face.second[0] = y2[0] - a * w.x * w.x;
    face.second[1] = y2[1] - a * w.y * w.y;
    face.second[2] = y2[2] - a * w.z * w.z;
    face.second[3] = y2[3] - a * w.x * w.y;
    face.second[4] = y2[4] - a * w.x * w.z;
    face.second[5] = y2[5] - a * w.y * w.z;
    const Vec3<T> yw = {y2[0] * w.x + y2[3] * w.y + y2[4] * w.z, y2[3] * w.x + y2[1] * w.y + y2[5] * w.z,
                        y2[4] * w.x + y2[5] * w.y + y2[2] * w.z};
    face.third = y3 - (y2[0] + y2[1] + y2[2]) * w - T(2) * yw + (T(2) * a * dot(w, w)) * w;
  }
  return true;
}

// The faces of a computed cell, its planes split over its lanes (plane q on
// lane q % lanes). target_of(q, plane) says what each face is (a neighbour,
// a wall, or kNoFace); emit(slot, target, face) is called for each, `slot`
// the face's rank among the cell's neighbour faces (in plane order; -1 for a
// wall). Returns the number of neighbour faces, in every lane.
template <bool kMoments, typename Cell, typename OnPlane, typename TargetOf, typename Emit>
TV_HD int for_each_face_on(const Cell& cell, OnPlane&& on_plane, TargetOf&& target_of, Emit&& emit) {
  using T = typename Cell::Scalar;
  const typename Cell::Lanes lanes = cell.group();
  constexpr int kLanes = Cell::Lanes::kCount;
  const int planes = cell.plane_count();
  int count = 0;
  for (int base = 0; base < planes; base += kLanes) {
    const int q = base + lanes.index();
    Face<T> face;
    int32_t target = kNoFace;
    if (q < planes && face_of_plane<kMoments>(cell, q, on_plane, face)) target = target_of(q, cell.plane(q));
    const bool neighbor_face = target >= 0;
    const uint32_t word = lanes.ballot(neighbor_face);
    if (target != kNoFace) emit(neighbor_face ? count + bit_count(word & lanes.below()) : -1, target, face);
    count += bit_count(word);
  }
  return count;
}

// A cell of one lane whose Cell::kIndexedVertices bounds its vertices
// (nonzero) lists each plane's vertices first (VerticesByPlane); the
// others scan them for every plane.
template <bool kMoments, typename Cell, typename TargetOf, typename Emit>
TV_HD int for_each_face(const Cell& cell, TargetOf&& target_of, Emit&& emit) {
  if constexpr (Cell::Lanes::kCount == 1 && Cell::kIndexedVertices > 0) {
    const VerticesByPlane<Cell::kMaxBisectors + kBoxPlanes, Cell::kIndexedVertices> index(cell);
    const auto on_plane = [&](int q, auto&& visit) { index.on_plane(q, visit); };
    return for_each_face_on<kMoments>(cell, on_plane, target_of, emit);
  } else {
    const auto on_plane = [&](int q, auto&& visit) { ScanVertices::on_plane(cell, q, visit); };
    return for_each_face_on<kMoments>(cell, on_plane, target_of, emit);
  }
}

}  // namespace core
}  // namespace torchvor
