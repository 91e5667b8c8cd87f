// The host's clips of float64 points (clip_on_host.h).
#include "clip_on_host.h"

TORCHVOR_CLIP_ON_HOST(, double);
