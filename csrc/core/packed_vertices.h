// The thread cell's two loops over all its vertices, classify and integrate
// (convex_cell.h), on the host's vector units: a pack of vertices at a time
// (host_packs.h), with the same formulas as the scalar loops. The GPU runs
// the scalar loops (a thread is already one lane of a vector there).
#pragma once

#include <cstring>
#include <type_traits>

#include "cell_moments.h"
#include "common.h"
#include "host_packs.h"

#if defined(TORCHVOR_HOST_PACKS)

namespace torchvor {
namespace core {

// Whether cells of scalar T run these loops (float and double; double-double
// decides by exact predicates, vertex by vertex).
template <typename T>
constexpr bool packs_vertices() {
  return std::is_same<T, float>::value || std::is_same<T, double>::value;
}

// Vertex t for t < count, else the last one (a lane past the end reads a
// real vertex, and its result is masked).
TV_HD int lane_vertex(int t, int count) {
  return t < count ? t : count - 1;
}

// The vertices [base, base + W) of a cell as a pack, lanes past `count`
// repeating the last vertex: a whole pack in three vector loads from the
// host's column slots, else gathered vertex by vertex.
template <typename T, typename Cell>
TV_HD Vec3<Pack<T>> vertex_pack(const Cell& cell, int base, int count) {
  using P = Pack<T>;
  Vec3<P> v;
  if constexpr (std::remove_reference<decltype(cell.triangle)>::type::kColumns) {
    if (base + P::kWidth <= count) {
      memcpy(&v.x.lanes, cell.triangle.x + base, sizeof(v.x.lanes));
      memcpy(&v.y.lanes, cell.triangle.y + base, sizeof(v.y.lanes));
      memcpy(&v.z.lanes, cell.triangle.z + base, sizeof(v.z.lanes));
      return v;
    }
  }
  for (int i = 0; i < P::kWidth; ++i) {
    const Vec3<T> vertex = cell.vertex(lane_vertex(base + i, count));
    v.x.lanes[i] = vertex.x;
    v.y.lanes[i] = vertex.y;
    v.z.lanes[i] = vertex.z;
  }
  return v;
}

// ConvexCell::classify: marks in `clipped` (cleared first) the vertices more
// than `threshold` (< 0) outside plane p; returns whether any is, and the
// largest |vertex|^2 of the others. The same tests as the scalar loop, and
// the same radius (|v|^2 rounded as squared_norm rounds it).
template <typename Cell, typename T, typename Mask>
TV_HD bool classify_packed(const Cell& cell, const Plane<T>& p, T threshold, Mask& clipped, T& kept_radius2) {
  using P = Pack<T>;
  constexpr int W = P::kWidth;
  static_assert(32 % W == 0, "a pack's bits fall in one mask word");
  const int count = cell.vertex_count();
  const P nx(p.normal.x), ny(p.normal.y), nz(p.normal.z), offset(p.offset), limit(threshold);
  const auto lanes = lane_indices<T>();
  P kept(T(0));
  uint32_t any_clipped = 0u;
  clipped.clear();
  for (int base = 0; base < count; base += W) {
    const Vec3<P> v = vertex_pack<T>(cell, base, count);
    const PackMask<T> valid = {lanes < count - base};
    const PackMask<T> outside = (dot(Vec3<P>{nx, ny, nz}, v) + offset < limit) & valid;
    kept = select(outside | ~valid, kept, max_of(kept, squared_norm(v)));
    const uint32_t bits = mask_bits(outside);
    clipped.word[base >> 5] |= bits << (base & 31);
    any_clipped |= bits;
  }
  kept_radius2 = kept.max();
  return any_clipped != 0u;
}

// ConvexCell::integrate's sum over the vertices: CellMoments::add_vertex of
// every vertex, its position and planes taken relative to `origin` (a
// power cell's; the seed, the origin of coordinates, for the others).
template <bool kGeneralPlanes, typename Cell, typename T>
TV_HD CellMoments<T, kGeneralPlanes> add_vertices_packed(const Cell& cell, Vec3<T> origin) {
  using P = Pack<T>;
  constexpr int W = P::kWidth;
  const int count = cell.vertex_count();
  const auto lanes = lane_indices<T>();
  CellMoments<P, kGeneralPlanes> total = CellMoments<P, kGeneralPlanes>::zero();
  for (int base = 0; base < count; base += W) {
    Plane<P> planes[3];
    CachedVertex<P> vertex;
    vertex.position = vertex_pack<T>(cell, base, count);
    if constexpr (kGeneralPlanes) vertex.position = vertex.position - Vec3<P>{P(origin.x), P(origin.y), P(origin.z)};
    vertex.radius2 = squared_norm(vertex.position);
    P rounding2 = vertex.radius2;
    for (int i = 0; i < W; ++i) {
      const int t = lane_vertex(base + i, count);
      if constexpr (kGeneralPlanes) rounding2.lanes[i] = cell.rounding_radius2(t);
      int ids[3];
      cell.vertex_planes(t, ids);
      for (int e = 0; e < 3; ++e) {
        const Plane<T> plane = cell.plane(ids[e]);
        planes[e].normal.x.lanes[i] = plane.normal.x;
        planes[e].normal.y.lanes[i] = plane.normal.y;
        planes[e].normal.z.lanes[i] = plane.normal.z;
        planes[e].offset.lanes[i] = kGeneralPlanes ? plane.offset + dot(plane.normal, origin) : plane.offset;
      }
    }
    CellMoments<P, kGeneralPlanes> part = CellMoments<P, kGeneralPlanes>::zero();
    part.add_vertex(planes, vertex, rounding2);
    const PackMask<T> valid = {lanes < count - base};
    const P zero(T(0));
    total.six_volume += select(valid, part.six_volume, zero);
    total.unsigned_six_volume += select(valid, part.unsigned_six_volume, zero);
    total.conditioned_six_volume += select(valid, part.conditioned_six_volume, zero);
    total.m1.x += select(valid, part.m1.x, zero);
    total.m1.y += select(valid, part.m1.y, zero);
    total.m1.z += select(valid, part.m1.z, zero);
    total.m2 += select(valid, part.m2, zero);
    total.unsigned_m2 += select(valid, part.unsigned_m2, zero);
  }
  return {total.six_volume.sum(),
          total.unsigned_six_volume.sum(),
          total.conditioned_six_volume.sum(),
          {total.m1.x.sum(), total.m1.y.sum(), total.m1.z.sum()},
          total.m2.sum(),
          total.unsigned_m2.sum()};
}

}  // namespace core
}  // namespace torchvor

#endif
