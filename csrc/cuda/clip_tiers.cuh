// The CUDA clip kernels (ops::clip_chunk_tier, the speculative pass's
// ops::clip_chunk_up_to_device_count, and all they launch) are compiled in
// translation units of their own, one a pair of point and cell precisions
// (clip_float.cu, clip_float_in_double.cu, clip_double.cu), so that the
// build compiles them in parallel with each other and with the rest of
// voronoi.cu, which declares them extern: they are most of the CUDA
// build's compile time.
#pragma once

#include "../ops/clip_pass.h"
#include "exec.cuh"

// TORCHVOR_CLIP_CHUNK_TIER(extern, io_t, T) declares the instantiation for
// points of io_t clipped in T; TORCHVOR_CLIP_CHUNK_TIER(, io_t, T) defines it.
#define TORCHVOR_CLIP_CHUNK_TIER(EXTERN, io_t, T)                                                            \
  EXTERN template void torchvor::ops::clip_chunk_tier<torchvor::cuda::CudaExec, io_t, T>(                   \
      const at::Tensor& points, const at::Tensor& box, const c10::optional<at::Tensor>& batch,              \
      const at::Tensor& cells, const at::Tensor& neighbors, int tier, const torchvor::ops::Grid* vertex_balls, \
      c10::optional<double> neighbor_spread, const torchvor::ops::Options& options,                          \
      torchvor::ops::PositionOutputs& out)

// The speculative retry pass's clip (ops::run_speculative_pass) for points of io_t.
#define TORCHVOR_CLIP_CHUNK_UP_TO_DEVICE_COUNT(EXTERN, io_t)                                            \
  EXTERN template void torchvor::ops::clip_chunk_up_to_device_count<torchvor::cuda::CudaExec, io_t>(     \
      const at::Tensor& points, const at::Tensor& box, const c10::optional<at::Tensor>& batch,          \
      const at::Tensor& cells, const at::Tensor& neighbors, c10::optional<double> neighbor_spread,      \
      const torchvor::core::DeviceCount& live, const torchvor::ops::Options& options,                  \
      torchvor::ops::PositionOutputs& out)

// Every clip that ops::voronoi_passes runs on the GPU.
#define TORCHVOR_CLIP_CHUNK_TIERS(EXTERN)                \
  TORCHVOR_CLIP_CHUNK_TIER(EXTERN, float, float);        \
  TORCHVOR_CLIP_CHUNK_TIER(EXTERN, float, double);       \
  TORCHVOR_CLIP_CHUNK_TIER(EXTERN, double, double);      \
  TORCHVOR_CLIP_CHUNK_UP_TO_DEVICE_COUNT(EXTERN, float); \
  TORCHVOR_CLIP_CHUNK_UP_TO_DEVICE_COUNT(EXTERN, double)
