// Float64 points, clipped in float64 (clip_tiers.cuh).
#include "clip_tiers.cuh"

TORCHVOR_CLIP_CHUNK_TIER(, double, double);
TORCHVOR_CLIP_CHUNK_UP_TO_DEVICE_COUNT(, double);
