// Runs a functor over [0, n) on all CPU threads (ATen's OpenMP pool).
#pragma once

#include <ATen/Parallel.h>

#include <vector>

#include "../core/common.h"

namespace torchvor {
namespace cpu {

struct CpuExec {
  // A cell reads its neighbour list in one cache line or two: row-major.
  static constexpr bool kColumnMajorNeighbors = false;

  // Small grains: the work per index varies a lot (cells near the box,
  // recovery passes), and the grid-ordered indices keep locality anyway.
  static constexpr int64_t kGrain = 64;

  template <typename Functor>
  static void for_each(int64_t n, const Functor& functor) {
    at::parallel_for(0, n, kGrain, [&](int64_t begin, int64_t end) {
      for (int64_t i = begin; i < end; ++i) functor(i);
    });
  }

  // functor(i, scratch): scratch is `slots` Slots of working memory for item
  // i, reused by the next item of the same thread.
  template <typename Slot, typename Functor>
  static void for_each_with_scratch(int64_t n, int64_t slots, const Functor& functor) {
    at::parallel_for(0, n, kGrain, [&](int64_t begin, int64_t end) {
      std::vector<Slot> scratch(static_cast<size_t>(slots));
      const core::StridedArray<Slot> view{scratch.data(), 1};
      for (int64_t i = begin; i < end; ++i) functor(i, view);
    });
  }
};

}  // namespace cpu
}  // namespace torchvor
