// Float32 points clipped in float64: the retries of their ill-conditioned cells (clip_tiers.cuh).
#include "clip_tiers.cuh"

TORCHVOR_CLIP_CHUNK_TIER(, float, double);
