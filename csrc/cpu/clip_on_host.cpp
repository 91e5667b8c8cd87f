#include "clip_on_host.h"

TORCHVOR_CLIPS_ON_HOST();
