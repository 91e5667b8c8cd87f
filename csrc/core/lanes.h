// The lanes that compute one item together (a cell in cooperative_cell.h, a
// query in grid_search.h): the 32 lanes of a warp on the GPU, a single lane
// on the host. The lanes of a group always take the same branches; these are
// their collective operations.
#pragma once

#include "common.h"

namespace torchvor {
namespace core {

// A group of one: every collective is the identity. The host runs the
// cooperative cell this way (tests use it to check that algorithm on a CPU).
struct SingleLane {
  static constexpr int kCount = 1;
  TV_HD int index() const { return 0; }
  TV_HD uint32_t below() const { return 0u; }  // the lanes with a lower index, as bits
  TV_HD uint32_t ballot(bool predicate) const { return uint32_t(predicate); }
  TV_HD bool all(bool predicate) const { return predicate; }
  TV_HD bool any(bool predicate) const { return predicate; }
  TV_HD void sync() const {}
  TV_HD void set_shared_bits(uint32_t* word, uint32_t bits) const { *word |= bits; }
  TV_HD void store_shared(uint32_t* word, uint32_t value) const { *word = value; }
  template <typename T>
  TV_HD T sum(T value) const { return value; }
  template <typename T>
  TV_HD T max(T value) const { return value; }
  template <typename T>
  TV_HD T min(T value) const { return value; }
  template <typename T>
  TV_HD T broadcast(T value, int /*lane*/) const { return value; }
};

#if defined(__CUDACC__)
// All 32 lanes of a warp, every one of them active (the kernel gives each
// warp one item, so a warp never splits). The bodies are device-only; the
// host fallbacks exist only so that host-device templates compile.
struct WarpLanes {
  static constexpr int kCount = 32;
  static constexpr unsigned kAll = 0xffffffffu;

  TV_HD int index() const {
#if defined(__CUDA_ARCH__)
    return int(threadIdx.x & 31u);
#else
    return 0;
#endif
  }
  TV_HD uint32_t below() const { return (1u << index()) - 1u; }
  TV_HD uint32_t ballot(bool predicate) const {
#if defined(__CUDA_ARCH__)
    return __ballot_sync(kAll, predicate);
#else
    return uint32_t(predicate);
#endif
  }
  TV_HD bool all(bool predicate) const {
#if defined(__CUDA_ARCH__)
    return __all_sync(kAll, predicate) != 0;
#else
    return predicate;
#endif
  }
  TV_HD bool any(bool predicate) const {
#if defined(__CUDA_ARCH__)
    return __any_sync(kAll, predicate) != 0;
#else
    return predicate;
#endif
  }
  // *word |= bits, from any number of lanes at once (shared memory).
  TV_HD void set_shared_bits(uint32_t* word, uint32_t bits) const {
#if defined(__CUDA_ARCH__)
    atomicOr(word, bits);
#else
    *word |= bits;
#endif
  }
  // *word = value from any number of lanes at once (shared memory): one
  // store lands whole; the lanes may then check whose did.
  TV_HD void store_shared(uint32_t* word, uint32_t value) const {
#if defined(__CUDA_ARCH__)
    atomicExch(word, value);
#else
    *word = value;
#endif
  }
  // Orders the lanes' shared-memory writes before the reads that follow.
  TV_HD void sync() const {
#if defined(__CUDA_ARCH__)
    __syncwarp(kAll);
#endif
  }
  // Butterfly reductions: every lane ends with the same bits (each step adds
  // or compares the same two values in either order).
  template <typename T>
  TV_HD T sum(T value) const {
    return butterfly(value, [](T mine, T other) { return mine + other; });
  }
  template <typename T>
  TV_HD T max(T value) const {
    return butterfly(value, [](T mine, T other) { return max_of(mine, other); });
  }
  template <typename T>
  TV_HD T min(T value) const {
    return butterfly(value, [](T mine, T other) { return min_of(mine, other); });
  }
  // Lane `lane`'s value, in every lane.
  template <typename T>
  TV_HD T broadcast(T value, int lane) const {
#if defined(__CUDA_ARCH__)
    return __shfl_sync(kAll, value, lane);
#else
    (void)lane;
    return value;
#endif
  }

 private:
  // value = combine(value, the value of the lane `offset` away), for offsets
  // 16, 8, 4, 2, 1.
  template <typename T, typename Combine>
  TV_HD T butterfly(T value, Combine combine) const {
#if defined(__CUDA_ARCH__)
    TV_UNROLL
    for (int offset = 16; offset > 0; offset /= 2) value = combine(value, __shfl_xor_sync(kAll, value, offset));
#else
    (void)combine;
#endif
    return value;
  }
};
#endif

}  // namespace core
}  // namespace torchvor
