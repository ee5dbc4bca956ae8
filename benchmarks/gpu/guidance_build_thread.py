"""Does building the CSD guidance in another thread slow its first steps, and what makes a
machine's first process slow? (``docs/BENCHMARKS.md``, "`tiger edit` end to end"; raw
``benchmarks/gpu/results/guidance_build_thread_h100.txt``: the thread makes no difference, only a
machine's first process is slow.) One variant per process, so that no thread's cuDNN/cuBLAS state
carries over:

- ``main``: ``build_guidance`` in this thread (models loaded, guidances built, then the steps);
- ``bg``: ``build_guidance`` in a background thread (``tiger.utils.threads.in_background``), as
  ``tiger edit`` does, then the steps here;
- ``evict``: ``main`` after dropping the CUDA libraries' pages (torch's ``lib`` and the ``nvidia``
  wheels' shared libraries) from the page cache (``posix_fadvise(DONTNEED)``, before torch loads
  them): a cold machine's disk reads, if those are what the first process waits for;
- ``evict_prefetch``: ``evict``, then the same files read ahead (``posix_fadvise(WILLNEED)``) while
  the models load: whether prefetching them at a command's start would hide that wait.

(``CUDA_CACHE_DISABLE=1 python -m ... main`` tests the other suspect, the driver's JIT cache. The
answer, raw ``guidance_cold_start_h100.txt``: the JIT cache; evicting or prefetching the libraries
moves the first step by ~1 s.)
Prints the build time, the first step (warm-up and CUDA-graph capture of both guidances), the
second, and the mean of steps 3-12 (pooled views, 4 x 512², new pool ids every step as at the
start of an edit). Run the variants alternately (main bg main bg) so a cold first process shows as
such. Needs full-size models in ``$TIGER_MODELS`` (``python -m benchmarks.gpu.write_random_models
DIR --only ip2p mvdream``).

    python -m benchmarks.gpu.guidance_build_thread main|bg|evict|evict_prefetch      # CUDA only
"""
from __future__ import annotations

import importlib.util
import os
import sys
import threading
import time
from pathlib import Path

VARIANTS = ("main", "bg", "evict", "evict_prefetch")


def cuda_library_files() -> list[Path]:
    """The shared libraries of torch's CUDA build: ``torch/lib`` and the ``nvidia`` wheels' ``lib``
    folders (cuDNN, cuBLAS, ...), found without importing torch."""
    spec = importlib.util.find_spec("torch")
    if spec is None or spec.origin is None:
        return []
    site = Path(spec.origin).parent.parent
    files = [*(site / "torch" / "lib").glob("*.so*"), *(site / "nvidia").glob("*/lib/*.so*")]
    return sorted(f for f in files if f.is_file())


def advise(files: list[Path], advice: int) -> int:
    """``posix_fadvise(advice)`` over each whole file; returns the bytes advised."""
    total = 0
    for f in files:
        fd = os.open(f, os.O_RDONLY)
        try:
            os.posix_fadvise(fd, 0, 0, advice)
            total += os.fstat(fd).st_size
        finally:
            os.close(fd)
    return total


def main(argv: list[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if len(args) != 1 or args[0] not in VARIANTS:
        raise SystemExit(f"usage: python -m benchmarks.gpu.guidance_build_thread {'|'.join(VARIANTS)}")
    variant = args[0]
    t0 = time.perf_counter()
    note = ""
    if variant.startswith("evict"):  # before torch maps the libraries: mapped pages stay resident
        files = cuda_library_files()
        note = f"; evicted {advise(files, os.POSIX_FADV_DONTNEED) / 2**30:.2f} GiB in {len(files)} files"
        if variant == "evict_prefetch":
            threading.Thread(target=advise, args=(files, os.POSIX_FADV_WILLNEED), daemon=True).start()
    import torch

    if not torch.cuda.is_available():
        raise SystemExit("benchmarks.gpu.guidance_build_thread needs CUDA")
    from benchmarks.guidance import ring
    from tiger.edit.build import build_guidance
    from tiger.edit.guidance.base import ViewBatch
    from tiger.utils.threads import in_background

    def build():
        return build_guidance("ip2p+mvdream", "make it look like a tiger", device=torch.device("cuda"), seed=0,
                              mvdream_kwargs={"lazy": False})

    guidance = in_background(build, "tiger-edit-models")() if variant == "bg" else build()
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
          f"steps 3-12 {1e3 * sum(times[2:]) / 10:.1f} ms each{note}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
