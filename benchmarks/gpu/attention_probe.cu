// Standalone probe of tiger::attention_rows' Hopper kernel variants (csrc/attention/attention_sm90a.cu,
// compiled into this file) without torch: InstructPix2Pix's 64² layer (batch x 8 heads x 4096 tokens,
// head dim 40, q/k/v as strided column blocks of one stacked [batch·4096, 960] bf16 matrix), each
// variant's error against float64 on 48 sampled rows, its largest difference from the first variant
// on every row, and its time: eager launches, best of 6 runs of 20 calls by CUDA events. "one"
// launches one variant three times, for Nsight Compute. Built and run on an H100:
//   nvcc -gencode arch=compute_90a,code=sm_90a -std=c++17 -O3 -I csrc benchmarks/gpu/attention_probe.cu -o probe
//   ./probe time [batch]        ./probe one [batch] VARIANT_INDEX
// torch's SDPA timed the same way: python -m benchmarks.gpu.sdpa_event_time.
#include "attention/attention_sm90a.cu"
#include <cstdio>
#include <cstdlib>
#include <cmath>
#include <vector>
#include <random>
#include <algorithm>
#include <string>

using namespace tiger::attention;
typedef cudaError_t (*Launch)(const AttentionParams&, cudaStream_t);
struct Variant { const char* name; Launch fn; };

static Variant variants[] = {
  {"producer x3", launch_ws<3>},
  {"producer x2", launch_ws<2>},
  {"lockstep x2", launch<2>},
  {"lockstep x4", launch<4>},
};
static const int nvar = sizeof(variants) / sizeof(variants[0]);

#define CK(x) do { cudaError_t e = (x); if (e != cudaSuccess) { printf("CUDA error %s at %d\n", cudaGetErrorString(e), __LINE__); exit(1);} } while (0)

static float bf2f(__nv_bfloat16 v) { return __bfloat162float(v); }

int main(int argc, char** argv) {
  const int B = argc > 2 ? atoi(argv[2]) : 12, H = 8, L = 4096, D = 40, W = 3 * H * D;
  std::string mode = argc > 1 ? argv[1] : "time";
  const size_t rows = (size_t)B * L;
  std::vector<__nv_bfloat16> hqkv(rows * W);
  std::mt19937 g(0);
  std::normal_distribution<float> n(0.f, 1.f);
  for (auto& x : hqkv) x = __float2bfloat16(n(g));
  __nv_bfloat16 *qkv, *out, *ref;
  CK(cudaMalloc(&qkv, hqkv.size() * 2));
  CK(cudaMalloc(&out, rows * H * D * 2));
  CK(cudaMalloc(&ref, rows * H * D * 2));
  CK(cudaMemcpy(qkv, hqkv.data(), hqkv.size() * 2, cudaMemcpyHostToDevice));
  AttentionParams p{};
  p.q = qkv; p.k = qkv + H * D; p.v = qkv + 2 * H * D;
  p.q_stride = p.k_stride = p.v_stride = W; p.out_stride = H * D;
  p.L = L; p.heads = H; p.batch = B;
  p.scale_log2 = (float)(1.0 / std::sqrt(40.0) / std::log(2.0));
  cudaStream_t st; CK(cudaStreamCreate(&st));
  if (mode == "one") {  // for ncu: variant argv[3], 3 launches
    int v = atoi(argv[3]);
    for (int i = 0; i < 3; ++i) { p.out = out; CK(variants[v].fn(p, st)); }
    CK(cudaStreamSynchronize(st));
    printf("ran %s\n", variants[v].name);
    return 0;
  }
  // float64 reference on sampled (b, h, row)
  std::vector<int> sb, sh, sr;
  std::mt19937 g2(1);
  for (int i = 0; i < 48; ++i) { sb.push_back(g2() % B); sh.push_back(g2() % H); sr.push_back(g2() % L); }
  std::vector<double> refv(48 * D);
  for (int i = 0; i < 48; ++i) {
    const size_t base = (size_t)sb[i] * L;
    std::vector<double> sc(L);
    double mx = -1e300;
    for (int t = 0; t < L; ++t) {
      double d = 0;
      for (int c = 0; c < D; ++c) d += (double)bf2f(hqkv[(base + sr[i]) * W + sh[i] * D + c]) * bf2f(hqkv[(base + t) * W + H * D + sh[i] * D + c]);
      sc[t] = d / std::sqrt(40.0); mx = std::max(mx, sc[t]);
    }
    double sum = 0; for (int t = 0; t < L; ++t) { sc[t] = std::exp(sc[t] - mx); sum += sc[t]; }
    for (int c = 0; c < D; ++c) { double a = 0; for (int t = 0; t < L; ++t) a += sc[t] * bf2f(hqkv[(base + t) * W + 2 * H * D + sh[i] * D + c]); refv[i * D + c] = a / sum; }
  }
  std::vector<__nv_bfloat16> ho(rows * H * D), hr(rows * H * D);
  cudaEvent_t e0, e1; cudaEventCreate(&e0); cudaEventCreate(&e1);
  for (int v = 0; v < nvar; ++v) {
    p.out = v == 0 ? ref : out;
    CK(cudaMemset(p.out, 0xFF, rows * H * D * 2));
    CK(variants[v].fn(p, st));
    CK(cudaStreamSynchronize(st));
    CK(cudaMemcpy(ho.data(), p.out, ho.size() * 2, cudaMemcpyDeviceToHost));
    if (v == 0) hr = ho;
    double num = 0, den = 0, mdiff = 0; int bad = 0;
    for (int i = 0; i < 48; ++i) for (int c = 0; c < D; ++c) {
      double a = bf2f(ho[((size_t)sb[i] * L + sr[i]) * H * D + sh[i] * D + c]), r = refv[i * D + c];
      num += (a - r) * (a - r); den += r * r;
    }
    for (size_t i = 0; i < ho.size(); ++i) { double d = std::fabs((double)bf2f(ho[i]) - bf2f(hr[i])); if (!(d <= 1e9)) bad++; else mdiff = std::max(mdiff, d); }
    float ms_best = 1e9;
    for (int rep = 0; rep < 7; ++rep) {
      CK(cudaEventRecord(e0, st));
      for (int i = 0; i < 20; ++i) variants[v].fn(p, st);
      CK(cudaEventRecord(e1, st));
      CK(cudaEventSynchronize(e1));
      float ms; cudaEventElapsedTime(&ms, e0, e1); ms /= 20; if (rep > 0) ms_best = std::min(ms_best, ms);
    }
    printf("%-24s B=%d  %.4f ms   rel.err vs f64 %.3e   max|diff| vs first %.3e  nonfinite %d\n", variants[v].name, B, ms_best,
           std::sqrt(num / den), mdiff, bad);
  }
  return 0;
}
