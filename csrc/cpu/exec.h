// Runs a functor over [0, n) on all CPU threads (ATen's OpenMP pool).
#pragma once

#include <ATen/ATen.h>
#include <ATen/Parallel.h>

#include <algorithm>
#include <cstddef>
#include <limits>
#include <memory>
#include <vector>

#include "../core/common.h"
#include "../core/device_count.h"
#include "../core/lanes.h"
#include "../ops/options.h"
#include "isa.h"
#include "large_buffers.h"

namespace torchvor {
namespace cpu {

// The loops over cells and queries run only the items that
// core::items_to_run says are valid (a speculative pass's list: its count is
// in host memory here), so that at::parallel_for splits those evenly between
// the threads rather than all launched slots (one thread could get every
// valid one).
struct CpuExec {
  using HostExec = CpuExec;  // where the double-double last resort runs
  using Lanes = core::SingleLane;  // the lanes of one cooperative item
  // A cell reads its neighbour list in one cache line or two: row-major.
  static constexpr bool kColumnMajorNeighbors = false;
  // Float32 thread cells keep full 16-byte triangles: a core's caches hold
  // them, and the compact triangles' rounding and masks only cost it time.
  static constexpr bool kCompactTriangles = false;
  // One thread per cell (ConvexCell) and per kNN query: a group of lanes
  // has nothing to share its work with here (the cooperative loops run a
  // group of one lane, for the tests).
  static bool cooperative_cells(int64_t /*cells*/, int64_t /*k*/, c10::optional<double> /*neighbor_spread*/) {
    return false;
  }
  static bool cells_need_spread(int64_t /*cells*/, int64_t /*k*/) { return false; }
  static bool cooperative_queries(int64_t /*queries*/) { return false; }
  static bool fits_cooperative_scratch(int64_t /*bytes_per_item*/) { return true; }

  // Small grains: the work per index varies a lot (cells near the box,
  // recovery passes), and the grid-ordered indices keep locality anyway.
  static constexpr int64_t kGrain = 64;

  // Output tensors: large ones on huge pages (see large_buffers.h).
  static at::Tensor empty(at::IntArrayRef sizes, const at::TensorOptions& options) {
    return empty_large(sizes, options);
  }

  // 0, 1, ..., n - 1 as int32.
  static at::Tensor iota(int64_t n, const at::TensorOptions& options) {
    return at::arange(n, options.dtype(at::kInt));
  }

  // The permutation (int32) that sorts `keys` (int32, each below 2^bits)
  // stably; `sorted_keys`, where given, receives the keys in sorted order.
  static at::Tensor stable_order(const at::Tensor& keys, int /*bits*/, const at::Tensor& /*identity*/ = {},
                                 at::Tensor* sorted_keys = nullptr) {
    const auto sorted = at::sort(keys, /*stable=*/true, /*dim=*/0, /*descending=*/false);
    if (sorted_keys != nullptr) *sorted_keys = std::get<0>(sorted);
    return std::get<1>(sorted).to(at::kInt);
  }

  // out[i] = max(values[0..i]) of an int32 tensor (one pass, one thread:
  // a grid's cells, a few per point at most).
  static at::Tensor running_max(const at::Tensor& values) {
    const at::Tensor out = values.contiguous().clone();
    int32_t* data = out.data_ptr<int32_t>();
    for (int64_t i = 1; i < out.numel(); ++i) data[i] = std::max(data[i], data[i - 1]);
    return out;
  }

  // A small tensor read on the host: here it is there already.
  class HostRead {
   public:
    explicit HostRead(const at::Tensor& words) : words_(words) {}
    at::Tensor wait() const { return words_; }

   private:
    at::Tensor words_;
  };

  // The bytes a scattering kernel writes in one pass (InvertOrderFunctor):
  // no limit, as the GPU's L2 sets one (CudaExec) and a core's caches gain
  // nothing from several passes over the reads.
  static int64_t cached_scatter_bytes() { return std::numeric_limits<int64_t>::max(); }

  template <typename Functor>
  static void for_each(int64_t n, const Functor& functor) {
    at::parallel_for(0, n, kGrain, [&](int64_t begin, int64_t end) {
      for (int64_t i = begin; i < end; ++i) functor(i);
    });
  }

  // Like for_each, for the loop that carries the CPU time (one cell per index):
  // on CPUs with AVX2 and FMA the loop runs from a copy compiled for them
  // (isa.h), where a * b + c may round once, as on the GPU. Not for code that
  // relies on separately rounded products (double-double's Dekker split).
  template <typename Functor>
  static void for_each_cell(int64_t launched, int64_t /*k*/, const ops::Options& options, const Functor& functor) {
    const int64_t n = core::items_to_run(functor, launched);
    const Isa isa = cpu_isa(options.cpu_baseline_isa);
    at::parallel_for(0, n, kGrain, [&](int64_t begin, int64_t end) {
      run_range(isa, begin, end, functor);
    });
  }

  // A thread per item of long, irregular work that carries the CPU time
  // (power cells walking the grid): as for_each_cell.
  template <typename Functor>
  static void for_each_walk(int64_t n, const ops::Options& options, const Functor& functor) {
    for_each_cell(n, 0, options, functor);
  }

  // functor(i, lanes, arrays) with a group of one lane (core::SingleLane) and
  // one Arrays per thread, reused from item to item.
  template <typename Arrays, typename Functor>
  static void for_each_cooperative(int64_t launched, const Functor& functor) {
    const int64_t n = core::items_to_run(functor, launched);
    at::parallel_for(0, n, kGrain, [&](int64_t begin, int64_t end) {
      const auto arrays = std::make_unique<Arrays>();
      for (int64_t i = begin; i < end; ++i) functor(i, core::SingleLane{}, *arrays);
    });
  }

  // functor(i, lanes, arena): for_each_with_scratch with a group of one lane.
  template <typename Functor>
  static void for_each_cooperative_with_scratch(int64_t launched, int64_t bytes, const Functor& functor) {
    for_each_with_scratch(core::items_to_run(functor, launched), bytes, [&](int64_t i, core::ScratchArena arena) {
      functor(i, core::SingleLane{}, arena);
    });
  }

  // functor(i, arena): `bytes` of working memory for item i (one lane),
  // reused by the next item of the same thread. (The kNN search runs here;
  // an AVX2 copy of it measured no faster.)
  template <typename Functor>
  static void for_each_with_scratch(int64_t launched, int64_t bytes, const Functor& functor) {
    const int64_t n = core::items_to_run(functor, launched);
    at::parallel_for(0, n, kGrain, [&](int64_t begin, int64_t end) {
      std::vector<std::max_align_t> scratch((bytes + sizeof(std::max_align_t) - 1) /
                                            sizeof(std::max_align_t));
      unsigned char* base = reinterpret_cast<unsigned char*>(scratch.data());
      for (int64_t i = begin; i < end; ++i) functor(i, core::ScratchArena{base, 0, 1});
    });
  }
};

}  // namespace cpu
}  // namespace torchvor
