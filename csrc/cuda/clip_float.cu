// Float32 points clipped in float32: the first passes of float32 input (clip_tiers.cuh).
#include "clip_tiers.cuh"

TORCHVOR_CLIP_CHUNK_TIER(, float, float);
