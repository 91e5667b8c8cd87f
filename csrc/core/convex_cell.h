// A convex cell clipped by half-spaces, stored in dual form (paper §3.2-3.5).
//
// Coordinates are local to the seed (the seed is the origin), so that large
// offsets cost no precision. Planes: dot(normal, x) + offset > 0 inside. A
// vertex of the cell is a dual triangle (a, b, c) of the three plane ids that
// meet there; its position is cached when the triangle is created. Triangles
// are oriented consistently, which the integrals (§3.5) rely on.
#pragma once

#include <cstdint>
#include <type_traits>

#include "cell_moments.h"
#include "cell_planes.h"
#include "cell_start.h"
#include "common.h"
#include "double_double.h"
#include "exact_predicates.h"
#include "lanes.h"
#include "packed_vertices.h"
#include "status.h"

namespace torchvor {
namespace core {

// A dual triangle of the thread cell: its three plane ids and its vertex,
// one 16-byte record in float32 (one vector store; the corners and the
// position are read together by the integrals). |vertex|^2 is recomputed
// where needed rather than stored: the thread cell's speed is bound by how
// much cell state its threads keep in the L1 cache, and arithmetic is cheap beside a local-memory word.
template <typename T, typename Corners = uint32_t>
struct alignas(16) DualTriangle {
  Vec3<T> position;
  Corners corners;  // plane ids (a, b, c) packed (PlaneIds)
};

// How a thread cell's triangles name their planes: three ids packed in one
// word, a | b << kBits | c << 2 kBits; a byte each up to 255 planes, 16 bits
// each beyond (the host's largest tiers). The largest id means "none".
template <bool kWide>
struct PlaneIds {
  using Id = uint8_t;
  using Corners = uint32_t;
  static constexpr int kBits = 8;
};
template <>
struct PlaneIds<true> {
  using Id = uint16_t;
  using Corners = uint64_t;
  static constexpr int kBits = 16;
};

// Whether triangle `corners` (a, b, c) has the directed edge with code
// from | to << 8: its edges (a, b), (b, c), (c, a).
TV_HD bool has_edge(uint32_t corners, uint32_t code) {
  return ((corners & 0xffffu) == code) | ((corners >> 8) == code) |
         (((corners >> 16) | (corners & 0xffu) << 8) == code);
}
// The same with 16-bit ids (PlaneIds<true>): code from | to << 16.
TV_HD bool has_edge(uint64_t corners, uint64_t code) {
  return ((corners & 0xffffffffu) == code) | ((corners >> 16) == code) |
         (((corners >> 32) | (corners & 0xffffu) << 16) == code);
}

// Whether a removed region's boundary of `length` edges is one cycle without
// walking it, given that its edges leave distinct planes, enter distinct
// planes, and enter only planes they leave: then they form disjoint cycles.
// None has one edge (an edge joins two planes) or two (edges a -> b and
// b -> a of removed triangles are interior, not boundary edges), so up to 5
// edges make a single cycle. Longer boundaries are walked (a walk is a
// visible share of the warp cell's stalls).
TV_HD bool short_cycle_needs_no_walk(int length) { return length <= 5; }

// A small bit set (one bit per triangle slot, or per plane). Every word is
// addressed with a compile-time index (unrolled loops, selects): on the GPU
// the set stays in registers, where a dynamically indexed array would go to
// local memory.
template <int WORDS>
struct BitSet {
  static constexpr int kWords = WORDS;
  uint32_t word[WORDS];

  TV_HD void clear() {
    TV_UNROLL
    for (int i = 0; i < WORDS; ++i) word[i] = 0u;
  }
  TV_HD void set(int t) {
    const uint32_t bit = 1u << (t & 31);
    TV_UNROLL
    for (int i = 0; i < WORDS; ++i) word[i] |= ((t >> 5) == i) ? bit : 0u;
  }

  TV_HD uint32_t get(int w) const {  // word w, w in [0, WORDS)
    uint32_t value = word[0];
    TV_UNROLL
    for (int i = 1; i < WORDS; ++i) value = (w == i) ? word[i] : value;
    return value;
  }
  TV_HD bool test(int t) const { return (get(t >> 5) >> (t & 31)) & 1u; }
  TV_HD int count() const {
    int total = 0;
    TV_UNROLL
    for (int i = 0; i < WORDS; ++i) total += bit_count(word[i]);
    return total;
  }

  // Walks the set bits in increasing order.
  struct Cursor {
    BitSet mask;  // a copy: no pointer that could pin the mask to memory
    int w;
    uint32_t bits;  // bits of word w not visited yet
    TV_HD int next() {  // requires a set bit left
      while (bits == 0u) bits = mask.get(++w);
      const int t = 32 * w + lowest_bit(bits);
      bits &= bits - 1u;
      return t;
    }
  };
  TV_HD Cursor cursor() const { return {*this, 0, word[0]}; }
};

// Inserts `offset` (with its squared norm) into the `count` neighbours
// r[], r2[] sorted by increasing (distance, x, y, z), unless it is nearer
// than sqrt(nearest2): the cells' bounding_neighbors (an insertion sort of a
// few dozen at most).
template <typename T>
TV_HD void insert_by_distance(Vec3<T> offset, T nearest2, Vec3<T>* r, T* r2, int& count) {
  const T offset2 = squared_norm(offset);
  if (offset2 < nearest2) return;
  const auto before = [](T a2, Vec3<T> a, T b2, Vec3<T> b) {
    if (a2 < b2 || b2 < a2) return a2 < b2;
    if (a.x < b.x || b.x < a.x) return a.x < b.x;
    if (a.y < b.y || b.y < a.y) return a.y < b.y;
    return a.z < b.z;
  };
  int at = count++;
  for (; at > 0 && before(offset2, offset, r2[at - 1], r[at - 1]); --at) {
    r[at] = r[at - 1];
    r2[at] = r2[at - 1];
  }
  r[at] = offset;
  r2[at] = offset2;
}

// Where a thread cell keeps its dual triangles: one DualTriangle a slot
// (16 bytes in float32, 32 in float64), or 12 bytes (CompactTriangles).
// On the host (TORCHVOR_HOST_PACKS) the slots are columns instead: each
// coordinate of consecutive slots side by side, so that the packed loops
// (packed_vertices.h) load a pack of vertices in three vector loads.
#if defined(TORCHVOR_HOST_PACKS)
template <typename T, int N, typename Corners = uint32_t>
struct TriangleSlots {
  static constexpr bool kColumns = true;
  T x[N], y[N], z[N];
  Corners corner[N];
  Vec3<T> position(int t) const { return {x[t], y[t], z[t]}; }
  Corners corners(int t) const { return corner[t]; }
  // Stores a vertex and returns it as it reads back (here: as given).
  Vec3<T> set(int t, Vec3<T> position, Corners corners) {
    x[t] = position.x;
    y[t] = position.y;
    z[t] = position.z;
    corner[t] = corners;
    return position;
  }
  void set_corners(int t, Corners corners) { corner[t] = corners; }
  void copy(int to, int from) {
    x[to] = x[from];
    y[to] = y[from];
    z[to] = z[from];
    corner[to] = corner[from];
  }
};
#else
template <typename T, int N, typename Corners = uint32_t>
struct TriangleSlots {
  static constexpr bool kColumns = false;
  DualTriangle<T, Corners> slot[N];
  TV_HD Vec3<T> position(int t) const { return slot[t].position; }
  TV_HD Corners corners(int t) const { return slot[t].corners; }
  // Stores a vertex and returns it as it reads back (here: as given).
  TV_HD Vec3<T> set(int t, Vec3<T> position, Corners corners) {
    slot[t] = {position, corners};
    return position;
  }
  TV_HD void set_corners(int t, Corners corners) { slot[t].corners = corners; }
  TV_HD void copy(int to, int from) { slot[to] = slot[from]; }
};
#endif

// Dual triangles in 12 bytes a slot, for float32 cells of at most 32 planes:
// each coordinate is rounded to 18 mantissa bits (to nearest, ties to even)
// and its 5 low bits hold one corner's plane id.
// Why: the thread cell's speed is bound by how much cell state its threads
// keep in the L1 cache, and the triangles are most of it.
// The cost: vertices held to 2^-19 relative instead of float32's 2^-24, so
// float32 volumes differ a few times more from float64's (docs/design.md).
// Ties away from zero would push every vertex outwards (the volumes would
// sum too large). A cell in units of a power of two, which frees an
// exponent bit for a 19th mantissa bit, costs more in conversions than it
// gains (docs/performance.md).
// Reading a coordinate back is one mask; its rounding cannot make a finite
// vertex non-finite short of FLT_MAX (then it reads as Inf, and the clip
// fails as for any non-finite vertex).
template <int N>
struct CompactTriangles {
  static constexpr bool kColumns = false;
  static constexpr uint32_t kId = 31u;  // the low 5 bits
  uint32_t word[N][3];                  // x, y, z, each with one corner's plane id (a, b, c)

  TV_HD static float coordinate(uint32_t word) { return bits_float(word & ~kId); }
  TV_HD static uint32_t with_id(uint32_t word, uint32_t id) { return (word & ~kId) | id; }
  TV_HD static uint32_t rounded(float x) {
    const uint32_t bits = float_bits(x);
    return bits + (kId >> 1) + (bits >> 5 & 1u);  // the magnitude to nearest, ties to even
  }

  TV_HD Vec3<float> position(int t) const {
    return {coordinate(word[t][0]), coordinate(word[t][1]), coordinate(word[t][2])};
  }
  TV_HD uint32_t corners(int t) const {
    return (word[t][0] & kId) | (word[t][1] & kId) << 8 | (word[t][2] & kId) << 16;
  }
  TV_HD Vec3<float> set(int t, Vec3<float> position, uint32_t corners) {
    const uint32_t x = with_id(rounded(position.x), corners & kId);
    const uint32_t y = with_id(rounded(position.y), corners >> 8 & kId);
    const uint32_t z = with_id(rounded(position.z), corners >> 16 & kId);
    word[t][0] = x;
    word[t][1] = y;
    word[t][2] = z;
    return {coordinate(x), coordinate(y), coordinate(z)};
  }
  TV_HD void set_corners(int t, uint32_t corners) {
    TV_UNROLL
    for (int e = 0; e < 3; ++e) word[t][e] = with_id(word[t][e], corners >> (8 * e) & kId);
  }
  TV_HD void copy(int to, int from) {
    TV_UNROLL
    for (int e = 0; e < 3; ++e) word[to][e] = word[from][e];
  }
};

// The homogeneous coordinates of a double-double cell's vertices, by slot
// (exact_predicates.h); nothing for other cells.
template <bool kExact, int N>
struct HomogeneousSlots {
  exact::HomogeneousVertex slot[N];
};
template <int N>
struct HomogeneousSlots<false, N> {};

// What a power cell (kWeighted) keeps beside each bisector's neighbour: the
// weight difference that moves its plane (power_plane) and the neighbour's
// index (its face's target). Nothing for a Voronoi cell: an empty base.
template <typename T, int N, bool kWeighted>
struct PowerTerms {
  TV_HD void move_terms(int /*to*/, int /*from*/) {}
};
template <typename T, int N>
struct PowerTerms<T, N, true> {
  T shift[N];        // w_seed - w_j of bisector q - kBoxPlanes
  int32_t owner[N];  // j
  TV_HD void move_terms(int to, int from) {
    shift[to] = shift[from];
    owner[to] = owner[from];
  }
};

// kCompact: the triangles in CompactTriangles (float32, at most 32 planes).
// kWeighted: a power cell (clip_by_power_plane), whose planes are power
// bisectors; it may be empty (kEmpty; a float cell only where rounding
// cannot explain it, outside_beyond_rounding, else kIllConditioned).
template <typename T, int MAX_PLANES, int MAX_TRIANGLES, bool kCompact = false, bool kWeighted = false>
struct ConvexCell : PowerTerms<T, MAX_PLANES - kBoxPlanes, kWeighted> {
  using Scalar = T;
  using Lanes = SingleLane;  // one thread computes the cell
  static constexpr bool kTetrahedronStart = true;  // init_tetrahedron (start_tetrahedron)
  using Ids = PlaneIds<(MAX_PLANES > 255)>;
  using Id = typename Ids::Id;
  using Corners = typename Ids::Corners;
  static constexpr Id kNone = static_cast<Id>(-1);
  // Double-double cells (the last resort, on the host) clip by exact
  // predicates (exact_predicates.h): their clips are never inconsistent.
  static constexpr bool kExactPredicates = std::is_same<T, DoubleDouble>::value;
  static_assert(MAX_PLANES <= kNone, "plane ids must stay below kNone");
  static_assert(!kCompact || (std::is_same<T, float>::value && MAX_PLANES <= 32),
                "compact triangles hold float32 coordinates and 5-bit plane ids");
  static constexpr int kMaskWords = (MAX_TRIANGLES + 31) / 32;
  using Mask = BitSet<kMaskWords>;
  using PlaneSet = BitSet<(MAX_PLANES + 31) / 32>;

  // Planes 0-5 are the box's faces; plane q >= 6 is the bisector of the
  // seed and the neighbour at neighbor[q - 6] (relative to the seed), kept
  // as that point: 12 bytes a plane, not 16 (as DualTriangle, for the
  // cache), and rebuilt as the clip built it (bisector_plane, squared_norm:
  // bit for bit). Compaction keeps the faces' ids. The faces are written by
  // the box start only (init_tetrahedron says why).
  Plane<T> box_face[kBoxPlanes];
  Vec3<T> neighbor[MAX_PLANES - kBoxPlanes];
  typename std::conditional<kCompact, CompactTriangles<MAX_TRIANGLES>,
                            TriangleSlots<T, MAX_TRIANGLES, Corners>>::type triangle;
  int32_t num_planes;
  int32_t num_triangles;
  T radius2;         // the largest |vertex|^2: the ball around the seed holding the cell
  T tolerance;       // relative tolerance of the clipping predicate
  int8_t status;
  HomogeneousSlots<kExactPredicates, MAX_TRIANGLES> homogeneous;  // last: an empty one fills padding

  TV_HD Lanes group() const { return {}; }

  TV_HD Plane<T> plane(int q) const {
    if (q < kBoxPlanes) return box_face[q];
    const Vec3<T> r = neighbor[q - kBoxPlanes];
    if constexpr (kWeighted) return power_plane(r, squared_norm(r), this->shift[q - kBoxPlanes]);
    return bisector_plane(r, squared_norm(r));
  }

  TV_HD static Corners pack(Corners a, Corners b, Corners c) { return a | b << Ids::kBits | c << (2 * Ids::kBits); }
  TV_HD static Id corner(Corners triangle, int e) { return Id(triangle >> (Ids::kBits * e)); }
  // Corners packed a byte an id (box_triangle, StartTetrahedron) in this cell's packing.
  TV_HD static Corners from_bytes(uint32_t packed) {
    if constexpr (Ids::kBits == 8) {
      return packed;
    } else {
      return pack(packed & 0xffu, packed >> 8 & 0xffu, packed >> 16 & 0xffu);
    }
  }

  // The box [lo, hi] (relative to the seed) as 6 planes and 8 dual triangles.
  TV_HD void init_box(Vec3<T> lo, Vec3<T> hi, T relative_tolerance) {
    init_faces_and_settings(lo, hi, relative_tolerance);
    num_planes = kBoxPlanes;
    num_triangles = 8;
    radius2 = T(0);
    for (int t = 0; t < 8; ++t) {
      const Corners corners = from_bytes(box_triangle(t));
      radius2 = max_of(radius2, set_triangle(t, corner(corners, 0), corner(corners, 1), corner(corners, 2)).radius2);
    }
  }

  // The tetrahedron `start` (start_tetrahedron, strictly inside the box):
  // its four bisectors are planes 6-9. Planes 0-5, the box's faces, are left
  // unwritten: no vertex of the tetrahedron lies on them and clips add only
  // bisectors, so no triangle ever names them and plane() never reads them.
  // Their 24 words a cell would be stores to local memory that nothing reads.
  TV_HD void init_tetrahedron(const StartTetrahedron<T>& start, T relative_tolerance) {
    init_settings(relative_tolerance);
    num_planes = kBoxPlanes + 4;
    num_triangles = 4;
    radius2 = T(0);
    TV_UNROLL
    for (int t = 0; t < 4; ++t) {
      neighbor[t] = start.offset[t];
      const Vec3<T> vertex = triangle.set(t, start.vertex[t], from_bytes(start.corners[t] + 0x060606u));
      radius2 = max_of(radius2, squared_norm(vertex));
    }
#if !defined(__CUDA_ARCH__)
    if constexpr (kExactPredicates) {
      for (int t = 0; t < 4; ++t) set_homogeneous(t, triangle.corners(t));
    }
#endif
  }

  // Store triangle t = (a, b, c) and its vertex; returns the vertex.
  TV_HD CachedVertex<T> set_triangle(int t, Id a, Id b, Id c) {
    return set_triangle(t, a, b, c, plane(a), plane(b), plane(c));
  }
  // The same with the planes of a, b, c already at hand.
  TV_HD CachedVertex<T> set_triangle(int t, Id a, Id b, Id c, const Plane<T>& pa,
                                     const Plane<T>& pb, const Plane<T>& pc) {
    Vec3<T> vertex;
    if constexpr (kExactPredicates) {
      vertex = intersect_planes(pa, pb, pc, {a >= kBoxPlanes, b >= kBoxPlanes, c >= kBoxPlanes},
                                {shift_of(a), shift_of(b), shift_of(c)});
#if !defined(__CUDA_ARCH__)
      homogeneous.slot[t] = exact::homogeneous(pa, pb, pc);
#endif
    } else {
      vertex = intersect_planes(pa, pb, pc);
    }
    const Vec3<T> position = triangle.set(t, vertex, pack(a, b, c));
    return {position, squared_norm(position)};
  }

  // The cell's vertices (sweep_vertex_balls sweeps their balls), their
  // planes and the planes' count (for_each_face).
  TV_HD int vertex_count() const { return num_triangles; }
  TV_HD Vec3<T> vertex(int t) const { return triangle.position(t); }
  TV_HD bool vertex_planes(int t, int (&ids)[3]) const {
    const Corners corners = triangle.corners(t);
    for (int e = 0; e < 3; ++e) ids[e] = corner(corners, e);
    return true;
  }
  TV_HD int plane_count() const { return num_planes; }
  static constexpr int kMaxBisectors = MAX_PLANES - kBoxPlanes;
  // for_each_face's per-plane vertex lists (VerticesByPlane) for the device
  // tiers; 0: the host's largest (on the heap) scan instead.
  static constexpr int kIndexedVertices = MAX_PLANES <= 255 ? MAX_TRIANGLES : 0;
  // Whether the bisector of the neighbour at r is among the cell's planes. A
  // second clip by it is not a no-op: its own vertices, rounded, may fall
  // outside it, and the new ones would meet it twice (a NaN vertex).
  TV_HD bool has_bisector(Vec3<T> r) const {
    for (int q = kBoxPlanes; q < num_planes; ++q) {
      const Vec3<T> other = neighbor[q - kBoxPlanes];
      if (other.x == r.x && other.y == r.y && other.z == r.z) return true;
    }
    return false;
  }
  // The neighbours (relative to the seed) whose bisectors bound the cell (a
  // vertex lies on them) and that are at least sqrt(nearest2) away, with
  // their squared distances, in increasing (distance, x, y, z) order: at
  // most kMaxBisectors. Returns how many.
  TV_HD int bounding_neighbors(T nearest2, Vec3<T>* r, T* r2) const {
    PlaneSet used;
    used.clear();
    for (int t = 0; t < num_triangles; ++t) {
      const Corners corners = triangle.corners(t);
      for (int e = 0; e < 3; ++e) used.set(corner(corners, e));
    }
    int count = 0;
    for (int q = kBoxPlanes; q < num_planes; ++q) {
      if (used.test(q)) insert_by_distance(neighbor[q - kBoxPlanes], nearest2, r, r2, count);
    }
    return count;
  }

  // Whether no neighbour this far (or farther) can cut the cell.
  // The largest |vertex|^2 (compute_cell's radius).
  TV_HD T largest_radius2() const { return radius2; }
  TV_HD bool security_radius_reached(T neighbor_dist2) const {
    return beyond_security_radius(neighbor_dist2, radius2, tolerance);
  }

  // Clip by the bisector of the seed (origin) and a neighbour at `r` (paper
  // §3.3, Alg. 3). Returns false and sets `status` when the cell cannot be
  // represented (array overflow) or the predicates were inconsistent.
  TV_HD bool clip_by_bisector(Vec3<T> r) {
    static_assert(!kWeighted, "a power cell clips by power planes");
    const T r2 = squared_norm(r);
    return clip(r, r2, bisector_plane(r, r2), T(0), -1);
  }

  // A power cell's clip by the power bisector of the neighbour `owner` at r
  // (power_plane: shift = w_seed - w_owner). False with status kEmpty when
  // the plane removes every vertex.
  TV_HD bool clip_by_power_plane(Vec3<T> r, T shift, int32_t owner) {
    static_assert(kWeighted, "a Voronoi cell clips by bisectors");
    const T r2 = squared_norm(r);
    return clip(r, r2, power_plane(r, r2, shift), shift, owner);
  }
  // The power shift of plane q (power_plane; 0 for a box face or a Voronoi cell).
  TV_HD T shift_of(int q) const {
    if constexpr (kWeighted) {
      if (q >= kBoxPlanes) return this->shift[q - kBoxPlanes];
    }
    return T(0);
  }
  // The squared length on whose scale rounding moves power cell vertex t
  // (CellMoments::add_vertex): its distance from the seed (the clip's
  // coordinates), or a power plane's (|r|^2 + |shift|) / (2 |r|), the scale
  // its offset is rounded on, where that is larger (a large shift).
  TV_HD T rounding_radius2(int t) const {
    const Corners corners = triangle.corners(t);
    T largest = squared_norm(triangle.position(t));
    for (int e = 0; e < 3; ++e) {
      const int q = corner(corners, e);
      if (q < kBoxPlanes) continue;
      const T r2 = squared_norm(neighbor[q - kBoxPlanes]);
      const T shift = shift_of(q);
      const T span = r2 + (shift < T(0) ? -shift : shift);
      largest = max_of(largest, span * span / (T(4) * r2));
    }
    return largest;
  }
  // Whether every vertex lies outside plane p by more than `band` and more
  // than rounding can have moved it (2^-14 rounding_radius2's length over
  // the sine of its planes, well above a float vertex's error), so that the
  // exact cell lies outside it too: a float cell's EMPTY verdict.
  TV_HD bool outside_beyond_rounding(const Plane<T>& p, T band) const {
    const T norm = sqrt_of(dot(p.normal, p.normal));
    for (int t = 0; t < num_triangles; ++t) {
      const Corners corners = triangle.corners(t);
      const Plane<T> planes[3] = {plane(corner(corners, 0)), plane(corner(corners, 1)), plane(corner(corners, 2))};
      const T det = dot(cross(planes[0].normal, planes[1].normal), planes[2].normal);
      const T norms = sqrt_of(dot(planes[0].normal, planes[0].normal) * dot(planes[1].normal, planes[1].normal) *
                              dot(planes[2].normal, planes[2].normal));
      const T moved = T(1.0 / 16384.0) * sqrt_of(rounding_radius2(t)) * norms;  // times sine: the vertex's reach
      const T value = dot(p.normal, triangle.position(t)) + p.offset;
      const T det_abs = det < T(0) ? -det : det;
      if (!(value < -band) || !(-value * det_abs > norm * moved)) return false;
    }
    return true;
  }
  // A power cell's neighbour across plane q >= kBoxPlanes.
  TV_HD int32_t owner_of(int q) const {
    if constexpr (kWeighted) return this->owner[q - kBoxPlanes];
    return -1;
  }

  // Volume, first moment and second moment (integral of |x|^2) of the cell,
  // all relative to the seed, and the cancellation measure (CellMoments).
  // A power cell integrates about the mean of its vertices (a point of the
  // cell), not about its seed, which may lie far outside it: tetrahedra from
  // there would cancel.
  TV_HD void integrate(T& volume, Vec3<T>& first_moment, T& second_moment,
                       CellRounding<T>& rounding) const {
    Vec3<T> origin = {T(0), T(0), T(0)};
    if constexpr (kWeighted) {
      for (int t = 0; t < num_triangles; ++t) origin = origin + triangle.position(t);
      origin = (T(1) / T(num_triangles > 0 ? num_triangles : 1)) * origin;
    }
    CellMoments<T, kWeighted> moments = CellMoments<T, kWeighted>::zero();
#if defined(TORCHVOR_HOST_PACKS)
    if constexpr (packs_vertices<T>()) {
      moments = add_vertices_packed<kWeighted>(*this, origin);
    } else
#endif
    {
      for (int t = 0; t < num_triangles; ++t) {
        const Corners corners = triangle.corners(t);
        Vec3<T> position = triangle.position(t);
        Plane<T> planes[3] = {plane(corner(corners, 0)), plane(corner(corners, 1)), plane(corner(corners, 2))};
        T rounding2 = T(0);  // the rounding weights' scale (rounding_radius2), where they are kept
        if constexpr (kWeighted) {
          if constexpr (CellMoments<T, kWeighted>::kConditioned) rounding2 = rounding_radius2(t);
          position = position - origin;
          for (int e = 0; e < 3; ++e) planes[e].offset += dot(planes[e].normal, origin);
        }
        const T radius2_here = squared_norm(position);
        moments.add_vertex(planes, {position, radius2_here}, kWeighted ? rounding2 : radius2_here);
      }
    }
    moments.finish(volume, first_moment, second_moment, rounding);
    if constexpr (kWeighted) {  // back to moments about the seed
      second_moment += T(2) * dot(origin, first_moment) + volume * squared_norm(origin);
      first_moment = first_moment + volume * origin;
    }
  }

 private:
  // The clip by plane p, the bisector (power bisector) of the neighbour at r
  // (r2 = |r|^2; shift and owner are kept by power cells).
  TV_HD bool clip(Vec3<T> r, T r2, const Plane<T>& p, T shift, int32_t owner) {
    if constexpr (!kWeighted) {
      (void)shift;
      (void)owner;
    }
    // Vertices within the tolerance band of the plane are kept. If the removed
    // region is then not a disc (inconsistent predicates: vertices of nearly
    // parallel planes, computed with errors beyond the band), fail: a later
    // pass retries in wider arithmetic, and the last, double-double, decides
    // by exact predicates, which are never inconsistent.
    Mask clipped;
    T kept_radius2;  // the largest |vertex|^2 of the vertices the plane keeps
    Id next[MAX_PLANES];
    PlaneSet on_boundary;
    int boundary_length = 0;
    Id start = kNone;
    if (far_beside_bisector(r2, radius2)) {
      for (int t = 0; t < num_triangles; ++t) {
        if (rounding_could_cut(dot(p.normal, triangle.position(t)) + p.offset, r2 * radius2)) {
          return fail(kIllConditioned);
        }
      }
    }
    if (!classify(p, shift, -tolerance * r2, clipped, kept_radius2)) return true;  // the plane misses the cell
    if constexpr (kWeighted) {
      if (clipped.count() == num_triangles) {
        bool empty = true;
        if constexpr (std::is_same<T, float>::value) empty = outside_beyond_rounding(p, tolerance * r2);
        num_triangles = 0;
        radius2 = T(0);
        return fail(empty ? kEmpty : kIllConditioned);  // a float sliver that rounding removed whole: to float64
      }
    }
    if (num_planes == MAX_PLANES) compact_planes();
    if (num_planes == MAX_PLANES) return fail(kTooManyPlanes);
    if (!removed_boundary(clipped, next, on_boundary, boundary_length, start)) return fail(kBoundaryError);
    const int removed = clipped.count();
    if (num_triangles - removed + boundary_length > MAX_TRIANGLES) return fail(kTooManyVertices);
    const int new_plane = num_planes++;
    neighbor[new_plane - kBoxPlanes] = r;
    if constexpr (kWeighted) {
      this->shift[new_plane - kBoxPlanes] = shift;
      this->owner[new_plane - kBoxPlanes] = owner;
    }
    // Close the hole with a fan of triangles (s, t, p) along the boundary
    // cycle, written into the removed triangles' slots first and appended
    // after the last one beyond that: no kept triangle moves. The order of
    // triangles carries no meaning (the integrals are sums over them).
    // The radius stays exact: the kept vertices' and the new ones'. Each
    // boundary plane is loaded once (it is `to` of one new vertex and `from`
    // of the next), and the new plane comes from registers. On the GPU a
    // plane load is a scattered local access (local memory interleaves the
    // threads' 4-byte words, so one thread's plane spans up to three
    // sectors), so loading each plane once cuts the fan's L1 traffic.
    typename Mask::Cursor holes = clipped.cursor();
    Id from = start;
    Plane<T> from_plane = plane(from);
    T largest = kept_radius2;
    bool misplaced = false;  // a new vertex beyond the cell it cuts (beyond_the_cell)
    for (int e = 0; e < boundary_length; ++e) {
      const Id to = next[from];
      const Plane<T> to_plane = plane(to);
      const int slot = e < removed ? holes.next() : num_triangles++;
      const T v2 = set_triangle(slot, from, to, static_cast<Id>(new_plane), from_plane, to_plane, p).radius2;
      if (!is_finite_value(v2)) return fail(kBoundaryError);  // degenerate: NaN or Inf vertex
      misplaced = misplaced || beyond_the_cell(v2, radius2);
      largest = max_of(largest, v2);
      from = to;
      from_plane = to_plane;
    }
    if (misplaced) return fail(kIllConditioned);
    if (boundary_length < removed) fill_holes(holes, removed - boundary_length, clipped);
    radius2 = largest;
    return true;
  }

  TV_HD bool fail(int8_t code) {
    status = code;
    return false;
  }

  // What the box start sets: the box's faces (planes 0-5) and the settings.
  TV_HD void init_faces_and_settings(Vec3<T> lo, Vec3<T> hi, T relative_tolerance) {
    for (int q = 0; q < kBoxPlanes; ++q) box_face[q] = box_plane(q, lo, hi);
    init_settings(relative_tolerance);
  }
  // What every start sets.
  TV_HD void init_settings(T relative_tolerance) {
    tolerance = relative_tolerance;
    status = kSuccess;
  }

  // Marks the vertices more than `threshold` (< 0) outside plane p; returns
  // whether any is, and the largest |vertex|^2 of the others (the radius
  // after the clip, the new vertices aside, with no second pass over the
  // vertices). Independent iterations: several vertex loads in flight at
  // once (the GPU kernel is bound by local-memory latency); the mask words
  // are built in registers.
  // `shift`: p's power shift (the exact predicates' offset).
  TV_HD bool classify(const Plane<T>& p, T shift, T threshold, Mask& clipped, T& kept_radius2) const {
    if constexpr (kExactPredicates) {
#if !defined(__CUDA_ARCH__)
      return classify_exactly(p, shift, clipped, kept_radius2);
#endif
    }
#if defined(TORCHVOR_HOST_PACKS)
    if constexpr (packs_vertices<T>()) return classify_packed(*this, p, threshold, clipped, kept_radius2);
#endif
    uint32_t any_clipped = 0u;
    kept_radius2 = T(0);
    TV_UNROLL
    for (int w = 0; w < kMaskWords; ++w) {
      uint32_t bits = 0u;
      const int end = min_of(num_triangles - 32 * w, 32);
      for (int i = 0; i < end; ++i) {
        const Vec3<T> v = triangle.position(32 * w + i);
        const bool outside = dot(p.normal, v) + p.offset < threshold;
        bits |= uint32_t(outside) << i;
        kept_radius2 = outside ? kept_radius2 : max_of(kept_radius2, squared_norm(v));
      }
      clipped.word[w] = bits;
      any_clipped |= bits;
    }
    return any_clipped != 0u;
  }

#if !defined(__CUDA_ARCH__)
  void set_homogeneous(int t, Corners corners) {
    homogeneous.slot[t] = exact::homogeneous(plane(corner(corners, 0)), plane(corner(corners, 1)),
                                             plane(corner(corners, 2)));
  }

  // classify for a bisector p by the exact sign of each vertex (no band).
  // Whether the filter (exact::filtered_side) holds for plane q, whose error
  // bounds take its double-double offset within a few roundings of its
  // magnitude: true of box faces and bisectors, and of power bisectors
  // whose shift cancels less than half of |r|^2 + |shift| (offset (|r|^2 +
  // shift) / 2, rounded on that scale).
  bool filter_holds(int q) const { return q < kBoxPlanes || filter_holds(plane(q), shift_of(q)); }
  static bool filter_holds(const Plane<T>& p, T shift) {
    if constexpr (!kWeighted) return true;
    const double r2 = static_cast<double>(squared_norm(p.normal)), twice = 2.0 * static_cast<double>(p.offset);
    const double s = static_cast<double>(shift);
    return (twice < 0.0 ? -twice : twice) >= 0.5 * (r2 + (s < 0.0 ? -s : s));
  }

  // Power planes whose shift cancels their offset (filter_holds) skip the
  // filter.
  bool classify_exactly(const Plane<T>& p, T shift, Mask& clipped, T& kept_radius2) const {
    const bool filter_plane = filter_holds(p, shift);
    uint32_t any_clipped = 0u;
    kept_radius2 = T(0);
    for (int w = 0; w < kMaskWords; ++w) {
      uint32_t bits = 0u;
      const int end = min_of(num_triangles - 32 * w, 32);
      for (int i = 0; i < end; ++i) {
        const int t = 32 * w + i;
        const Corners corners = triangle.corners(t);
        const Id a = corner(corners, 0), b = corner(corners, 1), c = corner(corners, 2);
        const bool filter = filter_plane && (!kWeighted || (filter_holds(a) && filter_holds(b) && filter_holds(c)));
        int side = filter ? exact::filtered_side(homogeneous.slot[t], p) : 2;
        if (side == 2) {  // undecided: expand the vertex's planes exactly
          const Plane<T> planes[3] = {plane(a), plane(b), plane(c)};
          const Plane<T>* const rows[4] = {&planes[0], &planes[1], &planes[2], &p};
          side = exact::exact_side(rows, {a >= kBoxPlanes, b >= kBoxPlanes, c >= kBoxPlanes, true},
                                   {shift_of(a), shift_of(b), shift_of(c), shift});
        }
        const bool outside = side < 0;
        bits |= uint32_t(outside) << i;
        if (!outside) kept_radius2 = max_of(kept_radius2, squared_norm(triangle.position(t)));
      }
      clipped.word[w] = bits;
      any_clipped |= bits;
    }
    return any_clipped != 0u;
  }
#endif

  // Fewer new triangles than removed ones: move kept triangles from the end
  // into the `count` holes left, lowest hole first, and shorten the list.
  TV_HD void fill_holes(typename Mask::Cursor& holes, int count, const Mask& clipped) {
    int last = num_triangles - 1;  // the highest slot that may still hold a kept triangle
    for (; count > 0; --count) {
      const int hole = holes.next();
      while (last > hole && clipped.test(last)) --last;  // drop holes at the end
      if (last <= hole) {  // nothing kept above this hole: the list ends before it
        last = min_of(last, hole - 1);
        break;
      }
      triangle.copy(hole, last);
      if constexpr (kExactPredicates) homogeneous.slot[hole] = homogeneous.slot[last];
      --last;
    }
    num_triangles = last + 1;
  }

  // Boundary of the removed region R (Alg. 4): the directed edges of R whose
  // reverse is not in R, as a successor map over plane ids (next[x] is valid
  // where `on_boundary` has x). False if the boundary is not one simple
  // cycle (short_cycle_needs_no_walk, cycle_length). The removed triangles
  // are gathered first, so that the search for reverse edges is a short
  // branch-free loop of the same length in every lane.
  TV_HD bool removed_boundary(const Mask& clipped, Id* next, PlaneSet& on_boundary,
                              int& length, Id& start) const {
    Corners removed[MAX_TRIANGLES];
    int count = 0;
    for (int w = 0; w < kMaskWords; ++w) {
      for (uint32_t bits = clipped.get(w); bits != 0u; bits &= bits - 1u)
        removed[count++] = triangle.corners(32 * w + lowest_bit(bits));
    }
    on_boundary.clear();
    PlaneSet targets;  // the planes boundary edges go to
    targets.clear();
    length = 0;
    start = kNone;
    for (int i = 0; i < count; ++i) {
      const Corners corners = removed[i];
      // Bit e: edge e's reverse is in a removed triangle (the edge is
      // interior). One pass over the removed triangles tests all three
      // edges, one load each (cheaper than a pass per edge).
      Corners reverse[3];
      TV_UNROLL
      for (int e = 0; e < 3; ++e) {
        reverse[e] = Corners(corner(corners, (e + 1) % 3)) | Corners(corner(corners, e)) << Ids::kBits;
      }
      uint32_t interior = 0u;
      for (int j = 0; j < count; ++j) {
        const Corners other = removed[j];
        TV_UNROLL
        for (int e = 0; e < 3; ++e) interior |= uint32_t(has_edge(other, reverse[e])) << e;
      }
      for (int e = 0; e < 3; ++e) {
        if ((interior >> e) & 1u) continue;
        const Id from = corner(corners, e), to = corner(corners, (e + 1) % 3);
        // A plane twice on the boundary: not a simple cycle.
        if (on_boundary.test(from) || targets.test(to)) return false;
        on_boundary.set(from);
        targets.set(to);
        next[from] = to;
        start = from;
        ++length;
      }
    }
    if (length < 3) return false;
    TV_UNROLL
    for (int w = 0; w < PlaneSet::kWords; ++w) {
      if (targets.word[w] != on_boundary.word[w]) return false;  // an edge leads off the boundary
    }
    return short_cycle_needs_no_walk(length) || cycle_length(next, on_boundary, start) == length;
  }

  // Edges on the way from `start` back to itself; stops early at a dead end.
  TV_HD static int cycle_length(const Id* next, const PlaneSet& on_boundary, Id start) {
    int length = 0;
    Id from = start;
    do {
      from = next[from];
      ++length;
    } while (from != start && on_boundary.test(from) && length <= MAX_PLANES);
    return from == start ? length : -1;
  }

  // Drop planes that no vertex uses any more and renumber the rest, so that a
  // long clipping sequence does not overflow the plane array with dead planes.
  TV_HD void compact_planes() {
    Id renumber[MAX_PLANES];
    for (int q = 0; q < num_planes; ++q) renumber[q] = kNone;
    for (int t = 0; t < num_triangles; ++t) {
      const Corners corners = triangle.corners(t);
      for (int e = 0; e < 3; ++e) renumber[corner(corners, e)] = 0;
    }
    for (int q = 0; q < kBoxPlanes; ++q) renumber[q] = static_cast<Id>(q);
    int live = kBoxPlanes;
    for (int q = kBoxPlanes; q < num_planes; ++q) {
      if (renumber[q] == kNone) continue;
      neighbor[live - kBoxPlanes] = neighbor[q - kBoxPlanes];
      this->move_terms(live - kBoxPlanes, q - kBoxPlanes);
      renumber[q] = static_cast<Id>(live++);
    }
    for (int t = 0; t < num_triangles; ++t) {
      const Corners corners = triangle.corners(t);
      triangle.set_corners(t, pack(renumber[corner(corners, 0)], renumber[corner(corners, 1)],
                                   renumber[corner(corners, 2)]));
    }
    num_planes = live;
  }
};

}  // namespace core
}  // namespace torchvor
