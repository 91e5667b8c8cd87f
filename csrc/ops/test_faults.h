// Fault injection for the tests (Options::Testing), kept out of the passes
// themselves: a pass runner is wrapped once, before the retry loop.
#pragma once

#include <ATen/ATen.h>

#include <utility>

#include "../core/status.h"
#include "cell_records.h"
#include "options.h"

namespace torchvor {
namespace ops {

// `run` itself, except that with Options::Testing::forget_position set, its
// first call's result for that grid position is dropped: the record zeroed
// and the status set back to "not computed", as if no pass had written it.
// Such a cell asks for nothing to be raised, so unless other cells do, no
// later pass computes it; the tests check that it then reads as not computed.
template <typename Run>
auto with_test_faults(const Options::Testing& testing, PositionOutputs& out, Run run) {
  return [&testing, &out, run, first = true](auto&&... args) mutable {
    run(std::forward<decltype(args)>(args)...);
    const int64_t position = testing.forget_position;
    if (first && position >= 0 && position < out.status.size(0)) {
      out.records.select(0, position).zero_();
      out.status.select(0, position).fill_(int(core::kNotComputed));
    }
    first = false;
  };
}

}  // namespace ops
}  // namespace torchvor
