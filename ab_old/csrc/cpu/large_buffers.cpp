#include "large_buffers.h"

#include <c10/core/Allocator.h>

#include <cstdlib>

#if defined(__linux__)
#include <sys/mman.h>
#endif

namespace torchvor {
namespace cpu {

#if defined(__linux__)
namespace {

constexpr size_t kHugePage = size_t(2) << 20;
// Below this the saved faults are not worth up to 2 MB of alignment slack.
constexpr size_t kMinBytes = 4 * kHugePage;

void free_buffer(void* data) { std::free(data); }

struct HugePageAllocator final : c10::Allocator {
  c10::DataPtr allocate(size_t bytes) override {
    void* data = nullptr;
    if (bytes > 0) {
      const int error = posix_memalign(&data, kHugePage, bytes);
      TORCH_CHECK_WITH(OutOfMemoryError, error == 0 && data != nullptr,
                       "torchvor: cannot allocate ", bytes, " bytes of host memory");
      // Advisory only: where huge pages are disabled the kernel ignores it.
      madvise(data, bytes, MADV_HUGEPAGE);
    }
    return {data, data, &free_buffer, c10::Device(c10::DeviceType::CPU)};
  }
  c10::DeleterFnPtr raw_deleter() const override { return &free_buffer; }
  void copy_data(void* dest, const void* src, std::size_t count) const override {
    default_copy_data(dest, src, count);
  }
};

HugePageAllocator huge_page_allocator;

}  // namespace

at::Tensor empty_large(at::IntArrayRef sizes, const at::TensorOptions& options) {
  TORCH_INTERNAL_ASSERT(options.device().is_cpu());
  size_t bytes = options.dtype().itemsize();
  for (const int64_t size : sizes) bytes *= static_cast<size_t>(size);
  if (bytes < kMinBytes) return at::empty(sizes, options);
  return at::detail::empty_generic(sizes, &huge_page_allocator,
                                   c10::DispatchKeySet(c10::DispatchKey::CPU),
                                   options.dtype().toScalarType(), c10::nullopt);
}

#else

at::Tensor empty_large(at::IntArrayRef sizes, const at::TensorOptions& options) {
  return at::empty(sizes, options);
}

#endif

}  // namespace cpu
}  // namespace torchvor
