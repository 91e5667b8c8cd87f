// What the CPU backend really runs with, for the tests and the benchmarks:
// - torchvor::cpu_threads_used: how many threads CpuExec (the executor of
//   every CPU kernel) runs on. A build without -fopenmp compiles
//   at::parallel_for to a serial loop without any warning; the tests compare
//   this with torch.get_num_threads().
// - torchvor::cpu_isa: the instruction set of the clip loop ("avx2+fma" or
//   "baseline", isa.h).
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <chrono>
#include <mutex>
#include <set>
#include <string>
#include <thread>

#include "../ops/options.h"
#include "exec.h"

namespace torchvor {
namespace cpu {
namespace {

struct RecordThread {
  std::mutex* mutex;
  std::set<int>* threads;
  void operator()(int64_t) const {
    // Long enough per index that the pool cannot finish before every thread starts.
    std::this_thread::sleep_for(std::chrono::microseconds(200));
    std::lock_guard<std::mutex> lock(*mutex);
    threads->insert(at::get_thread_num());
  }
};

int64_t cpu_threads_used() {
  std::mutex mutex;
  std::set<int> threads;
  CpuExec::for_each(64 * int64_t(at::get_num_threads()), RecordThread{&mutex, &threads});
  return static_cast<int64_t>(threads.size());
}

std::string cpu_isa_used() { return isa_name(cpu_isa(ops::Options::from_environment().cpu_baseline_isa)); }

}  // namespace

// No tensor arguments, so no dispatch key: catch-all kernels.
TORCH_LIBRARY_FRAGMENT(torchvor, m) {
  m.impl("cpu_threads_used", &cpu_threads_used);
  m.impl("cpu_isa", &cpu_isa_used);
}

}  // namespace cpu
}  // namespace torchvor
