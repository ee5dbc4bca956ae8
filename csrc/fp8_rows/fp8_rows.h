#pragma once
// Launchers of the CUDA fp8_rows kernels (fp8_rows_cuda.cu; raw pointers, no torch headers).
#include <cstdint>

namespace tiger {
namespace fp8_rows {

constexpr float kE4M3Max = 448.f;  // largest finite float8_e4m3fn

// x: M rows of in_cols = (geglu ? 2 : 1)·cols elements (row-major, contiguous); q: M × cols
// bytes (float8_e4m3fn), scale: M floats (formulas in ops.cpp).
template <typename T>
void launch_quantize_rows(const T* x, int64_t M, int64_t cols, bool geglu, unsigned char* q, float* scale,
                          void* stream);

// y [M, F] = x[:, :F]·gelu(x[:, F:]) for x [M, 2F] (row-major, contiguous).
template <typename T>
void launch_geglu(const T* x, int64_t M, int64_t F, T* y, void* stream);

}  // namespace fp8_rows
}  // namespace tiger
