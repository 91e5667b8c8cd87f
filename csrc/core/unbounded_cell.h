// A cell of any number of planes, on the host: the last step of recovery,
// for cells with thousands of faces or more (a point above a dense layer of
// points on a box wall faces every point of the layer below it).
//
// It computes what the double-double ConvexCell computes (the same planes,
// vertices, exact predicates and integrals) in arrays that grow. Its
// triangles also know their three neighbours, so a clip costs the removed
// region, not the whole cell: ConvexCell scans every vertex for each plane
// (planes x vertices, minutes at 100K faces). A clip walks from the
// newest vertex downhill on the plane's value, in double, to the vertex
// farthest outside the plane: a linear function on a convex polytope has no
// other local minimum. The walk crosses plateaus of vertices within
// rounding of each other (cospherical points). If that vertex is outside by
// the exact predicate, the removed region is gathered from it by adjacency,
// by exact predicates (so it is a disc, as in ConvexCell); if it is inside by
// more than rounding, the plane misses the cell; in between, the vertices
// near the plane are tested exactly.
//
// The interface is ConvexCell's, as compute_cell uses it.
#pragma once

#include <cmath>
#include <cstdint>
#include <queue>
#include <vector>

#include "convex_cell.h"
#include "exact_predicates.h"
#include "lanes.h"
#include "status.h"

namespace torchvor {
namespace core {

class UnboundedCell {
 public:
  using Scalar = DoubleDouble;
  using Lanes = SingleLane;
  static constexpr bool kTetrahedronStart = false;
  static constexpr bool kListOnly = true;  // compute_cell: never finished on the grid
  int8_t status = kSuccess;

  Lanes group() const { return {}; }

  // ConvexCell's accessors for for_each_face (vertex_planes: false for a free slot).
  static constexpr int kIndexedVertices = 0;  // no bound: for_each_face scans the vertices
  int plane_count() const { return int(planes_.size()); }
  Plane<DoubleDouble> plane(int q) const { return planes_[q]; }
  int vertex_count() const { return int(triangles_.size()); }
  Vec3<DoubleDouble> vertex(int t) const { return triangles_[t].position; }
  bool vertex_planes(int t, int (&ids)[3]) const {
    for (int e = 0; e < 3; ++e) ids[e] = triangles_[t].corner[e];
    return triangles_[t].alive;
  }

  // The box [lo, hi] (relative to the seed) as 6 planes and 8 triangles.
  void init_box(Vec3<DoubleDouble> lo, Vec3<DoubleDouble> hi, DoubleDouble relative_tolerance) {
    tolerance_ = relative_tolerance;
    status = kSuccess;
    planes_.clear();
    triangles_.clear();
    free_.clear();
    by_radius_ = {};
    for (int q = 0; q < kBoxPlanes; ++q) planes_.push_back(box_plane(q, lo, hi));
    for (int t = 0; t < 8; ++t) {
      const uint32_t c = box_triangle(t);
      triangles_.push_back({});
      set_triangle(t, int32_t(c & 0xffu), int32_t(c >> 8 & 0xffu), int32_t(c >> 16 & 0xffu));
    }
    for (int t = 0; t < 8; ++t) {  // each edge (a, b) meets its reverse (b, a)
      for (int e = 0; e < 3; ++e) {
        for (int u = 0; u < 8; ++u) {
          const int k = edge_index(triangles_[u], triangles_[t].corner[(e + 1) % 3], triangles_[t].corner[e]);
          if (u != t && k >= 0) triangles_[t].adjacent[e] = u;
        }
      }
    }
    hint_ = 0;
    stamp_.assign(triangles_.size(), 0u);
    generation_ = 0u;
  }

  // The largest |vertex|^2 (entries of removed or rewritten slots are
  // dropped as they surface).
  DoubleDouble largest_radius2() {
    while (!by_radius_.empty()) {
      const RadiusEntry& top = by_radius_.top();
      const Triangle& t = triangles_[top.slot];
      if (t.alive && t.version == top.version) return top.radius2;
      by_radius_.pop();
    }
    return DoubleDouble(0.0);
  }

  // Whether no neighbour this far (or farther) can cut the cell.
  bool security_radius_reached(DoubleDouble neighbor_dist2) {
    return beyond_security_radius(neighbor_dist2, largest_radius2(), tolerance_);
  }

  // Clip by the bisector of the seed and a neighbour at r.
  bool clip_by_bisector(Vec3<DoubleDouble> r) {
    const Plane<DoubleDouble> p = bisector_plane(r, squared_norm(r));
    const int32_t first = first_removed(p);
    if (first < 0) return true;  // the plane misses the cell
    if (planes_.size() >= size_t(INT32_MAX)) return fail(kTooManyPlanes);
    const int32_t q = int32_t(planes_.size());
    planes_.push_back(p);
    // The removed region, by adjacency from `first`, and its boundary edges
    // (from, to) with the kept triangle across each.
    next_generation();
    region_.clear();
    region_.push_back(first);
    stamp_[first] = generation_ | kRemoved;
    for (size_t i = 0; i < region_.size(); ++i) {
      const Triangle& t = triangles_[region_[i]];
      for (int e = 0; e < 3; ++e) {
        const int32_t u = t.adjacent[e];
        if ((stamp_[u] & ~kRemoved) == generation_) continue;
        const bool outside = side(u, p) < 0;
        stamp_[u] = generation_ | (outside ? kRemoved : 0u);
        if (outside) region_.push_back(u);
      }
    }
    boundary_.clear();
    for (const int32_t t : region_) {
      for (int e = 0; e < 3; ++e) {
        const int32_t u = triangles_[t].adjacent[e];
        if (stamp_[u] != (generation_ | kRemoved)) {
          boundary_.push_back({triangles_[t].corner[e], triangles_[t].corner[(e + 1) % 3], u});
        }
      }
    }
    // The boundary as one cycle: the edge leaving each plane.
    if (edge_from_.size() < planes_.size()) edge_from_.resize(planes_.size(), -1);
    for (size_t e = 0; e < boundary_.size(); ++e) {
      int32_t& slot = edge_from_[boundary_[e].from];
      if (slot >= 0) return clear_edges_and_fail();  // not a disc (cannot happen with exact predicates)
      slot = int32_t(e);
    }
    // Close the hole with a fan (from, to, q) along the cycle, in the removed
    // triangles' slots first.
    const int length = int(boundary_.size());
    fan_.assign(length, -1);
    int32_t e = 0;
    for (int n = 0; n < length; ++n) {
      const BoundaryEdge& edge = boundary_[e];
      const int32_t t = n < int(region_.size()) ? region_[n] : new_slot();
      set_triangle(t, edge.from, edge.to, q);
      if (!is_finite_value(triangles_[t].radius2)) return clear_edges_and_fail();
      triangles_[t].adjacent[0] = edge.outer;
      Triangle& outer = triangles_[edge.outer];
      outer.adjacent[edge_index(outer, edge.to, edge.from)] = t;
      fan_[e] = t;
      const int32_t next = edge_from_[edge.to];
      if (next < 0 || (n + 1 < length) == (next == 0)) return clear_edges_and_fail();
      e = next;
    }
    for (int n = 0; n < length; ++n) {  // (to, q) of edge n meets (q, to) of the edge leaving `to`
      const int32_t t = fan_[n], u = fan_[edge_from_[boundary_[n].to]];
      triangles_[t].adjacent[1] = u;
      triangles_[u].adjacent[2] = t;
    }
    for (size_t n = length; n < region_.size(); ++n) {  // fewer new triangles than removed
      triangles_[region_[n]].alive = false;
      free_.push_back(region_[n]);
    }
    for (const BoundaryEdge& edge : boundary_) edge_from_[edge.from] = -1;
    hint_ = fan_[0];
    return true;
  }

  // Volume, first and second moment (relative to the seed), as ConvexCell.
  void integrate(DoubleDouble& volume, Vec3<DoubleDouble>& first_moment, DoubleDouble& second_moment,
                 CellRounding<DoubleDouble>& rounding) const {
    CellMoments<DoubleDouble> moments = CellMoments<DoubleDouble>::zero();
    for (const Triangle& t : triangles_) {
      if (!t.alive) continue;
      const Plane<DoubleDouble> planes[3] = {planes_[t.corner[0]], planes_[t.corner[1]], planes_[t.corner[2]]};
      moments.add_vertex(planes, {t.position, t.radius2});
    }
    moments.finish(volume, first_moment, second_moment, rounding);
  }

 private:
  static constexpr uint32_t kRemoved = 0x80000000u;  // a stamp's flag: outside the plane

  struct Triangle {
    int32_t corner[3];    // planes a, b, c, as ConvexCell's triangles
    int32_t adjacent[3];  // across edge e (corner e, corner e + 1): the triangle with the reverse edge
    Vec3<DoubleDouble> position;
    DoubleDouble radius2;
    exact::HomogeneousVertex homogeneous;
    bool alive;
    uint32_t version;  // how many times the slot was written
  };
  struct RadiusEntry {
    DoubleDouble radius2;
    int32_t slot;
    uint32_t version;
    bool operator<(const RadiusEntry& other) const { return radius2 < other.radius2; }
  };
  struct BoundaryEdge {
    int32_t from, to;  // planes, in the removed triangle's orientation
    int32_t outer;     // the kept triangle across it
  };

  bool fail(int8_t code) {
    status = code;
    return false;
  }
  bool clear_edges_and_fail() {
    for (const BoundaryEdge& edge : boundary_) edge_from_[edge.from] = -1;
    return fail(kBoundaryError);
  }

  static int edge_index(const Triangle& t, int32_t from, int32_t to) {
    for (int e = 0; e < 3; ++e) {
      if (t.corner[e] == from && t.corner[(e + 1) % 3] == to) return e;
    }
    return -1;
  }

  void set_triangle(int32_t t, int32_t a, int32_t b, int32_t c) {
    Triangle& tri = triangles_[t];
    const Plane<DoubleDouble>&pa = planes_[a], &pb = planes_[b], &pc = planes_[c];
    tri.corner[0] = a;
    tri.corner[1] = b;
    tri.corner[2] = c;
    tri.position = intersect_planes(pa, pb, pc, {a >= kBoxPlanes, b >= kBoxPlanes, c >= kBoxPlanes},
                                    {DoubleDouble(0.0), DoubleDouble(0.0), DoubleDouble(0.0)});
    tri.radius2 = squared_norm(tri.position);
    tri.homogeneous = exact::homogeneous(pa, pb, pc);
    tri.alive = true;
    ++tri.version;
    by_radius_.push({tri.radius2, t, tri.version});
  }

  int32_t new_slot() {
    if (!free_.empty()) {
      const int32_t t = free_.back();
      free_.pop_back();
      return t;
    }
    triangles_.push_back({});
    stamp_.push_back(0u);
    return int32_t(triangles_.size() - 1);
  }

  void next_generation() {
    if (++generation_ >= kRemoved) {  // wrapped: restart the stamps
      std::fill(stamp_.begin(), stamp_.end(), 0u);
      generation_ = 1u;
    }
  }


  // -1 outside p, 0 on it, +1 inside: exact (exact_predicates.h).
  int side(int32_t t, const Plane<DoubleDouble>& p) const {
    const Triangle& tri = triangles_[t];
    const int filtered = exact::filtered_side(tri.homogeneous, p);
    if (filtered != 2) return filtered;
    const Plane<DoubleDouble>* const rows[4] = {&planes_[tri.corner[0]], &planes_[tri.corner[1]],
                                                &planes_[tri.corner[2]], &p};
    return exact::exact_side(rows,
                             {tri.corner[0] >= kBoxPlanes, tri.corner[1] >= kBoxPlanes, tri.corner[2] >= kBoxPlanes, true},
                             {DoubleDouble(0.0), DoubleDouble(0.0), DoubleDouble(0.0), DoubleDouble(0.0)});
  }

  // The plane's value at triangle t's vertex, in double (for the walk only).
  double value(int32_t t, const double (&n)[3], double offset) const {
    const Vec3<DoubleDouble>& v = triangles_[t].position;
    return n[0] * v.x.hi + n[1] * v.y.hi + n[2] * v.z.hi + offset;
  }

  // A triangle whose vertex p cuts away, or -1.
  int32_t first_removed(const Plane<DoubleDouble>& p) {
    const double n[3] = {p.normal.x.hi, p.normal.y.hi, p.normal.z.hi};
    const double offset = p.offset.hi;
    // Rounding of a value: far below 1e-12 of its terms' size.
    const double margin = 1e-12 * (std::sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]) *
                                       std::sqrt(largest_radius2().hi) + std::fabs(offset));
    int32_t t = hint_;
    if (!triangles_[t].alive) t = any_alive();
    double lowest = value(t, n, offset);
    for (;;) {
      // Downhill: to the lowest neighbour while it is lower.
      for (bool moved = true; moved;) {
        moved = false;
        const Triangle& tri = triangles_[t];
        for (int e = 0; e < 3; ++e) {
          const double f = value(tri.adjacent[e], n, offset);
          if (f < lowest) {
            lowest = f;
            t = tri.adjacent[e];
            moved = true;
          }
        }
      }
      // A plateau of vertices within `margin` of t's value (coincident
      // vertices of cospherical points) may hide a way down: look across it.
      const int32_t lower = lower_beyond_plateau(t, n, offset, lowest, margin);
      if (lower < 0) break;
      t = lower;
      lowest = value(t, n, offset);
    }
    if (lowest > margin) return -1;
    // Near the plane or outside it: the exact predicate decides, over the
    // vertices connected to t whose values are within rounding of 0 or below
    // (the sublevel sets of a linear function on a convex polytope are
    // connected).
    next_generation();
    region_.clear();
    region_.push_back(t);
    stamp_[t] = generation_;
    for (size_t i = 0; i < region_.size(); ++i) {
      const int32_t u = region_[i];
      if (side(u, p) < 0) return u;
      for (int e = 0; e < 3; ++e) {
        const int32_t w = triangles_[u].adjacent[e];
        if (stamp_[w] == generation_ || value(w, n, offset) > 2.0 * margin) continue;
        stamp_[w] = generation_;
        region_.push_back(w);
      }
    }
    return -1;
  }

  // A vertex lower than `lowest` - margin next to the plateau of vertices
  // within `margin` of it that holds t, or -1.
  int32_t lower_beyond_plateau(int32_t t, const double (&n)[3], double offset, double lowest, double margin) {
    next_generation();
    plateau_.clear();
    plateau_.push_back(t);
    stamp_[t] = generation_;
    for (size_t i = 0; i < plateau_.size(); ++i) {
      const Triangle& tri = triangles_[plateau_[i]];
      for (int e = 0; e < 3; ++e) {
        const int32_t u = tri.adjacent[e];
        if (stamp_[u] == generation_) continue;
        stamp_[u] = generation_;
        const double f = value(u, n, offset);
        if (f < lowest - margin) return u;
        if (f <= lowest + margin) plateau_.push_back(u);
      }
    }
    return -1;
  }

  int32_t any_alive() const {
    for (size_t t = 0; t < triangles_.size(); ++t) {
      if (triangles_[t].alive) return int32_t(t);
    }
    return 0;
  }

  std::vector<Plane<DoubleDouble>> planes_;  // 0-5 the box's faces, then the bisectors in clip order
  std::vector<Triangle> triangles_;          // slots, alive or free
  std::vector<int32_t> free_;                // the free slots
  std::vector<uint32_t> stamp_;              // per slot: the generation that last visited it (| kRemoved)
  uint32_t generation_ = 0u;
  std::vector<int32_t> region_, plateau_, fan_, edge_from_;
  std::vector<BoundaryEdge> boundary_;
  std::priority_queue<RadiusEntry> by_radius_;  // the vertices' |v|^2, largest first
  DoubleDouble tolerance_ = DoubleDouble(0.0);
  int32_t hint_ = 0;  // a triangle of the last fan: the next walk starts there
};

}  // namespace core
}  // namespace torchvor
