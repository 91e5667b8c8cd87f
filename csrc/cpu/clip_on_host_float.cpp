// The host's clips of float32 points (clip_on_host.h); float64 points' are in
// clip_on_host_double.cpp, so that the two compile in parallel.
#include "clip_on_host.h"

TORCHVOR_CLIP_ON_HOST(, float);
