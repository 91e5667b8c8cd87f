// Runs a functor over [0, n) on all CPU threads (ATen's OpenMP pool).
#pragma once

#include <ATen/Parallel.h>

namespace torchvor {
namespace cpu {

struct CpuExec {
  // A cell reads its neighbour list in one cache line or two: row-major.
  static constexpr bool kColumnMajorNeighbors = false;

  template <typename Functor>
  static void for_each(int64_t n, const Functor& functor) {
    // Small grains: the work per index varies a lot (cells near the box,
    // recovery passes), and the grid-ordered indices keep locality anyway.
    at::parallel_for(0, n, 64, [&](int64_t begin, int64_t end) {
      for (int64_t i = begin; i < end; ++i) functor(i);
    });
  }
};

}  // namespace cpu
}  // namespace torchvor
