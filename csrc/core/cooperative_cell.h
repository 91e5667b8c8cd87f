// A convex cell clipped by a group of lanes together (a warp on the GPU).
//
// The same cell as ConvexCell (convex_cell.h): dual triangles of plane ids
// with cached vertices, the same predicate, the same geometry (the free
// functions there), the same failure codes. What differs is who does the
// work. ConvexCell runs a cell on one thread, and on the GPU that thread's
// arrays live in local memory: the kernel waits on it, and the lanes of a
// warp diverge because every cell takes its own path. Here the arrays live in
// memory the group shares (shared memory on the GPU), every loop over
// triangles or removed triangles is spread across the lanes, and the lanes
// agree on every branch: ballots give the clip mask and the ranks at which
// removed triangles and boundary edges are gathered.
//
// Slot t belongs to lane t % kLanes in round t / kLanes: bit l of round j's
// ballot word is slot j * kLanes + l.
#pragma once

#include "convex_cell.h"
#include "lanes.h"

namespace torchvor {
namespace core {

// The arrays of one cooperative cell, in memory its lanes share.
template <typename T, int MAX_PLANES, int MAX_TRIANGLES>
struct CooperativeCellArrays {
  static constexpr int kMaxTriangles = MAX_TRIANGLES;
  Plane<T> plane[MAX_PLANES];
  CachedVertex<T> vertex[MAX_TRIANGLES];
  uint32_t triangle[MAX_TRIANGLES];  // plane ids (a, b, c) packed as a | b << 8 | c << 16
  // One clip's removed region: the removed triangles' corners and slots
  // (slots increasing), its boundary edges (from | to << 8, any order), and
  // the successor and the predecessor of each boundary plane id (to | stamp
  // << 8 and from | stamp << 8: the stamp tells this clip's links from older
  // ones without clearing the arrays).
  uint32_t removed[MAX_TRIANGLES];
  uint16_t hole[MAX_TRIANGLES];
  uint16_t edge[MAX_PLANES];
  uint32_t link[MAX_PLANES];
  uint32_t back_link[MAX_PLANES];
  // The removed triangles' directed edges as bits: bit `to` of plane
  // `from`'s kMaskWords words (cleared for the removed triangles' corners).
  static constexpr int kMaskWords = (MAX_PLANES + 31) / 32;
  uint32_t edge_mask[MAX_PLANES * kMaskWords];
  uint8_t renumber[MAX_PLANES];  // compact_planes
};

template <typename T, int MAX_PLANES, int MAX_TRIANGLES, typename LanesT>
struct CooperativeCell {
  using Scalar = T;
  using Lanes = LanesT;
  // Always from the box: a tetrahedron start slows this cell (see
  // start_tetrahedron).
  static constexpr bool kTetrahedronStart = false;
  using Arrays = CooperativeCellArrays<T, MAX_PLANES, MAX_TRIANGLES>;
  static_assert(MAX_PLANES <= 255, "plane ids are stored as uint8 (255 = none)");
  static_assert(MAX_TRIANGLES <= 65535, "slots are stored as uint16");
  static constexpr uint8_t kNone = 255;
  static constexpr int kLanes = Lanes::kCount;
  static constexpr int kRounds = (MAX_TRIANGLES + kLanes - 1) / kLanes;     // slots per lane
  static constexpr int kPlaneRounds = (MAX_PLANES + kLanes - 1) / kLanes;  // planes per lane

  Arrays& a;
  Lanes lanes;
  // Uniform across the lanes (each computes the same value).
  int32_t num_planes;
  int32_t num_triangles;
  T radius2;         // the largest |vertex|^2: the ball around the seed holding the cell
  T tolerance;       // relative tolerance of the clipping predicate
  int8_t status;
  uint32_t stamp;    // numbers the boundary searches (see CooperativeCellArrays::link)

  TV_HD CooperativeCell(Arrays& arrays, Lanes group) : a(arrays), lanes(group) {}

  TV_HD Lanes group() const { return lanes; }

  TV_HD static uint32_t pack(uint32_t p, uint32_t q, uint32_t r) { return p | q << 8 | r << 16; }
  TV_HD static uint8_t corner(uint32_t triangle, int e) { return uint8_t(triangle >> (8 * e)); }

  TV_HD void init_box(Vec3<T> lo, Vec3<T> hi, T relative_tolerance) {
    const int lane = lanes.index();
    for (int q = lane; q < kBoxPlanes; q += kLanes) a.plane[q] = box_plane(q, lo, hi);
    // Links of the previous cell in these arrays carry stamps this cell
    // will reuse: clear them.
    for (int q = lane; q < MAX_PLANES; q += kLanes) {
      a.link[q] = 0u;
      a.back_link[q] = 0u;
    }
    lanes.sync();
    T largest = T(0);
    for (int t = lane; t < 8; t += kLanes) largest = max_of(largest, set_triangle(t, box_triangle(t)).radius2);
    radius2 = lanes.max(largest);
    num_planes = kBoxPlanes;
    num_triangles = 8;
    tolerance = relative_tolerance;
    status = kSuccess;
    stamp = 0u;
    lanes.sync();
  }

  // The largest |vertex|^2 (compute_cell's radius), in every lane.
  TV_HD T largest_radius2() const { return radius2; }
  TV_HD bool security_radius_reached(T neighbor_dist2) const {
    return beyond_security_radius(neighbor_dist2, radius2, tolerance);
  }

  // ConvexCell's accessors for the sweep (vertex_balls.h), on the shared
  // arrays. Any lane may call them, each for its own arguments: they use no
  // collective. A bisector's plane is kept, not its neighbour; its normal is
  // minus the neighbour, exactly (bisector_plane).
  TV_HD int vertex_count() const { return num_triangles; }
  TV_HD Vec3<T> vertex(int t) const { return a.vertex[t].position; }
  TV_HD bool vertex_planes(int t, int (&ids)[3]) const {
    for (int e = 0; e < 3; ++e) ids[e] = corner(a.triangle[t], e);
    return true;
  }
  TV_HD int plane_count() const { return num_planes; }
  TV_HD Plane<T> plane(int q) const { return a.plane[q]; }
  static constexpr int kMaxBisectors = MAX_PLANES - kBoxPlanes;
  static constexpr int kIndexedVertices = 0;  // for_each_face scans the vertices (lanes share them)
  TV_HD Vec3<T> bisector_neighbor(int q) const {
    const Vec3<T> normal = a.plane[q].normal;
    return {-normal.x, -normal.y, -normal.z};
  }
  TV_HD bool has_bisector(Vec3<T> r) const {
    for (int q = kBoxPlanes; q < num_planes; ++q) {
      const Vec3<T> other = bisector_neighbor(q);
      if (other.x == r.x && other.y == r.y && other.z == r.z) return true;
    }
    return false;
  }
  // ConvexCell::bounding_neighbors: each lane computes the same list.
  TV_HD int bounding_neighbors(T nearest2, Vec3<T>* r, T* r2) const {
    BitSet<(MAX_PLANES + 31) / 32> used;
    used.clear();
    for (int t = 0; t < num_triangles; ++t) {
      const uint32_t corners = a.triangle[t];
      for (int e = 0; e < 3; ++e) used.set(corner(corners, e));
    }
    int count = 0;
    for (int q = kBoxPlanes; q < num_planes; ++q) {
      if (!used.test(q)) continue;
      insert_by_distance(bisector_neighbor(q), nearest2, r, r2, count);
    }
    return count;
  }

  // ConvexCell::clip_by_bisector, by the group: the same predicate, the
  // same failures. New triangles go into the removed triangles' slots first
  // (lowest first) and after the last one beyond that; with fewer new than
  // removed triangles, kept triangles from the end fill the holes left.
  TV_HD bool clip_by_bisector(Vec3<T> r) {
    const T r2 = squared_norm(r);  // as the thread cell: the same band, bit for bit
    const Plane<T> p = bisector_plane(r, r2);
    uint32_t clipped[kRounds];
    T kept_radius2;  // this lane's largest |vertex|^2 among the vertices the plane keeps
    int removed = 0;
    int boundary = 0;
    // As the thread cell's far_beside_bisector: a pass of its own, as rare
    // as such planes, so that classify's pass (every plane's) does no more.
    if (far_beside_bisector(r2, radius2)) {
      bool could_cut = false;
      for_own_slots([&](int t) {
        could_cut = could_cut || rounding_could_cut(dot(p.normal, a.vertex[t].position) + p.offset, r2 * radius2);
      });
      if (lanes.any(could_cut)) return fail(kIllConditioned);
    }
    if (!classify(p, -tolerance * r2, clipped, kept_radius2)) return true;  // the plane misses the cell
    if (num_planes == MAX_PLANES) compact_planes();
    if (num_planes == MAX_PLANES) return fail(kTooManyPlanes);
    if (!removed_boundary(clipped, removed, boundary)) return fail(kBoundaryError);
    const int new_count = num_triangles - removed + boundary;
    if (new_count > MAX_TRIANGLES) return fail(kTooManyVertices);
    const int lane = lanes.index();
    const int new_plane = num_planes++;
    if (lane == 0) a.plane[new_plane] = p;
    lanes.sync();
    // Close the hole with a fan: boundary edge e (from, to) becomes triangle
    // (from, to, new plane). The radius stays exact: the kept vertices' and
    // the new ones'.
    T largest = kept_radius2;
    bool finite = true;  // no NaN or Inf vertex
    bool placed = true;  // no new vertex beyond the cell it cuts (beyond_the_cell)
    for (int e = lane; e < boundary; e += kLanes) {
      const uint32_t edge = a.edge[e];
      const int slot = e < removed ? int(a.hole[e]) : num_triangles + (e - removed);
      const T v2 = set_triangle(slot, pack(edge & 0xffu, edge >> 8, uint32_t(new_plane)), p).radius2;
      finite = finite && is_finite_value(v2);
      placed = placed && !beyond_the_cell(v2, radius2);
      largest = max_of(largest, v2);
    }
    if (boundary < removed) fill_holes(clipped, boundary, new_count);
    lanes.sync();
    // One vote for both checks; which one failed is asked only then.
    if (!lanes.all(finite && placed)) return fail(lanes.all(finite) ? kIllConditioned : kBoundaryError);
    radius2 = lanes.max(largest);
    num_triangles = new_count;
    return true;
  }

  // ConvexCell::integrate, each lane over its slots, then summed over the
  // lanes (in another order than one thread would: equal up to rounding).
  TV_HD void integrate(T& volume, Vec3<T>& first_moment, T& second_moment,
                       CellRounding<T>& rounding) const {
    CellMoments<T> moments = CellMoments<T>::zero();
    for_own_slots([&](int t) {
      const uint32_t corners = a.triangle[t];
      const Plane<T> planes[3] = {a.plane[corner(corners, 0)], a.plane[corner(corners, 1)],
                                  a.plane[corner(corners, 2)]};
      moments.add_vertex(planes, a.vertex[t]);
    });
    moments.six_volume = lanes.sum(moments.six_volume);
    moments.unsigned_six_volume = lanes.sum(moments.unsigned_six_volume);
    if constexpr (CellMoments<T>::kConditioned) {
      moments.conditioned_six_volume = lanes.sum(moments.conditioned_six_volume);
    }
    moments.m1 = {lanes.sum(moments.m1.x), lanes.sum(moments.m1.y), lanes.sum(moments.m1.z)};
    moments.m2 = lanes.sum(moments.m2);
    moments.unsigned_m2 = lanes.sum(moments.unsigned_m2);
    moments.finish(volume, first_moment, second_moment, rounding);
  }

 private:
  // body(t) for each live slot t of this lane (t < num_triangles).
  template <typename Body>
  TV_HD void for_own_slots(Body&& body) const {
    TV_UNROLL
    for (int j = 0; j < kRounds; ++j) {
      const int t = j * kLanes + lanes.index();
      if (t < num_triangles) body(t);
    }
  }

  TV_HD bool fail(int8_t code) {
    status = code;
    return false;
  }

  // Store triangle t and its vertex (one lane); returns the vertex.
  TV_HD CachedVertex<T> set_triangle(int t, uint32_t corners) {
    return set_triangle(t, corners, a.plane[corner(corners, 2)]);
  }
  // The same with the plane of its third corner at hand (the new plane of a fan).
  TV_HD CachedVertex<T> set_triangle(int t, uint32_t corners, const Plane<T>& third) {
    a.triangle[t] = corners;
    const Vec3<T> position = intersect_planes(a.plane[corner(corners, 0)], a.plane[corner(corners, 1)], third);
    const CachedVertex<T> v = {position, squared_norm(position)};
    a.vertex[t] = v;
    return v;
  }

  // The ballot words of the vertices more than `threshold` (< 0) outside
  // plane p; whether any is; and the largest |vertex|^2 of this lane's
  // vertices that the plane keeps.
  TV_HD bool classify(const Plane<T>& p, T threshold, uint32_t (&clipped)[kRounds], T& kept_radius2) const {
    uint32_t any_clipped = 0u;
    kept_radius2 = T(0);
    TV_UNROLL
    for (int j = 0; j < kRounds; ++j) {
      const int t = j * kLanes + lanes.index();
      bool outside = false;
      if (t < num_triangles) {
        const CachedVertex<T> v = a.vertex[t];
        outside = dot(p.normal, v.position) + p.offset < threshold;
        kept_radius2 = outside ? kept_radius2 : max_of(kept_radius2, v.radius2);
      }
      clipped[j] = lanes.ballot(outside);
      any_clipped |= clipped[j];
    }
    return any_clipped != 0u;
  }

  // Boundary of the removed region (Alg. 4): the directed edges of removed
  // triangles whose reverse no removed triangle has. Gathers the removed
  // triangles (a.removed, a.hole) and the boundary edges (a.edge); false if
  // the boundary is not one simple cycle.
  TV_HD bool removed_boundary(const uint32_t (&clipped)[kRounds], int& removed, int& boundary) {
    const int lane = lanes.index();
    const uint32_t below = lanes.below();
    lanes.sync();  // the previous attempt's reads of a.removed are done
    removed = 0;
    TV_UNROLL
    for (int j = 0; j < kRounds; ++j) {
      if ((clipped[j] >> lane) & 1u) {
        const int t = j * kLanes + lane;
        const int i = removed + bit_count(clipped[j] & below);
        const uint32_t corners = a.triangle[t];
        a.removed[i] = corners;
        a.hole[i] = static_cast<uint16_t>(t);
        TV_UNROLL
        for (int e = 0; e < 3; ++e) {
          TV_UNROLL
          for (int w = 0; w < Arrays::kMaskWords; ++w) a.edge_mask[corner(corners, e) * Arrays::kMaskWords + w] = 0u;
        }
      }
      removed += bit_count(clipped[j]);
    }
    stamp += 1u;
    lanes.sync();
    // An edge from -> to is interior iff a removed triangle has to -> from:
    // each removed triangle sets its edges' bits, then every edge tests one
    // bit (not every removed triangle).
    for (int i = lane; i < removed; i += kLanes) {
      const uint32_t corners = a.removed[i];
      TV_UNROLL
      for (int e = 0; e < 3; ++e) {
        const uint32_t from = corner(corners, e), to = corner(corners, (e + 1) % 3);
        lanes.set_shared_bits(&a.edge_mask[from * Arrays::kMaskWords + to / 32], 1u << (to % 32));
      }
    }
    lanes.sync();
    boundary = 0;
    for (int base = 0; base < removed; base += kLanes) {
      const int i = base + lane;
      const uint32_t corners = i < removed ? a.removed[i] : 0u;
      bool on_boundary[3] = {false, false, false};
      if (i < removed) {
        TV_UNROLL
        for (int e = 0; e < 3; ++e) {
          const uint32_t from = corner(corners, e), to = corner(corners, (e + 1) % 3);
          on_boundary[e] = ((a.edge_mask[to * Arrays::kMaskWords + from / 32] >> (from % 32)) & 1u) == 0u;
        }
      }
      const uint32_t words[3] = {lanes.ballot(on_boundary[0]), lanes.ballot(on_boundary[1]),
                                 lanes.ballot(on_boundary[2])};
      int index = boundary;
      TV_UNROLL
      for (int e = 0; e < 3; ++e) index += bit_count(words[e] & below);
      TV_UNROLL
      for (int e = 0; e < 3; ++e) {
        if (!on_boundary[e]) continue;
        const uint32_t from = corner(corners, e), to = corner(corners, (e + 1) % 3);
        if (index < MAX_PLANES) a.edge[index] = static_cast<uint16_t>(from | to << 8);
        // Two edges from one plane (or to one) store to the same link, and
        // one store lands: the check below finds the other edge's missing.
        lanes.store_shared(&a.link[from], to | stamp << 8);
        lanes.store_shared(&a.back_link[to], from | stamp << 8);
        ++index;
      }
      boundary += bit_count(words[0]) + bit_count(words[1]) + bit_count(words[2]);
    }
    // More edges than planes: some plane is on the boundary twice.
    if (boundary < 3 || boundary > MAX_PLANES) return false;
    lanes.sync();
    // Every plane at most once on the boundary: each edge's links are its
    // own (two edges from one plane, or to one plane: one of their links was
    // overwritten); and every edge leads to a plane that an edge leaves.
    bool own_links = true;
    for (int e = lane; e < boundary; e += kLanes) {
      const uint32_t edge = a.edge[e];
      const uint32_t from = edge & 0xffu, to = edge >> 8;
      own_links = own_links && a.link[from] == (to | stamp << 8) && a.back_link[to] == (from | stamp << 8) &&
                  (a.link[to] >> 8) == stamp;
    }
    if (!lanes.all(own_links)) return false;
    if (short_cycle_needs_no_walk(boundary)) return true;
    // One simple cycle through every boundary edge (not several): walk it
    // (every lane, reading the same links).
    const uint32_t start = a.edge[0] & 0xffu;
    uint32_t at = start;
    int length = 0;
    do {
      const uint32_t link = a.link[at];
      if ((link >> 8) != stamp) return false;  // a dead end
      at = link & 0xffu;
      ++length;
    } while (at != start && length <= boundary);
    return at == start && length == boundary;
  }

  // Fewer new triangles than removed ones: the list shrinks to `new_count`.
  // The holes below new_count not taken by the fan are hole[boundary ...];
  // the kept triangles at or above new_count (as many) move into them, in
  // order.
  TV_HD void fill_holes(const uint32_t (&clipped)[kRounds], int boundary, int new_count) {
    const int lane = lanes.index();
    const uint32_t below = lanes.below();
    int moved = 0;
    TV_UNROLL
    for (int j = 0; j < kRounds; ++j) {
      const int t = j * kLanes + lane;
      const bool kept_tail = t >= new_count && t < num_triangles && !((clipped[j] >> lane) & 1u);
      const uint32_t word = lanes.ballot(kept_tail);
      if (kept_tail) {
        const int hole = a.hole[boundary + moved + bit_count(word & below)];
        a.triangle[hole] = a.triangle[t];
        a.vertex[hole] = a.vertex[t];
      }
      moved += bit_count(word);
    }
  }

  // ConvexCell::compact_planes, by the group: drop the planes no vertex
  // uses and renumber the rest, keeping their order.
  TV_HD void compact_planes() {
    const int lane = lanes.index();
    const uint32_t below = lanes.below();
    for (int q = lane; q < num_planes; q += kLanes) a.renumber[q] = kNone;
    lanes.sync();
    for_own_slots([&](int t) {
      const uint32_t corners = a.triangle[t];
      TV_UNROLL
      for (int e = 0; e < 3; ++e) a.renumber[corner(corners, e)] = 0;  // same value from any lane
    });
    lanes.sync();
    Plane<T> kept[kPlaneRounds];
    int new_id[kPlaneRounds];
    int live = 0;
    TV_UNROLL
    for (int j = 0; j < kPlaneRounds; ++j) {
      const int q = j * kLanes + lane;
      const bool used = q < num_planes && a.renumber[q] != kNone;
      const uint32_t word = lanes.ballot(used);
      new_id[j] = used ? live + bit_count(word & below) : -1;
      if (used) kept[j] = a.plane[q];
      live += bit_count(word);
    }
    lanes.sync();  // every plane read before any moves
    TV_UNROLL
    for (int j = 0; j < kPlaneRounds; ++j) {
      if (new_id[j] >= 0) {
        a.plane[new_id[j]] = kept[j];
        a.renumber[j * kLanes + lane] = static_cast<uint8_t>(new_id[j]);
      }
    }
    lanes.sync();
    for_own_slots([&](int t) {
      const uint32_t corners = a.triangle[t];
      a.triangle[t] = pack(a.renumber[corner(corners, 0)], a.renumber[corner(corners, 1)],
                           a.renumber[corner(corners, 2)]);
    });
    lanes.sync();
    num_planes = live;
  }
};

}  // namespace core
}  // namespace torchvor
