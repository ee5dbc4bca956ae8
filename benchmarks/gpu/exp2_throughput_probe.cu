// Probe: exponentials per second on the SFU, float32 (`ex2.approx.ftz.f32`, one result an
// instruction) against half precision (`ex2.approx.f16x2`, two), the premise of the attention lead
// in benchmarks/gpu/NOTES.md (an attention bound by its softmax's exponentials would compute them
// at half precision: its probabilities are rounded to bfloat16 for the P·V product anyway).
// Each thread runs 8 independent chains; results are summed so nothing is optimised away.
//
//   nvcc -O3 -arch=sm_90a benchmarks/gpu/exp2_throughput_probe.cu -o exp2_probe && ./exp2_probe
#include <cstdio>
#include <cuda_fp16.h>

constexpr int kIters = 4096, kChains = 8;

__global__ void exp2_f32(float* out, float seed) {
  float v[kChains];
#pragma unroll
  for (int c = 0; c < kChains; ++c) v[c] = seed * (threadIdx.x + c) * 1e-7f - 0.5f;
  for (int i = 0; i < kIters; ++i) {
#pragma unroll
    for (int c = 0; c < kChains; ++c) {
      float r;
      asm volatile("ex2.approx.ftz.f32 %0, %1;" : "=f"(r) : "f"(v[c]));
      v[c] = r - 1.5f;  // keeps the chain in (-1.5, -0.5]: no overflow, no denormals
    }
  }
  float s = 0.f;
#pragma unroll
  for (int c = 0; c < kChains; ++c) s += v[c];
  out[blockIdx.x * blockDim.x + threadIdx.x] = s;
}

__global__ void exp2_f16x2(float* out, float seed) {
  __half2 v[kChains];
  const __half2 shift = __float2half2_rn(1.5f);
#pragma unroll
  for (int c = 0; c < kChains; ++c) v[c] = __float2half2_rn(seed * (threadIdx.x + c) * 1e-7f - 0.5f);
  for (int i = 0; i < kIters; ++i) {
#pragma unroll
    for (int c = 0; c < kChains; ++c) {
      unsigned r, a = *reinterpret_cast<unsigned*>(&v[c]);
      asm volatile("ex2.approx.f16x2 %0, %1;" : "=r"(r) : "r"(a));
      v[c] = __hsub2(*reinterpret_cast<__half2*>(&r), shift);
    }
  }
  float s = 0.f;
#pragma unroll
  for (int c = 0; c < kChains; ++c) s += __low2float(v[c]) + __high2float(v[c]);
  out[blockIdx.x * blockDim.x + threadIdx.x] = s;
}

template <typename K>
double rate(K kernel, int blocks, int threads, float* out, double per_instruction) {
  kernel<<<blocks, threads>>>(out, 1.f);  // warm-up
  cudaEvent_t a, b;
  cudaEventCreate(&a);
  cudaEventCreate(&b);
  cudaEventRecord(a);
  for (int r = 0; r < 5; ++r) kernel<<<blocks, threads>>>(out, 1.f + r);
  cudaEventRecord(b);
  cudaEventSynchronize(b);
  float ms = 0.f;
  cudaEventElapsedTime(&ms, a, b);
  const double exps = 5.0 * blocks * threads * double(kIters) * kChains * per_instruction;
  return exps / (ms * 1e-3);
}

int main() {
  int sms = 0;
  cudaDeviceGetAttribute(&sms, cudaDevAttrMultiProcessorCount, 0);
  int clock_khz = 0;
  cudaDeviceGetAttribute(&clock_khz, cudaDevAttrClockRate, 0);
  const int blocks = sms * 8, threads = 256;
  float* out = nullptr;
  cudaMalloc(&out, sizeof(float) * blocks * threads);
  const double f32 = rate(exp2_f32, blocks, threads, out, 1.0);
  const double f16 = rate(exp2_f16x2, blocks, threads, out, 2.0);
  const double per_clk = 1e3 * clock_khz * sms;
  printf("%d SMs at %.0f MHz (max clock attribute)\n", sms, clock_khz / 1e3);
  printf("ex2.approx.ftz.f32 : %.3g exponentials/s (%.1f per SM per clock)\n", f32, f32 / per_clk);
  printf("ex2.approx.f16x2   : %.3g exponentials/s (%.1f per SM per clock), %.2fx float32's\n", f16, f16 / per_clk,
         f16 / f32);
  printf("softmax of the 64² self-attention (96 x 4096² scores): %.3f ms at float32's rate, %.3f ms at f16x2's\n",
         96.0 * 4096 * 4096 / f32 * 1e3, 96.0 * 4096 * 4096 / f16 * 1e3);
  cudaFree(out);
  return cudaGetLastError() == cudaSuccess ? 0 : 1;
}
