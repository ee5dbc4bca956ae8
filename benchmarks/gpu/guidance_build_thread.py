"""Does building the CSD guidance in another thread slow its first steps? (``docs/BENCHMARKS.md``,
"`tiger edit` end to end"; raw ``benchmarks/gpu/results/guidance_build_thread_h100.txt``: no, only
a machine's first process is slow.) One variant per process, so that no thread's cuDNN/cuBLAS
state carries over:

- ``main``: ``build_guidance`` in this thread (models loaded, guidances built, then the steps);
- ``bg``: ``build_guidance`` in a background thread (``tiger.utils.threads.in_background``), as
  ``tiger edit`` does, then the steps here.

Prints the build time, the first step (warm-up and CUDA-graph capture of both guidances), the
second, and the mean of steps 3-12 (pooled views, 4 x 512², new pool ids every step as at the
start of an edit). Run the variants alternately (main bg main bg) so a cold first process shows as
such. Needs full-size models in ``$TIGER_MODELS`` (``python -m benchmarks.gpu.write_random_models
DIR --only ip2p mvdream``).

    python -m benchmarks.gpu.guidance_build_thread main|bg       # CUDA only
"""
from __future__ import annotations

import sys
import time

import torch


def main(argv: list[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if len(args) != 1 or args[0] not in ("main", "bg"):
        raise SystemExit("usage: python -m benchmarks.gpu.guidance_build_thread main|bg")
    if not torch.cuda.is_available():
        raise SystemExit("benchmarks.gpu.guidance_build_thread needs CUDA")
    from benchmarks.guidance import ring
    from tiger.edit.build import build_guidance
    from tiger.edit.guidance.base import ViewBatch
    from tiger.utils.threads import in_background

    variant = args[0]
    t0 = time.perf_counter()

    def build():
        return build_guidance("ip2p+mvdream", "make it look like a tiger", device=torch.device("cuda"), seed=0,
                              mvdream_kwargs={"lazy": False})

    guidance = build() if variant == "main" else in_background(build, "tiger-edit-models")()
    torch.cuda.synchronize()
    t_build = time.perf_counter() - t0
    renders = torch.rand(4, 3, 512, 512, device="cuda")
    cams = ring(4, 512)
    times = []
    for step in range(12):
        views = ViewBatch(cameras=cams, originals=torch.rand(4, 3, 512, 512, device="cuda"),
                          view_ids=torch.arange(4) + 4 * step, step=step, total_steps=1200,
                          object_center=torch.zeros(3))
        t = time.perf_counter()
        guidance.grad(renders, views)
        torch.cuda.synchronize()
        times.append(time.perf_counter() - t)
    print(f"{variant}: build {t_build:.2f} s; first step {times[0]:.2f} s, second {times[1]:.2f} s, "
          f"steps 3-12 {1e3 * sum(times[2:]) / 10:.1f} ms each")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
