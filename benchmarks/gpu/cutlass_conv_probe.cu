// Probe: can a CUTLASS 3 SM90 implicit-GEMM convolution (TMA + warpgroup MMA) match cuDNN on the
// VAE encoder's 3x3 convolutions (channels-last bf16)? It is what a convolution with the GroupNorm
// apply + SiLU in its prologue would be built on (benchmarks/gpu/NOTES.md). Times a few tile
// configurations and checks each against CUTLASS's reference convolution; cuDNN's figures for the
// same shapes come from benchmarks/gpu/cudnn_conv_time.py in the same call. Not part of the
// package; raw: benchmarks/gpu/results/cutlass_conv_vs_cudnn_h100.txt.
//
//   pip download nvidia-cutlass==4.2.0 --no-deps && unzip nvidia_cutlass-*.whl -d cutlass
//   S=cutlass/cutlass_library/source
//   nvcc -std=c++17 -O3 -arch=sm_90a --expt-relaxed-constexpr -I$S/include -I$S/tools/util/include \
//        benchmarks/gpu/cutlass_conv_probe.cu -o conv_probe && ./conv_probe
//
// CUTLASS 4.2 offers only the non-persistent warp-specialized schedule for SM90 convolutions
// (its cooperative and ping-pong schedules static_assert "Persistent schedules not support for conv yet").
#include <cstdio>
#include <algorithm>
#include <vector>
#include "cutlass/cutlass.h"
#include "cute/tensor.hpp"
#include "cutlass/kernel_hardware_info.hpp"
#include "cutlass/conv/convolution.h"
#include "cutlass/conv/convnd_problem_shape.hpp"
#include "cutlass/tensor_ref.h"
#include "cutlass/conv/dispatch_policy.hpp"
#include "cutlass/conv/collective/collective_builder.hpp"
#include "cutlass/epilogue/collective/collective_builder.hpp"
#include "cutlass/conv/device/conv_universal_adapter.hpp"
#include "cutlass/conv/kernel/conv_universal.hpp"
#include "cutlass/util/device_memory.h"
#include "cutlass/util/reference/device/convolution.h"
#include "cutlass/util/reference/device/tensor_compare.h"

using namespace cute;
using Elem = cutlass::bfloat16_t;
constexpr int Align = 8;
using LayoutA = cutlass::layout::TensorNHWC;
using LayoutB = cutlass::layout::TensorNHWC;  // KRSC
using LayoutC = cutlass::layout::TensorNHWC;
constexpr cutlass::conv::Operator ConvOp = cutlass::conv::Operator::kFprop;

template <class TileShape, class ClusterShape, class MainSched, class EpiSched>
struct Config {
  using CollectiveEpilogue = typename cutlass::epilogue::collective::CollectiveBuilder<
      cutlass::arch::Sm90, cutlass::arch::OpClassTensorOp, TileShape, ClusterShape,
      cutlass::epilogue::collective::EpilogueTileAuto, float, float, Elem, LayoutC, Align, Elem, LayoutC, Align,
      EpiSched>::CollectiveOp;
  using CollectiveMainloop = typename cutlass::conv::collective::CollectiveBuilder<
      cutlass::arch::Sm90, cutlass::arch::OpClassTensorOp, ConvOp, Elem, LayoutA, Align, Elem, LayoutB, Align, float,
      TileShape, ClusterShape,
      cutlass::conv::collective::StageCountAutoCarveout<static_cast<int>(sizeof(typename CollectiveEpilogue::SharedStorage))>,
      MainSched>::CollectiveOp;
  using ProblemShape = cutlass::conv::ConvProblemShape<ConvOp, CollectiveMainloop::DispatchPolicy::NumSpatialDimensions>;
  using Kernel = cutlass::conv::kernel::ConvUniversal<ProblemShape, CollectiveMainloop, CollectiveEpilogue>;
  using Conv = cutlass::conv::device::ConvUniversalAdapter<Kernel>;
};

struct Problem { int n, h, w, c, k; };

__global__ void fill(Elem* p, size_t n, uint32_t seed, float scale) {
  for (size_t i = blockIdx.x * size_t(blockDim.x) + threadIdx.x; i < n; i += size_t(gridDim.x) * blockDim.x) {
    uint32_t h = uint32_t(i) * 2654435761u ^ (seed * 40503u + uint32_t(i >> 32));
    h ^= h >> 15; h *= 2246822519u; h ^= h >> 13; h *= 3266489917u; h ^= h >> 16;
    p[i] = Elem(scale * (float(h & 0xffffff) / 8388608.f - 1.f));
  }
}

template <class Cfg>
void run(const char* name, const Problem& pb, Elem* A, Elem* B, Elem* C, Elem* D, Elem* Dref, int iters) {
  using Conv = typename Cfg::Conv;
  using ProblemShape = typename Cfg::ProblemShape;
  using StrideC = typename Conv::ConvKernel::StrideC;
  using StrideD = typename Conv::ConvKernel::StrideD;
  ProblemShape ps(cutlass::conv::Mode::kCrossCorrelation, {pb.n, pb.h, pb.w, pb.c}, {pb.k, 3, 3, pb.c}, {1, 1},
                  {1, 1}, {1, 1}, {1, 1}, 1);
  StrideC sc;
  StrideD sd;
  cute::for_each(cute::make_seq<cute::rank<0>(StrideC{})>{}, [&](auto i) { cute::get<0, i>(sc) = ps.stride_C[ProblemShape::RankT - 2 - i]; });
  cute::for_each(cute::make_seq<cute::rank<0>(StrideD{})>{}, [&](auto i) { cute::get<0, i>(sd) = ps.stride_C[ProblemShape::RankT - 2 - i]; });
  typename Conv::Arguments args{ps, {A, B}, {{1.f, 0.f}, C, sc, D, sd}};
  Conv conv;
  if (conv.can_implement(args) != cutlass::Status::kSuccess) { printf("%-34s cannot implement\n", name); return; }
  size_t ws = Conv::get_workspace_size(args);
  cutlass::device_memory::allocation<uint8_t> workspace(ws);
  if (conv.initialize(args, workspace.get()) != cutlass::Status::kSuccess) { printf("%-34s init failed\n", name); return; }
  for (int i = 0; i < 3; ++i) conv.run();
  cudaEvent_t a, b;
  cudaEventCreate(&a); cudaEventCreate(&b);
  std::vector<float> t;
  for (int i = 0; i < iters; ++i) {
    cudaEventRecord(a); conv.run(); cudaEventRecord(b); cudaEventSynchronize(b);
    float ms; cudaEventElapsedTime(&ms, a, b); t.push_back(ms);
  }
  std::sort(t.begin(), t.end());
  const double flop = 2.0 * pb.n * pb.h * pb.w * double(pb.k) * 9 * pb.c;
  const size_t nD = size_t(pb.n) * pb.h * pb.w * pb.k;
  bool ok = cutlass::reference::device::BlockCompareRelativelyEqual(Dref, D, nD, Elem(0.02f), Elem(0.05f));
  printf("%-34s %8.4f ms  %6.0f TFLOP/s  matches reference: %s  (%s)\n", name, t[t.size() / 2],
         flop / (t[t.size() / 2] * 1e-3) / 1e12, ok ? "yes" : "NO", cudaGetErrorString(cudaGetLastError()));
}

int main() {
  using namespace cutlass::conv;
  std::vector<Problem> problems = {{4, 512, 512, 128, 128}, {4, 256, 256, 256, 256}, {4, 128, 128, 512, 512}, {12, 64, 64, 320, 320}};
  for (const auto& pb : problems) {
    const size_t nA = size_t(pb.n) * pb.h * pb.w * pb.c, nB = size_t(pb.k) * 9 * pb.c, nD = size_t(pb.n) * pb.h * pb.w * pb.k;
    cutlass::device_memory::allocation<Elem> A(nA), B(nB), C(nD), D(nD), Dref(nD);
    fill<<<1024, 256>>>(A.get(), nA, 1, 1.f);
    fill<<<1024, 256>>>(B.get(), nB, 2, 0.05f);
    fill<<<1024, 256>>>(C.get(), nD, 3, 1.f);
    cutlass::conv::Conv2dProblemSize size(pb.n, pb.h, pb.w, pb.c, pb.k, 3, 3, pb.h, pb.w, 1, 1, 1, 1, 1, 1,
                                          cutlass::conv::Mode::kCrossCorrelation);
    cutlass::TensorRef<Elem, LayoutA> rA(A.get(), LayoutA::packed({pb.n, pb.h, pb.w, pb.c}));
    cutlass::TensorRef<Elem, LayoutB> rB(B.get(), LayoutB::packed({pb.k, 3, 3, pb.c}));
    cutlass::TensorRef<Elem, LayoutC> rC(C.get(), LayoutC::packed({pb.n, pb.h, pb.w, pb.k}));
    cutlass::TensorRef<Elem, LayoutC> rD(Dref.get(), LayoutC::packed({pb.n, pb.h, pb.w, pb.k}));
    cutlass::reference::device::Conv2dFprop<Elem, LayoutA, Elem, LayoutB, Elem, LayoutC, float, float>(size, rA, rB, rC, rD, 1.f, 0.f);
    cudaDeviceSynchronize();
    printf("== %d x %d x %d x %d -> %d (NHWC bf16, 3x3, pad 1)\n", pb.n, pb.h, pb.w, pb.c, pb.k);
    run<Config<Shape<_128, _128, Shape<_64>>, Shape<_1, _1, _1>, KernelImplicitTmaWarpSpecializedSm90, cutlass::epilogue::TmaWarpSpecialized>>(
        "128x128x64 cluster 1x1", pb, A.get(), B.get(), C.get(), D.get(), Dref.get(), 20);
    run<Config<Shape<_128, _256, Shape<_64>>, Shape<_1, _1, _1>, KernelImplicitTmaWarpSpecializedSm90, cutlass::epilogue::TmaWarpSpecialized>>(
        "128x256x64 cluster 1x1", pb, A.get(), B.get(), C.get(), D.get(), Dref.get(), 20);
    run<Config<Shape<_128, _128, Shape<_64>>, Shape<_2, _1, _1>, KernelImplicitTmaWarpSpecializedSm90, cutlass::epilogue::TmaWarpSpecialized>>(
        "128x128x64 cluster 2x1", pb, A.get(), B.get(), C.get(), D.get(), Dref.get(), 20);
    run<Config<Shape<_64, _256, Shape<_64>>, Shape<_1, _1, _1>, KernelImplicitTmaWarpSpecializedSm90, cutlass::epilogue::TmaWarpSpecialized>>(
        "64x256x64 cluster 1x1", pb, A.get(), B.get(), C.get(), D.get(), Dref.get(), 20);
  }
  return 0;
}
