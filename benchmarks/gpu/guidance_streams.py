"""How the CSD guidance step's parts share one GPU: InstructPix2Pix and MVDream one after the
other on one stream, MVDream beside InstructPix2Pix on a high-priority side stream
(``CSDGuidance``'s default), that side stream at normal priority, and InstructPix2Pix's 4 views as two halves on two streams
(alone and beside MVDream). The side streams are drawn once: graphs are captured per stream. Full-size random-weight models as the loaders build them on CUDA
(bf16, fused norms, channels-last, default model kernels, CUDA graphs), camera pool (cached
image condition), renders of 512². The decision record of ``CSDGuidance.concurrent``.

Prints ms per call (median of CUDA-event times; the end event waits for every stream) and, per
CSD row, the step averaged over the λ schedule (MVDream on the first 75 % of the steps).

    python -m benchmarks.gpu.guidance_streams            # CUDA only, about a minute
"""
from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path
from typing import Callable

import torch

from benchmarks.common import cuda_time_ms, print_table
from benchmarks.guidance import build_models, ring, tokenizer
from benchmarks.guidance_floor import DEFAULT, MV_FRACTION, make_guidances
from tiger.edit.csd import CSDGuidance
from tiger.edit.guidance.base import ViewBatch


def on_streams(parts: list[tuple["torch.cuda.Stream", Callable[[], object]]]) -> Callable[[], None]:
    """A call that launches each part on its stream (after the current stream's work) and joins them."""
    def run() -> None:
        main = torch.cuda.current_stream()
        for stream, fn in parts:
            stream.wait_stream(main)
            with torch.cuda.stream(stream):
                fn()
        for stream, _ in parts:
            main.wait_stream(stream)
    return run


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--reps", type=int, default=20)
    ap.add_argument("--render", type=int, default=512)
    args = ap.parse_args()
    if not torch.cuda.is_available():
        raise SystemExit("benchmarks.gpu.guidance_streams needs CUDA")
    torch.manual_seed(0)
    ip_models, mv_models = build_models("full", "cuda", torch.bfloat16, tokenizer(Path(tempfile.mkdtemp())),
                                        fused_norms=True)
    ip, mv = make_guidances(ip_models, mv_models, graph=True, size="full", kernels=DEFAULT)
    res = args.render
    renders = torch.rand(4, 3, res, res, device="cuda")
    originals = torch.rand(4, 3, res, res, device="cuda")
    cams = ring(4, res)

    def views(sl: slice = slice(0, 4), step: int = 0) -> ViewBatch:
        return ViewBatch(cameras=cams[sl], originals=originals[sl], view_ids=torch.arange(4)[sl], step=step,
                         total_steps=4, object_center=torch.zeros(3))

    timer = lambda fn: cuda_time_ms(fn, iters=args.reps, warmup=3)  # noqa: E731
    main_stream = torch.cuda.current_stream()
    s1, s2 = torch.cuda.Stream(), torch.cuda.Stream()
    normal = torch.cuda.Stream(priority=0)
    halves = [(main_stream, lambda: ip.grad(renders[:2], views(slice(0, 2)))),
              (s2, lambda: ip.grad(renders[2:], views(slice(2, 4))))]
    sequential = CSDGuidance(ip, mv, concurrent=False)
    concurrent = CSDGuidance(ip, mv)
    normal_priority = CSDGuidance(ip, mv)
    normal_priority._side_stream = lambda device: normal  # instead of the high-priority side stream
    rows: list[dict] = []

    def record(row: dict) -> None:  # printed as it is measured: a hang still leaves the rows before it
        print(json.dumps(row), flush=True)
        rows.append(row)

    ip_ms = timer(lambda: ip.grad(renders, views()))
    record({"what": "InstructPix2Pix, 4 views, one stream", "ms": ip_ms})
    record({"what": "InstructPix2Pix, 2 + 2 views on two streams",
                 "ms": timer(on_streams(halves))})
    mv_ms = timer(lambda: mv.grad(renders, views()))
    record({"what": "MVDream alone", "ms": mv_ms})
    for name, csd in (("CSD, MVDream after InstructPix2Pix (one stream)", sequential),
                      ("CSD, MVDream beside InstructPix2Pix (high-priority side stream; default)", concurrent),
                      ("CSD, MVDream beside, side stream at normal priority", normal_priority)):
        both = timer(lambda: csd.grad(renders, views()))
        record({"what": name, "ms": both, "step_ms": MV_FRACTION * both + (1 - MV_FRACTION) * ip_ms})
    three = on_streams([(s1, lambda: mv.grad(renders, views()))] + halves)
    both = timer(three)
    record({"what": "MVDream beside InstructPix2Pix's 2 + 2 views (three streams)", "ms": both,
                 "step_ms": MV_FRACTION * both + (1 - MV_FRACTION) * rows[1]["ms"]})
    meta = {"device": torch.cuda.get_device_name(), "torch": torch.__version__, "render": res,
            "peak_GiB": torch.cuda.max_memory_allocated() / 2**30}
    print_table(rows, title=f"guidance calls on one GPU (ms; step_ms: averaged over the λ schedule), {meta}")


if __name__ == "__main__":
    main()
