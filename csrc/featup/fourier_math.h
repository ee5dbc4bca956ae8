#pragma once
// The per-channel formula of tiger::fourier_layer_norm (fourier.h), shared by the CPU and CUDA
// kernels so that both round the same way.
#include <cmath>
#include <cstdint>

#include "common/macros.h"
#include "featup/fourier.h"

namespace tiger {
namespace featup {

// a * b rounded to T, never contracted into a fused multiply-add with the following sum: the
// PyTorch composition multiplies and adds in separate kernels, and at arguments of ~10^4 radians
// an FMA moves the phase by a float32 ulp of the product (~1e-3). The host build contracts
// (-ffp-contract=fast with FMA), hence the volatile there.
template <typename T>
TIGER_HD T product_rn(T a, T b) {
#ifdef TIGER_DEVICE_CODE
  if constexpr (sizeof(T) == 4) {
    return __fmul_rn(a, b);
  } else {
    return __dmul_rn(a, b);
  }
#else
  volatile T p = a * b;
  return p;
#endif
}

// sin and cos of a. The CUDA build uses --use_fast_math, whose sinf/cosf are the hardware
// approximations, accurate only near [-pi, pi]; float arguments here reach ~10^4 radians, so
// they are first reduced by 2*pi (Cody-Waite, three-part constant: exact reduction for
// |a| < ~10^5), then evaluated on [-pi, pi].
template <typename T>
TIGER_HD void sin_cos(T a, T* s, T* c) {
#ifdef TIGER_DEVICE_CODE
  if constexpr (sizeof(T) == 4) {
    const float k = rintf(a * 0.15915494309189535f);
    float r = fmaf(-k, 6.28318548202514648f, a);  // 2*pi rounded to float
    r = fmaf(-k, -1.74845553e-7f, r);              // 2*pi minus that, in two more parts
    r = fmaf(-k, -7.10542736e-15f, r);
    __sincosf(r, s, c);
  } else {
    sincos(a, s, c);
  }
#else
  *s = std::sin(a);
  *c = std::cos(a);
#endif
}

// What channel c (< C = 10F + 3) reads: input 0..4, frequency (-1 for the colour channels) and
// kind (0 sin, 1 cos, 2 colour).
struct FourierChannel {
  int input, freq, kind;
};

TIGER_HD FourierChannel fourier_channel(int c, int n_freqs) {
  const int half = kFourierInputs * n_freqs;
  if (c >= 2 * half) return {2 + (c - 2 * half), -1, 2};
  const int m = c < half ? c : c - half;
  return {m % kFourierInputs, m / kFourierInputs, c < half ? 0 : 1};
}

// v[i] for a run-time i < 5 without indexing (keeps a pixel's inputs in registers on CUDA).
template <typename T>
TIGER_HD T select_input(const T* v, int i) {
  T r = v[0];
#ifdef TIGER_DEVICE_CODE
#pragma unroll
#endif
  for (int j = 1; j < kFourierInputs; ++j) r = i == j ? v[j] : r;
  return r;
}

// The phase a_c of Fourier channel c (kind 0 or 1) of a pixel with inputs v[5].
template <typename T>
TIGER_HD T fourier_phase(const T* v, const T* freqs, const T* phase, const FourierChannel& ch, int c) {
  return product_rn(select_input(v, ch.input), freqs[ch.freq]) + phase[c];
}

}  // namespace featup
}  // namespace tiger
