// Host tensors for large outputs, backed by transparent huge pages.
#pragma once

#include <ATen/ATen.h>

namespace torchvor {
namespace cpu {

// at::empty for CPU tensors that are written once, front to back (a 1M x 35
// kNN result is 420 MB). With 4 KB pages each first touch of such a buffer
// faults into the kernel, a visible share of a kNN call. Above a few MB (on
// Linux) the buffer is 2 MB aligned and advised for transparent huge pages,
// which cuts the faults 500-fold; it is an ordinary, resizable tensor
// otherwise. Small sizes use at::empty.
at::Tensor empty_large(at::IntArrayRef sizes, const at::TensorOptions& options);

}  // namespace cpu
}  // namespace torchvor
