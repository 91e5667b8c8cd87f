// Runs a functor over [0, n) as one CUDA kernel on the current stream.
#pragma once

#include <ATen/ATen.h>
#include <ATen/cuda/CUDAContext.h>
#include <c10/cuda/CUDAException.h>

#include <algorithm>

#include <cub/device/device_radix_sort.cuh>
#include <cub/device/device_scan.cuh>

#include "../core/common.h"
#include "../core/device_count.h"
#include "../core/lanes.h"
#include "../cpu/exec.h"
#include "../ops/options.h"

namespace torchvor {
namespace cuda {

template <typename Functor>
__global__ void for_each_kernel(int64_t n, Functor functor) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i < n) functor(i);
}

// Persistent kernels (a grid of the blocks the GPU holds at once, or fewer)
// whose warps claim their items from a counter (zeroed before the launch):
// a warp slowed by costly items claims fewer, so the kernel does not wait on
// its slowest warps' last items, and a block's warps never wait on each
// other. claim(): the first of the `count` items claimed by the calling
// warp (all its lanes call it together).
__device__ inline unsigned long long claim(unsigned long long* next_item, unsigned count) {
  unsigned long long first = 0;
  if ((threadIdx.x & 31) == 0) first = atomicAdd(next_item, static_cast<unsigned long long>(count));
  return __shfl_sync(0xffffffffu, first, 0);
}

// A thread per item, a warp claiming 32 consecutive items at a time (item
// 32 w + lane: a warp's cells read one line per neighbour, as before).
// Items past core::items_to_run are not claimed (a speculative pass's empty
// slots).
template <typename Functor>
__global__ void for_each_claimed_kernel(int64_t launched, unsigned long long* next_item, Functor functor) {
  const int64_t n = core::items_to_run(functor, launched);
  for (;;) {
    const unsigned long long first = claim(next_item, 32u);
    if (first >= static_cast<unsigned long long>(n)) return;
    const int64_t i = static_cast<int64_t>(first) + (threadIdx.x & 31);
    if (i < n) functor(i);
  }
}

// A warp per item, each warp claiming one item at a time, with its Arrays in
// dynamic shared memory. The Arrays are reused from item to item: the
// __syncwarp orders the last item's reads (its integrals) before the next
// item's writes (its start), which the shuffle in claim() does not
// (compute-sanitizer racecheck reported them).
template <typename Arrays, typename Functor>
__global__ void for_each_cooperative_claimed_kernel(int64_t launched, unsigned long long* next_item,
                                                    Functor functor) {
  extern __shared__ __align__(16) unsigned char shared_bytes[];
  const int64_t n = core::items_to_run(functor, launched);
  Arrays& arrays = reinterpret_cast<Arrays*>(shared_bytes)[threadIdx.x / 32];
  for (;;) {
    const unsigned long long item = claim(next_item, 1u);
    if (item >= static_cast<unsigned long long>(n)) return;
    functor(static_cast<int64_t>(item), core::WarpLanes{}, arrays);
    __syncwarp();
  }
}

// Scratch in dynamic shared memory, interleaved across the block's threads.
template <typename Functor>
__global__ void for_each_shared_scratch_kernel(int64_t n, Functor functor) {
  extern __shared__ __align__(16) unsigned char shared_bytes[];
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i < n) functor(i, core::ScratchArena{shared_bytes, threadIdx.x, blockDim.x});
}

// Scratch in global memory when it does not fit on chip, interleaved across
// all n items (a warp's lanes read consecutive addresses for the same slot).
template <typename Functor>
__global__ void for_each_global_scratch_kernel(int64_t n, unsigned char* scratch, Functor functor) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i < n) functor(i, core::ScratchArena{scratch, i, n});
}

// One warp per item with `bytes_per_item` of dynamic shared memory each.
template <typename Functor>
__global__ void for_each_cooperative_scratch_kernel(int64_t n, int64_t bytes_per_item, Functor functor) {
  extern __shared__ __align__(16) unsigned char shared_bytes[];
  const int warp = threadIdx.x / 32;
  const int64_t i = int64_t(blockIdx.x) * (blockDim.x / 32) + warp;
  if (i >= n) return;
  functor(i, core::WarpLanes{}, core::ScratchArena{shared_bytes + warp * bytes_per_item, 0, 1});
}

// out[i] = i.
struct IotaFunctor {
  int32_t* out;
  __device__ void operator()(int64_t i) const { out[i] = static_cast<int32_t>(i); }
};

// The larger of two int32 (running_max's scan).
struct MaxOfInt32 {
  __device__ int32_t operator()(int32_t a, int32_t b) const { return a < b ? b : a; }
};

struct CudaExec {
  using Lanes = core::WarpLanes;  // the lanes of one cooperative item
  using HostExec = cpu::CpuExec;  // where the double-double last resort runs

  // Output tensors: the caching allocator.
  static at::Tensor empty(at::IntArrayRef sizes, const at::TensorOptions& options) {
    return at::empty(sizes, options);
  }

  // 128 threads per block: other sizes measured no faster (docs/performance.md).
  static constexpr int kThreads = 128;
  // Neighbour n of cell t at n * chunk + t: a warp's 32 cells read and write
  // one contiguous line per neighbour instead of 32 scattered ones.
  static constexpr bool kColumnMajorNeighbors = true;
  // Float32 thread cells of the first tier keep 12-byte triangles
  // (CompactTriangles): more cells stay resident in the L1 cache.
  static constexpr bool kCompactTriangles = true;

  // The device's SMs (a MIG slice has fewer), asked at each launch.
  static int64_t sm_count(int& device) {
    int sms = 0;
    C10_CUDA_CHECK(cudaGetDevice(&device));
    C10_CUDA_CHECK(cudaDeviceGetAttribute(&sms, cudaDevAttrMultiProcessorCount, device));
    return sms;
  }

  // The zeroed item counter of a claimed kernel (claim()), on the current
  // stream (the caching allocator reuses it in stream order).
  static at::Tensor item_counter(int device, cudaStream_t stream) {
    const at::Tensor counter = at::empty({1}, at::TensorOptions().dtype(at::kLong).device(at::kCUDA, device));
    C10_CUDA_CHECK(cudaMemsetAsync(counter.data_ptr(), 0, sizeof(unsigned long long), stream));
    return counter;
  }
  static unsigned long long* counter_ptr(const at::Tensor& counter) {
    return reinterpret_cast<unsigned long long*>(counter.data_ptr<int64_t>());
  }

  // 0, 1, ..., n - 1 as int32, a store a thread (at::arange's kernel is
  // several times slower).
  static at::Tensor iota(int64_t n, const at::TensorOptions& options) {
    const at::Tensor out = at::empty({n}, options.dtype(at::kInt));
    for_each(n, IotaFunctor{out.data_ptr<int32_t>()});
    return out;
  }

  // The permutation (int32) that sorts `keys` (int32, each below 2^bits)
  // stably: cub's radix sort over those bits only, carrying int32 indices.
  // (at::sort carried int64 indices through all 32 bits of the keys: four
  // passes where a grid of 5M cells needs three.) `identity`, where given,
  // is iota(n), which the sort reads as its indices; `sorted_keys`, where
  // given, receives the keys in sorted order.
  static at::Tensor stable_order(const at::Tensor& keys, int bits, const at::Tensor& given_identity = {},
                                 at::Tensor* sorted_keys = nullptr) {
    const int64_t n = keys.size(0);
    TORCH_CHECK(n < (int64_t(1) << 31), "torchvor: too many points for int32 indices");
    const at::Tensor identity = given_identity.defined() ? given_identity : iota(n, keys.options());
    const at::Tensor keys_out = at::empty_like(keys);
    if (sorted_keys != nullptr) *sorted_keys = keys_out;
    if (n == 0) return identity;
    const at::Tensor order = at::empty_like(keys);
    const auto sort = [&](void* scratch, size_t& scratch_bytes) {
      // Non-negative int32 keys sort as their uint32 bits.
      return cub::DeviceRadixSort::SortPairs(
          scratch, scratch_bytes, reinterpret_cast<const uint32_t*>(keys.data_ptr<int32_t>()),
          reinterpret_cast<uint32_t*>(keys_out.data_ptr<int32_t>()), identity.data_ptr<int32_t>(),
          order.data_ptr<int32_t>(), static_cast<int>(n), 0, bits, at::cuda::getCurrentCUDAStream());
    };
    size_t scratch_bytes = 0;
    C10_CUDA_CHECK(sort(nullptr, scratch_bytes));
    const at::Tensor scratch = at::empty({static_cast<int64_t>(scratch_bytes)}, keys.options().dtype(at::kByte));
    C10_CUDA_CHECK(sort(scratch.data_ptr(), scratch_bytes));
    return order;
  }

  // out[i] = max(values[0..i]) of an int32 tensor: cub's scan.
  static at::Tensor running_max(const at::Tensor& values) {
    const int64_t n = values.size(0);
    TORCH_CHECK(n < (int64_t(1) << 31), "torchvor: too many grid cells for an int32 scan");
    const at::Tensor out = at::empty_like(values);
    if (n == 0) return out;
    const auto scan = [&](void* scratch, size_t& scratch_bytes) {
      return cub::DeviceScan::InclusiveScan(scratch, scratch_bytes, values.data_ptr<int32_t>(),
                                            out.data_ptr<int32_t>(), MaxOfInt32{}, static_cast<int>(n),
                                            at::cuda::getCurrentCUDAStream());
    };
    size_t scratch_bytes = 0;
    C10_CUDA_CHECK(scan(nullptr, scratch_bytes));
    const at::Tensor scratch = at::empty({static_cast<int64_t>(scratch_bytes)}, values.options().dtype(at::kByte));
    C10_CUDA_CHECK(scan(scratch.data_ptr(), scratch_bytes));
    return out;
  }

  // A small device tensor's copy to the host (pinned memory), which the
  // host waits for only in wait(): what the caller launches in between runs
  // on the device while the copy travels back and the host waits.
  class HostRead {
   public:
    explicit HostRead(const at::Tensor& device)
        : host_(at::empty(device.sizes(), device.options().device(at::kCPU).pinned_memory(true))) {
      host_.copy_(device, /*non_blocking=*/true);
      C10_CUDA_CHECK(cudaEventCreateWithFlags(&copied_, cudaEventDisableTiming));
      C10_CUDA_CHECK(cudaEventRecord(copied_, at::cuda::getCurrentCUDAStream()));
    }
    HostRead(const HostRead&) = delete;
    HostRead& operator=(const HostRead&) = delete;
    ~HostRead() { C10_CUDA_CHECK_WARN(cudaEventDestroy(copied_)); }
    at::Tensor wait() const {
      C10_CUDA_CHECK(cudaEventSynchronize(copied_));
      return host_;
    }

   private:
    at::Tensor host_;
    cudaEvent_t copied_ = nullptr;
  };

  // The bytes a scattering kernel should write in one launch so that its
  // writes fill whole sectors in the L2 cache before they reach memory: half
  // the L2 (the launch's reads pass through it too).
  static int64_t cached_scatter_bytes() {
    int device = 0, l2_bytes = 0;
    C10_CUDA_CHECK(cudaGetDevice(&device));
    C10_CUDA_CHECK(cudaDeviceGetAttribute(&l2_bytes, cudaDevAttrL2CacheSize, device));
    return std::max<int64_t>(1 << 20, l2_bytes / 2);
  }

  template <typename Functor>
  static void for_each(int64_t n, const Functor& functor) {
    if (n == 0) return;
    const int64_t blocks = (n + kThreads - 1) / kThreads;
    for_each_kernel<<<blocks, kThreads, 0, at::cuda::getCurrentCUDAStream()>>>(n, functor);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  }

  // A warp per cell (CooperativeCell) or a thread per cell (ConvexCell).
  // A pass over few cells (retries, the pilot) takes as long as its slowest
  // cell, and a warp cuts that latency; up to kCooperativeCellsUpTo cells,
  // where the two cross over.
  //
  // Over many cells, a thread per cell wins where the cells need about as
  // many neighbours as each other, and a warp where that varies widely: the
  // 32 threads of a warp run until its slowest cell is done, testing
  // neighbours against vertices one at a time, while a warp cell spreads
  // each test over its lanes. The spread of the neighbours the pilot's cells
  // needed (standard deviation / mean, pilot.h) tells the two apart; k does
  // not (perturbed grids and white noise both get k >= 40). Blue noise
  // (spread ~0.1) and jittered or perturbed grids run faster with threads,
  // white noise (~0.29) and clusters (~0.31) with warps; near
  // kCooperativeCellsFromSpread the two are within a few percent.
  // Without a spread (no pilot ran: a caller's k below 40, which
  // cells_need_spread leaves to k) k decides: from 40, warps, as the
  // irregular kinds' k is above and blue noise's (19-24) below.
  static constexpr int64_t kCooperativeCellsUpTo = 16384;
  static constexpr int64_t kCooperativeCellsFromK = 40;
  static constexpr double kCooperativeCellsFromSpread = 0.25;
  static bool cooperative_cells(int64_t cells, int64_t k, c10::optional<double> neighbor_spread) {
    if (cells <= kCooperativeCellsUpTo) return true;
    if (neighbor_spread.has_value()) return *neighbor_spread >= kCooperativeCellsFromSpread;
    return k >= kCooperativeCellsFromK;
  }
  // Whether a pass with the caller's k would be decided by k alone, where a
  // pilot's spread would decide better. The pilot (one pass over ~1000 cells
  // and a read) then runs, small next to the passes it decides.
  static bool cells_need_spread(int64_t cells, int64_t k) {
    return cells > kCooperativeCellsUpTo && k >= kCooperativeCellsFromK;
  }

  // functor(i, lanes, arrays): the 32 lanes of a warp (core::WarpLanes) per
  // item, sharing one Arrays in shared memory; up to 4 warps a block, fewer
  // when their arrays pass the 48 KB a block gets without opting in. The
  // warps claim one item at a time (for_each_cooperative_claimed_kernel), so
  // that no block holds its shared memory while its slowest cell finishes.
  template <typename Arrays, typename Functor>
  static void for_each_cooperative(int64_t n, const Functor& functor) {
    if (n == 0) return;
    constexpr int64_t kSharedPerBlock = 48 * 1024;
    static_assert(sizeof(Arrays) <= kSharedPerBlock, "a cell's arrays must fit in 48 KB of shared memory");
    const int64_t warps = std::min<int64_t>(kThreads / 32, kSharedPerBlock / int64_t(sizeof(Arrays)));
    const int64_t shared_bytes = warps * int64_t(sizeof(Arrays));
    const auto kernel = for_each_cooperative_claimed_kernel<Arrays, Functor>;
    static const int64_t most = [&] {  // blocks an SM holds (the kernel's and the architecture's)
      int blocks = 0;
      C10_CUDA_CHECK(cudaOccupancyMaxActiveBlocksPerMultiprocessor(&blocks, kernel, int(32 * warps), shared_bytes));
      return std::max<int64_t>(1, blocks);
    }();
    int device = 0;
    const int64_t blocks = std::min<int64_t>((n + warps - 1) / warps, sm_count(device) * most);
    const auto stream = at::cuda::getCurrentCUDAStream();
    const at::Tensor counter = item_counter(device, stream);
    kernel<<<blocks, int(32 * warps), shared_bytes, stream>>>(n, counter_ptr(counter), functor);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  }

  // The same for kNN queries: a pass over few queries (a retry pass inside
  // voronoi) waits on one thread's serial cell and point loads; a warp per
  // query has them in flight together. Up to kCooperativeQueriesUpTo
  // queries, where the two cross over.
  static constexpr int64_t kCooperativeQueriesUpTo = 16384;
  static bool cooperative_queries(int64_t queries) { return queries <= kCooperativeQueriesUpTo; }

  // Whether one warp's scratch fits the 48 KB of shared memory a block gets
  // without opting in (k up to ~6000 float32 neighbours).
  static bool fits_cooperative_scratch(int64_t bytes_per_item) { return bytes_per_item <= 48 * 1024; }

  // functor(i, lanes, arena): a warp per item with `bytes_per_item` of
  // shared memory (fits_cooperative_scratch), up to 4 warps a block.
  template <typename Functor>
  static void for_each_cooperative_with_scratch(int64_t n, int64_t bytes_per_item, const Functor& functor) {
    if (n == 0) return;
    const int64_t warps = std::max<int64_t>(1, std::min<int64_t>(kThreads / 32, 48 * 1024 / bytes_per_item));
    const int64_t blocks = (n + warps - 1) / warps;
    for_each_cooperative_scratch_kernel<Functor><<<blocks, int(32 * warps), warps * bytes_per_item,
                                                   at::cuda::getCurrentCUDAStream()>>>(n, bytes_per_item,
                                                                                      functor);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  }

  // One thread per cell (ConvexCell), with fewer threads resident than the
  // GPU could hold. Each thread's cell lives in local memory (a stack frame
  // of a few KB). At full residency the frames outgrow the L2 cache and the
  // clip kernel streams local memory from DRAM; capped at kCellFramesPerSm
  // bytes of stack frames an SM (the kernel's own frame size,
  // cudaFuncGetAttributes), the frames stay in cache. Passes of cells that
  // need more neighbours run best with fewer threads resident (such cells
  // grow more vertices and touch more of their frame): from a pass's k of
  // kLargeCellsFromK, three quarters of those blocks (rounded).
  // Options::cell_blocks_per_sm overrides the cap (benchmarks).
  // The warps claim 32 cells at a time (for_each_claimed_kernel), so that the
  // kernel does not wait on its slowest warps' last rounds.
  static constexpr int64_t kCellFramesPerSm = 1024 * 1024;
  static constexpr int64_t kLargeCellsFromK = 28;

  // functor(i) for i in [0, n), cells whose pass reads k neighbours each.
  template <typename Functor>
  static void for_each_cell(int64_t n, int64_t k, const ops::Options& options, const Functor& functor) {
    if (n == 0) return;
    const auto kernel = for_each_claimed_kernel<Functor>;
    // The kernel's frame and the blocks an SM holds depend only on the kernel
    // and the GPU architecture (a process is taken to see one), so they are
    // asked once, not at every pass.
    struct Residency {
      int64_t frame_bytes;  // the stack frame of one thread
      int64_t most;         // blocks of kThreads an SM can hold
    };
    static const Residency residency = [&] {
      cudaFuncAttributes attributes;
      C10_CUDA_CHECK(cudaFuncGetAttributes(&attributes, kernel));
      int most = 0;
      C10_CUDA_CHECK(cudaOccupancyMaxActiveBlocksPerMultiprocessor(&most, kernel, kThreads, 0));
      return Residency{std::max<int64_t>(1, static_cast<int64_t>(attributes.localSizeBytes)),
                       std::max<int64_t>(1, most)};
    }();
    int device = 0;
    const int64_t sms = sm_count(device);
    int64_t per_sm = kCellFramesPerSm / (kThreads * residency.frame_bytes);
    if (k >= kLargeCellsFromK) per_sm = (3 * per_sm + 2) / 4;
    if (options.cell_blocks_per_sm > 0) per_sm = options.cell_blocks_per_sm;
    per_sm = std::max<int64_t>(1, std::min<int64_t>(per_sm, residency.most));
    const int64_t blocks = std::min<int64_t>((n + kThreads - 1) / kThreads, sms * per_sm);
    const auto stream = at::cuda::getCurrentCUDAStream();
    const at::Tensor counter = item_counter(device, stream);
    kernel<<<blocks, kThreads, 0, stream>>>(n, counter_ptr(counter), functor);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  }

  // A thread per item of long, irregular work (power cells walking the
  // grid), every thread the GPU holds resident: capped as for_each_cell, the
  // power cells ran slower (docs/performance.md).
  template <typename Functor>
  static void for_each_walk(int64_t n, const ops::Options& /*options*/, const Functor& functor) {
    for_each(n, functor);
  }

  // functor(i, arena) with `bytes_per_item` of scratch per item, in shared
  // memory (at most half of an SM's per block, so that two blocks fit; fewer
  // threads per block for large scratch), or in global memory beyond that.
  template <typename Functor>
  static void for_each_with_scratch(int64_t n, int64_t bytes_per_item, const Functor& functor) {
    if (n == 0) return;
    const auto stream = at::cuda::getCurrentCUDAStream();
    int device = 0, max_shared = 0;
    C10_CUDA_CHECK(cudaGetDevice(&device));
    C10_CUDA_CHECK(cudaDeviceGetAttribute(&max_shared, cudaDevAttrMaxSharedMemoryPerBlockOptin, device));
    int threads = kThreads;
    while (threads > 32 && threads * bytes_per_item > max_shared / 2) threads /= 2;
    const int64_t shared_bytes = threads * bytes_per_item;
    if (shared_bytes <= max_shared) {
      const auto kernel = for_each_shared_scratch_kernel<Functor>;
      if (shared_bytes > 48 * 1024) {
        C10_CUDA_CHECK(cudaFuncSetAttribute(kernel, cudaFuncAttributeMaxDynamicSharedMemorySize,
                                            static_cast<int>(shared_bytes)));
      }
      const int64_t blocks = (n + threads - 1) / threads;
      kernel<<<blocks, threads, shared_bytes, stream>>>(n, functor);
      C10_CUDA_KERNEL_LAUNCH_CHECK();
      return;
    }
    const at::Tensor scratch = at::empty({n * bytes_per_item},
                                         at::TensorOptions().dtype(at::kByte).device(at::kCUDA, device));
    const int64_t blocks = (n + kThreads - 1) / kThreads;
    for_each_global_scratch_kernel<Functor><<<blocks, kThreads, 0, stream>>>(
        n, scratch.data_ptr<uint8_t>(), functor);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  }
};

}  // namespace cuda
}  // namespace torchvor
