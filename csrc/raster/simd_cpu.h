#pragma once
// Explicit vectors for the CPU rasterizer's two hot loops: the per-pixel alpha of a
// Gaussian over a tile row (an exp per pixel) and the features-only channel accumulation.
// GCC/Clang vector extensions, not intrinsics: AVX2 registers with -march=x86-64-v3 and
// register pairs without. GCC 12 leaves the equivalent scalar loops unvectorised (glibc's
// expf has no vector form there, and nested channel loops get unroll-and-jammed with the
// accumulators in memory).
#include <cstdint>
#include <cstring>

namespace tiger {
namespace simd {

// The register width of the build: 32 bytes with AVX, else 16 (SSE; TIGER_PORTABLE=1), where
// 32-byte vectors would be split and passed through memory.
#if defined(__AVX__)
constexpr int kVecBytes = 32;
#else
constexpr int kVecBytes = 16;
#endif

// (The attribute must sit on a non-dependent typedef: on a template alias GCC drops it.)
typedef float VecF __attribute__((vector_size(kVecBytes)));
typedef double VecD __attribute__((vector_size(kVecBytes)));
typedef int32_t VecI __attribute__((vector_size(kVecBytes)));

template <typename T>
struct VecOf;
template <>
struct VecOf<float> {
  using type = VecF;
};
template <>
struct VecOf<double> {
  using type = VecD;
};
template <typename T>
using Vec = typename VecOf<T>::type;

template <typename T>
constexpr int kLanes = int(sizeof(Vec<T>) / sizeof(T));

template <typename T>
inline Vec<T> load(const T* p) {
  Vec<T> v;
  std::memcpy(&v, p, sizeof v);
  return v;
}

template <typename T>
inline void store(T* p, const Vec<T>& v) {
  std::memcpy(p, &v, sizeof v);
}

template <typename T>
inline Vec<T> broadcast(T x) {
  return Vec<T>{} + x;
}

// {0, 1, ..., lanes - 1}
template <typename T>
inline Vec<T> iota() {
  Vec<T> v;
  for (int l = 0; l < kLanes<T>; ++l) v[l] = T(l);
  return v;
}

// exp(x) for a vector of floats: Cody-Waite reduction x = n ln2 + r with |r| <= ln2/2, a degree-6
// minimax polynomial for e^r (about 1 ulp), and 2^n written into the exponent bits.
// x is clamped to [-87, 88] so 2^n stays a normal float.
inline VecF exp(VecF x) {
  x = x < -87.0f ? broadcast(-87.0f) : x;
  x = x > 88.0f ? broadcast(88.0f) : x;
  // floor(y) as trunc(y + 128) - 128: y + 128 > 0 on the clamped range.
  const VecI n = __builtin_convertvector(x * 1.44269504088896341f + 128.5f, VecI) - 128;
  const VecF nf = __builtin_convertvector(n, VecF);
  VecF r = x - nf * 0.693359375f;  // ln2 in two parts: nf * hi is exact
  r = r + nf * 2.12194440e-4f;
  VecF p = broadcast(1.9875691500e-4f);
  p = p * r + 1.3981999507e-3f;
  p = p * r + 8.3334519073e-3f;
  p = p * r + 4.1665795894e-2f;
  p = p * r + 1.6666665459e-1f;
  p = p * r + 5.0000001201e-1f;
  p = p * r * r + r + 1.0f;
  return p * (VecF)((n + 127) << 23);
}

// out[c] += sum_{i<n} w[i] * src[i][c] for c in [c0, c0 + NV * lanes): the NV accumulators
// stay in registers while the pixel list streams past.
template <int NV, typename T>
inline void weighted_sum_block(const T* const* src, const T* w, int n, int64_t c0, T* out) {
  constexpr int L = kLanes<T>;
  Vec<T> acc[NV] = {};
  for (int i = 0; i < n; ++i) {
    const Vec<T> wi = broadcast(w[i]);
    const T* v = src[i] + c0;
    for (int j = 0; j < NV; ++j) acc[j] += wi * load(v + j * L);
  }
  for (int j = 0; j < NV; ++j) store(out + c0 + j * L, load(out + c0 + j * L) + acc[j]);
}

template <int R, typename T>
inline void weighted_sum_tail(const T* const* src, const T* w, int n, int64_t c0, T* out) {
  T acc[R] = {};
  for (int i = 0; i < n; ++i)
    for (int c = 0; c < R; ++c) acc[c] += w[i] * src[i][c0 + c];
  for (int c = 0; c < R; ++c) out[c0 + c] += acc[c];
}

// out[c] += sum_{i<n} w[i] * src[i][c] for every c < C (src rows hold C values each).
template <typename T>
inline void weighted_sum(const T* const* src, const T* w, int n, int64_t C, T* out) {
  constexpr int64_t L = kLanes<T>;
  int64_t c0 = 0;
  for (; C - c0 >= 4 * L; c0 += 4 * L) weighted_sum_block<4>(src, w, n, c0, out);
  for (; C - c0 >= L; c0 += L) weighted_sum_block<1>(src, w, n, c0, out);
  switch (C - c0) {  // fewer channels than a vector: fixed-size scalar accumulators
    case 1: return weighted_sum_tail<1>(src, w, n, c0, out);
    case 2: return weighted_sum_tail<2>(src, w, n, c0, out);
    case 3: return weighted_sum_tail<3>(src, w, n, c0, out);
    case 4: return weighted_sum_tail<4>(src, w, n, c0, out);
    case 5: return weighted_sum_tail<5>(src, w, n, c0, out);
    case 6: return weighted_sum_tail<6>(src, w, n, c0, out);
    case 7: return weighted_sum_tail<7>(src, w, n, c0, out);
    default: return;
  }
}

}  // namespace simd
}  // namespace tiger
