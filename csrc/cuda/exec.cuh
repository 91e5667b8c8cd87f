// Runs a functor over [0, n) as one CUDA kernel on the current stream.
#pragma once

#include <ATen/cuda/CUDAContext.h>
#include <c10/cuda/CUDAException.h>

namespace torchvor {
namespace cuda {

template <typename Functor>
__global__ void for_each_kernel(int64_t n, Functor functor) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i < n) functor(i);
}

struct CudaExec {
  // 128 threads per block: a sweep of 32-256 threads and of residency caps
  // changed nothing or made it slower (benchmarks/NOTES.md).
  static constexpr int kThreads = 128;
  // Neighbour n of cell t at n * chunk + t: a warp's 32 cells read and write
  // one contiguous line per neighbour instead of 32 scattered ones.
  static constexpr bool kColumnMajorNeighbors = true;

  template <typename Functor>
  static void for_each(int64_t n, const Functor& functor) {
    if (n == 0) return;
    const int64_t blocks = (n + kThreads - 1) / kThreads;
    for_each_kernel<<<blocks, kThreads, 0, at::cuda::getCurrentCUDAStream()>>>(n, functor);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  }
};

}  // namespace cuda
}  // namespace torchvor
