// The clips that no device runs (ops::clip_chunk_on_host: the largest tiers
// and double-double), compiled once for both backends, in clip_on_host_float.cpp
// and clip_on_host_double.cpp.
#pragma once

#include "../ops/clip_pass.h"
#include "exec.h"

// TORCHVOR_CLIP_ON_HOST(extern, io_t) declares the instantiation for points
// of io_t; TORCHVOR_CLIP_ON_HOST(, io_t) defines it.
#define TORCHVOR_CLIP_ON_HOST(EXTERN, io_t)                                                                     \
  EXTERN template void torchvor::ops::clip_chunk_on_host<torchvor::cpu::CpuExec, io_t>(                        \
      const at::Tensor& points, const at::Tensor& box, const c10::optional<at::Tensor>& batch,                 \
      const at::Tensor& cells, const at::Tensor& neighbors, bool column_major,                                 \
      const torchvor::ops::PassSettings& pass, const torchvor::ops::Grid* vertex_balls,                        \
      const torchvor::ops::Options& options, torchvor::ops::PositionOutputs& out)

#define TORCHVOR_CLIPS_ON_HOST(EXTERN)   \
  TORCHVOR_CLIP_ON_HOST(EXTERN, float); \
  TORCHVOR_CLIP_ON_HOST(EXTERN, double)
