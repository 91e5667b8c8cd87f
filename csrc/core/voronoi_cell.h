// One Voronoi cell from its sorted neighbour list (paper §3, Alg. 2).
#pragma once

#include <type_traits>

#include "convex_cell.h"
#include "cooperative_cell.h"
#include "vertex_balls.h"

namespace torchvor {
namespace core {

// The cancellation a cell's integrals may have (sum of the absolute volumes
// of its tetrahedra over its volume) when computed in T for outputs of type
// io_t. The relative rounding error of the volume is about the ratio times
// the vertices' unit roundoff: 2^-18 in a float thread cell's compact
// triangles (a cell at 31 came out 1.26e-4 off), so the float limit holds it
// near 6e-5, and 1e-12 for float64. White noise, perturbed grids and blue
// noise stay below 8; needle cells of tight clusters reach 1e9 and are
// recomputed in wider arithmetic. 0: no limit (double-double, the last resort).
// The same limit holds the second moment's cancellation (its tetrahedra's
// absolute second moments over it), which far feet make the larger in slab
// cells on a box wall.
template <typename io_t, typename T> struct CancellationLimit { static constexpr double value = 0.0; };
template <> struct CancellationLimit<float, float> { static constexpr double value = 16.0; };
template <> struct CancellationLimit<float, double> { static constexpr double value = 1e9; };
template <> struct CancellationLimit<double, double> { static constexpr double value = 1e4; };

// The same for the tetrahedra weighted by how far rounding moves their
// vertices (CellRounding::conditioned_volume: 1 / sine of the vertex's planes
// times |v| / h): nearly parallel planes, or a needle or slab cell hundreds of
// times longer than wide, whose float vertices are off by eps times the
// long side. Float cells over the limit are recomputed in double. Set where
// float32 cells of the fuzzer's inputs first exceed 1e-4 relative volume
// error against float64 (docs/design.md); white noise and perturbed grids
// stay below ~320.
template <typename io_t, typename T> struct ConditionLimit { static constexpr double value = 0.0; };
template <> struct ConditionLimit<float, float> { static constexpr double value = 700.0; };
// Float64 cells over 1e6 go to double-double: a needle 2e4 times longer than
// wide, of an anisotropic lattice, came out 1.2e-9 off in float64.
template <> struct ConditionLimit<double, double> { static constexpr double value = 1e6; };

// Whether a cell type is clipped by its list alone, never finished on the
// grid (Cell::kListOnly; UnboundedCell, whose list is its whole cloud).
template <typename Cell, typename = void>
struct ListOnly : std::false_type {};
template <typename Cell>
struct ListOnly<Cell, std::void_t<decltype(Cell::kListOnly)>> : std::integral_constant<bool, Cell::kListOnly> {};

template <typename T>
struct CellIntegrals {
  T volume;
  Vec3<T> centroid;    // absolute coordinates
  T second_moment;     // integral over the cell of |x - seed|^2
  int8_t status;
  int32_t neighbors;   // neighbours consumed before the radius of security
  float radius;        // the cell's largest distance from the seed to a vertex, rounded up (radius_bound)
};

// sqrt(radius2) as a float no smaller than it (NaN stays NaN): the ball
// around the seed that holds the cell, a bound callers can certify with.
template <typename T>
TV_HD float radius_bound(T radius2) {
  const double square = static_cast<double>(radius2);
  if (!(square >= 0.0)) return NAN;
  const double radius = sqrt_of(square);
  float bound = static_cast<float>(radius);
  if (static_cast<double>(bound) < radius) bound = nextafterf(bound, INFINITY);
  return bound;
}

// A cell's neighbours as its lanes read them: lane l reads neighbour base + l
// (the index, then the coordinates), and step n takes neighbour n from lane
// n % kCount. A warp so has 32 neighbours' two dependent loads in flight at
// once, where one at a time they stall it. A single lane reads each neighbour at
// its step, as before.
template <typename Lanes, typename io_t, typename T>
struct NeighborReader {
  Lanes lanes;
  const io_t* points;
  const int32_t* neighbors;  // the n-th at neighbors[n * stride]
  int64_t stride;
  int32_t k;
  Vec3<T> seed;
  int32_t own_index = -1;  // this lane's neighbour (-1: none, or past k)
  Vec3<T> own_offset = {T(0), T(0), T(0)};

  // Neighbour n's index and its offset from the seed, in every lane; steps
  // go up from n = 0, one at a time.
  TV_HD void read(int32_t n, int32_t& index, Vec3<T>& offset) {
    const int source = n % Lanes::kCount;
    if (source == 0) fetch(n);
    index = lanes.broadcast(own_index, source);
    offset = {lanes.broadcast(own_offset.x, source), lanes.broadcast(own_offset.y, source),
              lanes.broadcast(own_offset.z, source)};
  }

 private:
  TV_HD void fetch(int32_t base) {
    const int32_t n = base + lanes.index();
    own_index = n < k ? neighbors[n * stride] : -1;
    if (own_index >= 0) {
      own_offset = {T(points[3 * own_index]) - seed.x, T(points[3 * own_index + 1]) - seed.y,
                    T(points[3 * own_index + 2]) - seed.z};
    }
  }
};

// The outputs of a clipped cell (out.status as the clip left it): NaN for a
// failure, else its integrals, unless they are not finite or cancel beyond
// what T resolves for outputs of io_t (then kBoundaryError or
// kIllConditioned, NaN outputs: never a silent success; the caller retries
// in wider arithmetic). The centroid of an empty (zero-volume) cell is its seed.
template <typename io_t, typename Cell, typename T>
TV_HD void integrate_cell(Cell& cell, Vec3<T> seed, CellIntegrals<T>& out) {
  out.radius = radius_bound(cell.largest_radius2());
  const T nan = T(0) / T(0);
  if (out.status != kSuccess) {
    out.radius = float(nan);
    out.volume = nan;
    out.centroid = {nan, nan, nan};
    out.second_moment = nan;
    return;
  }
  Vec3<T> first_moment;
  CellRounding<T> rounding;
  cell.integrate(out.volume, first_moment, out.second_moment, rounding);
  const T sum = out.volume + out.second_moment + first_moment.x + first_moment.y + first_moment.z;
  constexpr double limit = CancellationLimit<io_t, T>::value;
  constexpr double condition_limit = ConditionLimit<io_t, T>::value;
  bool ill_conditioned = false;  // NaN measures count as over the limits
  if constexpr (limit > 0.0) {
    ill_conditioned = !(rounding.unsigned_volume <= T(limit) * out.volume) ||
                      !(rounding.unsigned_second_moment <= T(limit) * out.second_moment);
  }
  if constexpr (condition_limit > 0.0) {
    ill_conditioned = ill_conditioned || !(rounding.conditioned_volume <= T(condition_limit) * out.volume);
  }
  if (!is_finite_value(sum) || ill_conditioned) {
    out.status = is_finite_value(sum) ? kIllConditioned : kBoundaryError;
    out.radius = float(nan);
    out.volume = nan;
    out.centroid = {nan, nan, nan};
    out.second_moment = nan;
    return;
  }
  out.centroid = out.volume > T(0) ? seed + (T(1) / out.volume) * first_moment : seed;
}

// `neighbors` lists k indices (the n-th at neighbors[n * stride]) sorted by
// distance to the seed, padded with -1 when the batch element has fewer points. Coordinates are read as io_t
// and computed in T (T may be wider, for the float64 recovery pass).
// `Cell` is a ConvexCell (one thread) or a CooperativeCell (a group of lanes,
// each of which runs this function with the same arguments).
// With `vertex_balls`, a cell whose list runs out
// before the radius of security is finished by the empty-ball test of its
// vertices on that grid (finish_by_vertex_balls) instead of failing; its
// `neighbors` then counts the list and the further neighbours that bound it.
template <typename Cell, typename io_t, typename T = typename Cell::Scalar>
TV_HD CellIntegrals<T> compute_cell(Cell& cell, const io_t* points, int32_t seed_index,
                                    const int32_t* neighbors, int64_t stride, int32_t k,
                                    const io_t* box, T relative_tolerance,
                                    bool tetrahedron_start = true,
                                    const VertexBallGrid<io_t>* vertex_balls = nullptr) {
  const Vec3<T> seed = {T(points[3 * seed_index]), T(points[3 * seed_index + 1]),
                        T(points[3 * seed_index + 2])};
  const Vec3<T> lo = {T(box[0]), T(box[1]), T(box[2])};
  const Vec3<T> hi = {T(box[3]), T(box[4]), T(box[5])};
  NeighborReader<typename Cell::Lanes, io_t, T> reader{cell.group(), points, neighbors, stride, k, seed};
  CellIntegrals<T> out;
  T listed_dist2 = T(0);  // the last listed neighbour's
  // The first cell and the clips by the list, until the radius of security
  // or the list's end (out.status, out.neighbors). A lambda: the cells that
  // are finished on the grid run it again (finish_by_vertex_balls).
  const auto start_and_clip_list = [&]() {
    // The first cell: the tetrahedron of four of the first neighbours where
    // they surround the seed inside the box, else the box (start_choice,
    // start_tetrahedron). A cell type without kTetrahedronStart, or
    // `tetrahedron_start` false, always starts from the box. Neither a missing
    // neighbour nor a duplicate of the seed may be among the four. The chosen
    // ones are read again rather than kept: the registers hold only their
    // directions meanwhile.
    uint32_t used_by_start = 0u;  // bit n: neighbour n bounds the start tetrahedron
    if constexpr (Cell::kTetrahedronStart) {
      using S = typename ChoiceScalar<T>::type;
      StartChoice choice;
      choice.found = false;
      if (tetrahedron_start && k >= kStartCandidates) {
        Vec3<S> unit[kStartCandidates];
        bool usable = true;
        TV_UNROLL
        for (int n = 0; n < kStartCandidates; ++n) {
          int32_t j;
          Vec3<T> r;
          reader.read(n, j, r);
          const Vec3<S> direction = {S(r.x), S(r.y), S(r.z)};
          const S length2 = squared_norm(direction);
          usable = usable && j >= 0 && length2 > S(0);
          const S inverse_length = S(1) / sqrt_of(length2);
          unit[n] = {direction.x * inverse_length, direction.y * inverse_length, direction.z * inverse_length};
        }
        if (usable) choice = start_choice(unit);
      }
      if (choice.found) {
        Vec3<T> offset[4];
        int32_t j;
        reader.read(0, j, offset[0]);
        reader.read(choice.b, j, offset[1]);
        reader.read(choice.c, j, offset[2]);
        reader.read(choice.d, j, offset[3]);
        const StartTetrahedron<T> start = start_tetrahedron(offset, choice.positive, lo - seed, hi - seed);
        if (start.found) {
          cell.init_tetrahedron(start, relative_tolerance);
          used_by_start = choice.used();
        }
      }
    }
    if (used_by_start == 0u) cell.init_box(lo - seed, hi - seed, relative_tolerance);

    out.status = kSecurityRadiusNotReached;  // unless the loop below proves otherwise
    out.neighbors = k;
    Vec3<T> previous = {T(0), T(0), T(0)};
    for (int32_t n = 0; n < k; ++n) {
      int32_t j;
      Vec3<T> r;  // the neighbour relative to the seed
      reader.read(n, j, r);
      if (j < 0) {  // every point of the batch element has been used
        out.status = kSuccess;
        out.neighbors = n;
        break;
      }
      const T r2 = dot(r, r);
      listed_dist2 = r2;
      if (r2 == T(0)) {
        // Exact duplicate: the lowest index keeps the cell, the others are empty.
        if (j < seed_index) {
          out.status = kDuplicate;
          out.neighbors = n + 1;
          break;
        }
        continue;
      }
      // Exact copies among the neighbours (sorted, so adjacent) give the same
      // bisector twice: clip once.
      if (n > 0 && r.x == previous.x && r.y == previous.y && r.z == previous.z) continue;
      const Vec3<T> before = previous;
      previous = r;
      if (cell.security_radius_reached(r2)) {
        out.status = kSuccess;
        out.neighbors = n;
        break;
      }
      if (nearly_coincident_bisectors(before, r, r2, cell.largest_radius2())) {
        out.status = kIllConditioned;
        out.neighbors = n + 1;
        break;
      }
      // A neighbour of the start tetrahedron has clipped the cell already.
      if (n < kStartCandidates && ((used_by_start >> n) & 1u) != 0u) continue;
      if (!cell.clip_by_bisector(r)) {
        out.status = cell.status;
        out.neighbors = n + 1;
        break;
      }
    }
  };
  start_and_clip_list();

  if constexpr (!ListOnly<Cell>::value) {
    if (vertex_balls != nullptr && out.status == kSecurityRadiusNotReached) {
      int32_t further = 0;
      out.status = finish_by_vertex_balls(cell, *vertex_balls, seed_index, seed, listed_dist2,
                                          start_and_clip_list, further);
      out.neighbors = k + further;
    }
  }
  // One exit from the loop above (no early return inside it): on the GPU the
  // lanes of a warp meet again here and integrate together, instead of each
  // lane integrating as soon as its own loop ends while the others clip.
  if (out.status == kDuplicate) {
    out.radius = 0.0f;
    out.volume = T(0);
    out.centroid = seed;
    out.second_moment = T(0);
    return out;
  }
  integrate_cell<io_t>(cell, seed, out);
  return out;
}

}  // namespace core
}  // namespace torchvor
