// Host-only: a kNN row written by non-temporal stores. A store to a line
// that is not in the cache first reads the line in (read for ownership);
// a non-temporal store skips that read and the cache. That pays where the
// rows are written once, to places scattered over a result far larger than
// the caches (the public kNN writes each query's row at its caller's row,
// in grid order), and costs where the caller soon reads a result that would
// have stayed cached. Non-temporal stores are weakly ordered: each row ends
// with a fence, so the stores are visible before the thread moves on.
#pragma once

#if !defined(__CUDACC__) && defined(__GNUC__) && defined(__x86_64__)
#define TORCHVOR_HAS_STREAM_STORES 1

#include <emmintrin.h>

#include <cstdint>
#include <cstring>

namespace torchvor {
namespace core {

// *at = value, bypassing the caches (4- or 8-byte values).
template <typename V>
inline void stream_store(V* at, V value) {
  static_assert(sizeof(V) == 4 || sizeof(V) == 8, "stream_store writes 4 or 8 bytes");
  if constexpr (sizeof(V) == 4) {
    int bits;
    memcpy(&bits, &value, sizeof bits);
    _mm_stream_si32(reinterpret_cast<int*>(at), bits);
  } else {
    long long bits;
    memcpy(&bits, &value, sizeof bits);
    _mm_stream_si64(reinterpret_cast<long long*>(at), bits);
  }
}

// The `size` sorted keys as (dist2, index) at elements 0.. of a row of
// `capacity`, padded with (infinity, -1); `dist2_out` may be null.
template <typename Key, typename T, typename index_t>
inline void stream_row(const Key* keys, int32_t size, int32_t capacity, T* dist2_out, index_t* index_out,
                       T infinity) {
  for (int32_t e = 0; e < capacity; ++e) {
    const bool kept = e < size;
    stream_store(index_out + e, kept ? index_t(keys[e].index()) : index_t(-1));
    if (dist2_out) stream_store(dist2_out + e, kept ? keys[e].dist2() : infinity);
  }
  _mm_sfence();
}

}  // namespace core
}  // namespace torchvor

#endif
