// Runs a functor over [0, n) as one CUDA kernel on the current stream.
#pragma once

#include <ATen/cuda/CUDAContext.h>
#include <c10/cuda/CUDAException.h>

#include <cstdlib>

namespace torchvor {
namespace cuda {

template <typename Functor>
__global__ void for_each_kernel(int64_t n, Functor functor) {
  const int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i < n) functor(i);
}

struct CudaExec {
  static constexpr int kThreads = 128;

  template <typename Functor>
  static void for_each(int64_t n, const Functor& functor) {
    if (n == 0) return;
    int threads = kThreads;
    int padding = 0;  // EXPERIMENT: dynamic shared memory that limits blocks per SM
    if (Functor::kIsClip) {
      if (const char* s = std::getenv("TORCHVOR_CLIP_THREADS")) threads = std::atoi(s);
      if (const char* s = std::getenv("TORCHVOR_CLIP_SMEM")) padding = std::atoi(s);
      if (padding > 48 * 1024) {
        C10_CUDA_CHECK(cudaFuncSetAttribute(for_each_kernel<Functor>,
                                            cudaFuncAttributeMaxDynamicSharedMemorySize, padding));
      }
    }
    const int64_t blocks = (n + threads - 1) / threads;
    for_each_kernel<<<blocks, threads, padding, at::cuda::getCurrentCUDAStream()>>>(n, functor);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  }
};

}  // namespace cuda
}  // namespace torchvor
