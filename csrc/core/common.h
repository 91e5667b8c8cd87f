// Small vector types and the host/device qualifier shared by every kernel.
// Everything under csrc/core/ is header-only and compiles both with the host
// compiler (CPU path) and with nvcc (CUDA path): one geometry, two backends.
#pragma once

#include <cmath>
#include <cstdint>
#include <cstring>
#include <type_traits>

#if defined(__CUDACC__)
#define TV_HD __host__ __device__ __forceinline__
#elif defined(__GNUC__)
// Inlined on the host too, as nvcc inlines on the device: GCC does not
// always inline the small helpers of the hot loops, and forcing it speeds
// up the CPU kNN.
#define TV_HD inline __attribute__((always_inline))
#else
#define TV_HD inline
#endif

namespace torchvor {
namespace core {

template <typename T>
struct Vec3 {
  T x, y, z;
};

// 16-byte aligned: a GPU thread loads a float plane with one vector load.
template <typename T>
struct alignas(16) Plane {  // inside iff dot(normal, x) + offset > 0
  Vec3<T> normal;
  T offset;
};

template <typename T>
TV_HD Vec3<T> operator+(Vec3<T> a, Vec3<T> b) { return {a.x + b.x, a.y + b.y, a.z + b.z}; }
template <typename T>
TV_HD Vec3<T> operator-(Vec3<T> a, Vec3<T> b) { return {a.x - b.x, a.y - b.y, a.z - b.z}; }
template <typename T>
TV_HD Vec3<T> operator*(T s, Vec3<T> a) { return {s * a.x, s * a.y, s * a.z}; }
template <typename T>
TV_HD T dot(Vec3<T> a, Vec3<T> b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
template <typename T>
TV_HD Vec3<T> cross(Vec3<T> a, Vec3<T> b) {
  return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
}

template <typename T>
TV_HD Vec3<T> load_vec3(const T* p) { return {p[0], p[1], p[2]}; }

// A product rounded on its own, identically on host and device and at every
// call site: nvcc fuses multiply-adds (FMA) unless told not to, and so does
// GCC (-ffp-contract=fast) in code compiled for FMA, such as the CPU's AVX2
// copy of the clip loop (cpu/isa.h), each site its own way. kNN promises
// bitwise identical distances (hence identical tie-breaking) on CPU and
// CUDA, and the start tetrahedron's choice (det_rn) must come out alike on
// both (a kNN search compiled inside that loop would otherwise rank a
// neighbour differently from the kNN pass). On the host an empty
// asm that takes the product in a register keeps it from being fused into
// an addition.
template <typename F>
TV_HD F held_product(F product) {
#if !defined(__CUDA_ARCH__) && (defined(__x86_64__) || defined(__i386__)) && defined(__GNUC__)
  __asm__("" : "+x"(product));
#elif !defined(__CUDA_ARCH__) && defined(__aarch64__) && defined(__GNUC__)
  __asm__("" : "+w"(product));
#endif
  return product;
}
TV_HD float mul_rn(float a, float b) {
#if defined(__CUDA_ARCH__)
  return __fmul_rn(a, b);
#else
  return held_product(a * b);
#endif
}
TV_HD double mul_rn(double a, double b) {
#if defined(__CUDA_ARCH__)
  return __dmul_rn(a, b);
#else
  return held_product(a * b);
#endif
}
template <typename T>  // other scalars (double-double): their own product
TV_HD T mul_rn(T a, T b) {
  return a * b;
}
// |v|^2 rounded the same wherever it is computed: the thread cell recomputes
// a vertex's in several places and the warp cell caches it, and nvcc fuses
// each site's multiply-adds its own way; an ulp there moved the radius of
// security by one neighbour between the two cells (CUDA test).
template <typename T>
TV_HD T squared_norm(Vec3<T> v) {
  return (mul_rn(v.x, v.x) + mul_rn(v.y, v.y)) + mul_rn(v.z, v.z);
}
template <typename T>
TV_HD T squared_distance(Vec3<T> a, Vec3<T> b) {
  const T dx = a.x - b.x, dy = a.y - b.y, dz = a.z - b.z;
  return (mul_rn(dx, dx) + mul_rn(dy, dy)) + mul_rn(dz, dz);
}

// *word |= bits from many threads at once. The word is read first, so the
// threads that find their bits set already do not contend for it.
TV_HD void set_bits(int32_t* word, int32_t bits) {
#if defined(__CUDA_ARCH__)
  if ((*reinterpret_cast<volatile int32_t*>(word) & bits) != bits) atomicOr(word, bits);
#else
  if ((__atomic_load_n(word, __ATOMIC_RELAXED) & bits) != bits) __atomic_fetch_or(word, bits, __ATOMIC_RELAXED);
#endif
}

// ++*word from many threads at once.
TV_HD void atomic_increment(int32_t* word) {
#if defined(__CUDA_ARCH__)
  atomicAdd(word, 1);
#else
  __atomic_fetch_add(word, 1, __ATOMIC_RELAXED);
#endif
}

// *word += amount from many threads at once; returns the value before.
TV_HD unsigned long long fetch_add(unsigned long long* word, unsigned long long amount) {
#if defined(__CUDA_ARCH__)
  return atomicAdd(word, amount);
#else
  return __atomic_fetch_add(word, amount, __ATOMIC_RELAXED);
#endif
}

// list[(*count)++] = value if `keep`, from many threads at once; the order
// of the list is not defined. A warp's values go in lane order with one
// atomic add per warp (not one per value: a pass can fail 700K cells).
TV_HD void append_if(bool keep, int32_t value, int32_t* list, int32_t* count) {
#if defined(__CUDA_ARCH__)
  const unsigned active = __activemask();
  const unsigned keeping = __ballot_sync(active, keep);
  if (keeping == 0u) return;
  const unsigned lane = threadIdx.x & 31u;  // 1-D blocks of whole warps
  const int leader = __ffs(keeping) - 1;
  int32_t first = 0;
  if (int(lane) == leader) first = atomicAdd(count, __popc(keeping));
  first = __shfl_sync(active, first, leader);
  if (keep) list[first + __popc(keeping & ((1u << lane) - 1u))] = value;
#else
  if (keep) list[__atomic_fetch_add(count, 1, __ATOMIC_RELAXED)] = value;
#endif
}

// A per-item scratch array whose element e lives at data[e * stride]. The CPU
// gives each item a contiguous array (stride 1); the GPU interleaves the
// arrays of a block's threads in shared memory (stride = block size), so a
// warp's 32 lanes always hit 32 different banks, whatever index each reads.
template <typename Slot>
struct StridedArray {
  Slot* data;
  int64_t stride;
  TV_HD Slot& operator[](int64_t e) const { return data[e * stride]; }
};

// Working memory of one item (a kNN query, a cell), handed out by the
// executor: `lanes` items share the region at `base`, each array interleaved
// across them (this item is `lane`). Arrays are carved in order by take().
struct ScratchArena {
  unsigned char* base;
  int64_t lane, lanes;
  int64_t used = 0;  // bytes per lane handed out so far

  // Bytes per lane that take<Slot>(count) uses (16-byte aligned regions).
  template <typename Slot>
  TV_HD static constexpr int64_t bytes(int64_t count) {
    return (count * int64_t(sizeof(Slot)) + 15) / 16 * 16;
  }
  template <typename Slot>
  TV_HD StridedArray<Slot> take(int64_t count) {
    Slot* region = reinterpret_cast<Slot*>(base + used * lanes);
    used += bytes<Slot>(count);
    return {region + lane, lanes};
  }
};

// Full unrolling of a loop with a compile-time trip count, or none (nvcc;
// host compilers unroll on their own judgement).
#if defined(__CUDACC__)
#define TV_UNROLL _Pragma("unroll")
#define TV_NO_UNROLL _Pragma("unroll 1")
#else
#define TV_UNROLL
#define TV_NO_UNROLL
#endif

// Index of the lowest set bit (bits != 0) and number of set bits.
TV_HD int lowest_bit(uint32_t bits) {
#if defined(__CUDA_ARCH__)
  return __ffs(bits) - 1;
#else
  return __builtin_ctz(bits);
#endif
}
TV_HD int bit_count(uint32_t bits) {
#if defined(__CUDA_ARCH__)
  return __popc(bits);
#else
  return __builtin_popcount(bits);
#endif
}

// Square root (correctly rounded on both backends), 0 for x <= 0.
TV_HD float sqrt_of(float x) { return x > 0.0f ? sqrtf(x) : 0.0f; }
TV_HD double sqrt_of(double x) { return x > 0.0 ? sqrt(x) : 0.0; }
// x / y, approximate on the GPU (for estimates, not results).
TV_HD float estimate_divide(float x, float y) {
#if defined(__CUDA_ARCH__)
  return __fdividef(x, y);
#else
  return x / y;
#endif
}
// 1 / sqrt(x), approximate on the GPU (for estimates, not results).
TV_HD float rsqrt_of(float x) {
#if defined(__CUDA_ARCH__)
  return rsqrtf(x);
#else
  return 1.0f / sqrtf(x);
#endif
}

TV_HD double rsqrt_of(double x) {
#if defined(__CUDA_ARCH__)
  return rsqrt(x);
#else
  return 1.0 / sqrt(x);
#endif
}

// The bits of a float, and the float of some bits. memcpy is a register
// move on both compilers (nvcc and GCC), and well defined.
TV_HD uint32_t float_bits(float x) {
  uint32_t bits;
  memcpy(&bits, &x, sizeof bits);
  return bits;
}
TV_HD float bits_float(uint32_t bits) {
  float x;
  memcpy(&x, &bits, sizeof x);
  return x;
}

template <typename T>
TV_HD T min_of(T a, T b) { return a < b ? a : b; }
template <typename T>
TV_HD T max_of(T a, T b) { return a < b ? b : a; }
// Whether T is a pack of scalars (host_packs.h) rather than one scalar.
template <typename T>
struct IsPack : std::false_type {};

// a if `condition`, else b: the scalar form of a pack's lane-by-lane select
// (host_packs.h), so that formulas written with it run on both.
template <typename T>
TV_HD T select(bool condition, T a, T b) { return condition ? a : b; }

}  // namespace core
}  // namespace torchvor
