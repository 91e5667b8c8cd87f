// Work whose size only the device knows when the host launches it: the
// speculative retry pass of voronoi (ops/voronoi.h) runs on the cells that
// the status scan before it listed, without the host reading how many there
// are. The executors (cpu/exec.h, cuda/exec.cuh) launch such a functor over
// its list's capacity; items_to_run() lets a loop that claims its items
// stop at the valid ones.
#pragma once

#include <cstdint>
#include <utility>

#include "common.h"

namespace torchvor {
namespace core {

// The items of a list of which `*count` entries are valid, the count
// written by a kernel earlier on the same stream; a launch covers the list's
// `capacity` slots. When the count exceeds them the list is incomplete, and
// no item runs at all (so that which cells a pass computes never depends on
// the order in which the scan appended them).
struct DeviceCount {
  const int32_t* count = nullptr;
  int64_t capacity = 0;

  // The number of valid items, or 0 when they overflowed the capacity.
  TV_HD int64_t live() const {
    const int64_t valid = *count;
    return valid <= capacity ? valid : 0;
  }
  TV_HD bool runs(int64_t t) const { return t < live(); }
};

// `functor(t, ...)` for the launched items t that `live` says are valid.
// A type of its own: the kernels of the passes whose size the host knows
// are not touched (a warp of a cooperative kernel tests one item; the
// test is uniform across its lanes).
template <typename Functor>
struct UpToDeviceCount {
  Functor functor;
  DeviceCount live;

  template <typename... Args>
  TV_HD void operator()(int64_t t, Args&&... args) const {
    if (live.runs(t)) functor(t, std::forward<Args>(args)...);
  }
};

template <typename Functor>
UpToDeviceCount<Functor> up_to_device_count(const Functor& functor, const DeviceCount& live) {
  return {functor, live};
}

// How many of the `launched` items of `functor` can run: all of them, or
// for UpToDeviceCount the valid ones (read once by a loop that claims items
// one at a time, so that it does not claim the empty slots too).
template <typename Functor>
TV_HD int64_t items_to_run(const Functor& /*functor*/, int64_t launched) {
  return launched;
}
template <typename Functor>
TV_HD int64_t items_to_run(const UpToDeviceCount<Functor>& functor, int64_t launched) {
  const int64_t live = functor.live.live();
  return live < launched ? live : launched;
}

}  // namespace core
}  // namespace torchvor
