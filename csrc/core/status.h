// Per-cell outcome codes (paper §3.4, plus the ones torchvor adds).
// Mirrored by torchvor.CellStatus in Python; keep the two in sync.
#pragma once

#include <cstdint>

namespace torchvor {
namespace core {

enum CellStatus : int8_t {
  kNotComputed = -1,               // never written (poison value)
  kSuccess = 0,                    // the exact Voronoi cell (clipped to the box)
  kSecurityRadiusNotReached = 1,   // ran out of neighbours before the radius of security
  kTooManyPlanes = 2,              // the plane array overflowed
  kTooManyVertices = 3,            // the triangle (vertex) array overflowed
  kBoundaryError = 4,              // inconsistent predicates: removed region not a disc
  kDuplicate = 5,                  // exact copy of a lower-index point: empty cell
  kIllConditioned = 6,             // integrals cancel beyond what the arithmetic resolves
  kEmpty = 7,                      // a power cell that no point of space is nearest to (power_cell.h)
};

}  // namespace core
}  // namespace torchvor
