#include <torch/library.h>

#include "../ops/power.h"
#include "exec.h"

TORCH_LIBRARY_IMPL(torchvor, CPU, m) {
  m.impl("power_cells", &torchvor::ops::power_cells<torchvor::cpu::CpuExec>);
  m.impl("power_faces", &torchvor::ops::power_faces<torchvor::cpu::CpuExec>);
}
