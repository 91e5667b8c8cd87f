// Float32 points clipped in float32: the first passes of float32 input and
// the speculative retry (clip_tiers.cuh).
#include "clip_tiers.cuh"

TORCHVOR_CLIP_CHUNK_TIER(, float, float);
TORCHVOR_CLIP_CHUNK_UP_TO_DEVICE_COUNT(, float);
