"""How far the guidance step's current op sequence is from its roofline, op by op.

Records every ATen and tiger op of one eager InstructPix2Pix step (camera pool: condition cached)
and one MVDream step (full-size random models, bf16, the package's default model kernels, 4 views
of 512²) with a dispatch mode: its GPU time (its kernels' durations from torch.profiler), its
FLOPs (``torch.utils.flop_counter``'s formulas), the bytes of its tensors (inputs and outputs,
each counted once per op; views cost nothing) and, for attention, its exponentials. Each op's
roofline is the largest of: FLOPs at the bf16 matmul rate, bytes at the DRAM copy rate measured
in the same run, exponentials at the SFU rate (``exp2_throughput_h100.txt``), and one kernel
launch (the shortest kernel a CUDA graph replays back to back, measured too).

Prints, per op family and guidance: measured ms, the roofline's ms and their ratio; then the
CSD step's totals (InstructPix2Pix + 0.75 MVDream, the share of steps MVDream runs):

* **serial roofline**: every op of today's sequence at its own roofline, one after another
  (what faster kernels alone, without fusing ops, could reach);
* **overlap bound**: max(all FLOPs at the matmul rate, all bytes at the copy rate, all
  exponentials at the SFU rate): what fusion and perfect overlap could reach;

against the FLOP floor and issue 30's 1.6x target.

    python -m benchmarks.gpu.guidance_roofline [--top 20]      # CUDA only (about 1 minute)
"""
from __future__ import annotations

import argparse
import collections
import dataclasses
from typing import Any, Callable, Optional

import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_flatten

from benchmarks.common import _addmm_inplace_flops, cuda_copy_bandwidth, cuda_graph_ms, print_table
from benchmarks.guidance import H100_BF16_TFLOPS, ring
from benchmarks.guidance_floor import FLOOR_TARGET, MV_FRACTION, default_cuda_guidances, fixed_draws
from tiger.edit.guidance.base import ViewBatch

EXP_PER_S = 4.16e12  # SFU ex2 per second, H100 (benchmarks/gpu/results/exp2_throughput_h100.txt)
RANGE = "tiger_op#"  # profiler range of recorded op i: RANGE + str(i)
SDPA_OPS = ("_scaled_dot_product_cudnn_attention", "_scaled_dot_product_flash_attention",
            "_scaled_dot_product_efficient_attention")


def family(name: str) -> str:
    """The op family of an op's name (``aten::convolution``, ``tiger::group_norm``, ...)."""
    if "scaled_dot_product" in name:
        return "attention"
    if "convolution" in name:
        return "convolution"
    if any(k in name for k in ("::mm", "::addmm", "::bmm", "::baddbmm", "::linear")):
        return "matmul"
    if "group_norm" in name:
        return "group norm"
    if name.startswith("tiger::"):
        return "tiger other"
    return "aten other"


def _span_bytes(t: torch.Tensor) -> int:
    """Bytes a tensor's elements occupy: numel for dense tensors, the strided span for expanded
    or sliced ones (a broadcast operand is read once)."""
    if t.numel() == 0:
        return 0
    span = 1 + sum((s - 1) * abs(st) for s, st in zip(t.shape, t.stride()))
    return min(t.numel(), span) * t.element_size()


def _tensor_bytes(tree: Any) -> int:
    """Bytes of the CUDA tensors in ``tree`` (args, kwargs or outputs), each tensor once."""
    seen, total = set(), 0
    for t in tree_flatten(tree)[0]:
        if isinstance(t, torch.Tensor) and t.is_cuda:
            key = (t.data_ptr(), tuple(t.shape), tuple(t.stride()))
            if key not in seen:
                seen.add(key)
                total += _span_bytes(t)
    return total


def _is_view(func: Any) -> bool:
    """Whether an op returns a view of an input without writing it (aliases, reshapes)."""
    rets = func._schema.returns
    return bool(rets) and all(r.alias_info is not None and not r.alias_info.is_write for r in rets)


def _exponentials(func: Any, args: tuple) -> int:
    """Softmax exponentials of an attention forward: B·H·Lq·Lk."""
    if not any(k in str(func) for k in SDPA_OPS) or "backward" in str(func):
        return 0
    q, k = args[0], args[1]
    return int(q.shape[0] * q.shape[1] * q.shape[2] * k.shape[2])


@dataclasses.dataclass
class OpRecord:
    """One dispatched op: name (``aten::convolution``), FLOPs, bytes of its tensors, softmax
    exponentials, its first input's shape and its kernels' GPU time."""

    name: str
    flops: float
    bytes: int
    exps: int
    shape: tuple = ()  # of its first tensor argument
    ms: float = 0.0  # GPU time of the op's kernels (profiler)


class OpRecorder(TorchDispatchMode):
    """Sizes every op dispatched below autograd (also the backward's, on the engine's thread) and
    runs it inside a profiler range ``tiger_op#i``, so its kernels can be summed per op."""

    def __init__(self) -> None:
        super().__init__()
        from torch.utils.flop_counter import flop_registry
        from torch.utils.flop_counter import shape_wrapper

        self.formulas = dict(flop_registry)
        self.formulas[torch.ops.aten.addmm_] = shape_wrapper(_addmm_inplace_flops)
        self.records: list[OpRecord] = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if _is_view(func) or func._overloadpacket in (torch.ops.aten.empty, torch.ops.aten.empty_strided):
            return func(*args, **kwargs)  # no kernel: views, uninitialised allocations
        with torch.profiler.record_function(f"{RANGE}{len(self.records)}"):
            out = func(*args, **kwargs)
        formula = self.formulas.get(func._overloadpacket)
        flops = float(formula(*args, **kwargs, out_val=out)) if formula is not None else 0.0
        nbytes = _tensor_bytes((args, kwargs)) + _tensor_bytes(out)
        name = str(func._overloadpacket).replace(".", "::", 1)
        first = next((t for t in tree_flatten(args)[0] if isinstance(t, torch.Tensor)), None)
        shape = tuple(first.shape) if first is not None else ()
        self.records.append(OpRecord(name, flops, nbytes, _exponentials(func, args), shape))
        return out


def record_ops(fn: Callable[[], Any]) -> tuple[list[OpRecord], float]:
    """The ops of one ``fn()`` call with their kernels' GPU time (torch.profiler: exact kernel
    durations, whatever the host's speed), and the GPU time of all kernels the call ran (ms; the
    ops' sum falls short of it only by kernels launched outside any recorded op)."""
    from torch.profiler import ProfilerActivity, profile

    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        with OpRecorder() as rec:
            fn()
        torch.cuda.synchronize()
    events = prof.events()
    for ev in events:
        # the range's own device time is its GPU-side annotation (the span of its kernels): only
        # the kernels of the ops inside it count
        if ev.name.startswith(RANGE) and ev.device_type == torch.autograd.DeviceType.CPU:
            rec.records[int(ev.name[len(RANGE):])].ms += sum(ch.device_time_total for ch in ev.cpu_children) / 1e3
    kernels = sum(ev.device_time / 1e3 for ev in events
                  if ev.device_type == torch.autograd.DeviceType.CUDA and not ev.name.startswith(RANGE))
    return rec.records, kernels


def launch_floor_ms(calls: int = 2000) -> float:
    """ms per kernel of the shortest kernels (a 1-element add) replayed back to back in a CUDA graph."""
    x = torch.zeros(1, device="cuda")
    return cuda_graph_ms(lambda: x.add_(1), calls=calls)


@dataclasses.dataclass
class Rates:
    flops_per_ms: float
    bytes_per_ms: float
    exps_per_ms: float
    launch_ms: float

    def roof(self, r: OpRecord) -> tuple[float, str]:
        """(ms, what bounds it) of one op at its roofline."""
        parts = {"flops": r.flops / self.flops_per_ms, "bytes": r.bytes / self.bytes_per_ms,
                 "exp": r.exps / self.exps_per_ms, "launch": self.launch_ms}
        bound = max(parts, key=parts.get)
        return parts[bound], bound


def summarise(name: str, records: list[OpRecord], span_ms: float, rates: Rates, top: int) -> dict:
    """Print the per-family table of one guidance step; return its totals."""
    fam = collections.defaultdict(lambda: collections.Counter())
    worst: dict[tuple[str, str], collections.Counter] = {}
    for r in records:
        roof, bound = rates.roof(r)
        f = fam[family(r.name)]
        f["ops"] += 1
        f["ms"] += r.ms
        f["roof_ms"] += roof
        f[f"bound_{bound}"] += 1
        f["flops"] += r.flops
        f["bytes"] += r.bytes
        f["exps"] += r.exps
        w = worst.setdefault((r.name, "x".join(map(str, r.shape))), collections.Counter())
        w["n"] += 1
        w["ms"] += r.ms
        w["roof"] += roof
        w[bound] += 1
    rows = []
    for key, f in sorted(fam.items(), key=lambda kv: -kv[1]["ms"]):
        bounds = ", ".join(f"{b[6:]} {n}" for b, n in f.items() if b.startswith("bound_"))
        rows.append({"family": key, "ops": f["ops"], "ms": f"{f['ms']:.2f}", "roofline_ms": f"{f['roof_ms']:.2f}",
                     "x_roofline": f"{f['ms'] / max(f['roof_ms'], 1e-9):.2f}", "TFLOP": f"{f['flops'] / 1e12:.3f}",
                     "GB": f"{f['bytes'] / 1e9:.2f}", "bound by (ops)": bounds})
    total = {k: sum(f[k] for f in fam.values()) for k in ("ops", "ms", "roof_ms", "flops", "bytes", "exps")}
    rows.append({"family": "all", "ops": total["ops"], "ms": f"{total['ms']:.2f}",
                 "roofline_ms": f"{total['roof_ms']:.2f}", "x_roofline": f"{total['ms'] / total['roof_ms']:.2f}",
                 "TFLOP": f"{total['flops'] / 1e12:.3f}", "GB": f"{total['bytes'] / 1e9:.2f}", "bound by (ops)": ""})
    print_table(rows, f"{name}: ms of one step by op family (kernel time per op; roofline per op); "
                      f"all kernels {span_ms:.2f} ms, of which backward ops' "
                      f"{sum(r.ms for r in records if 'backward' in r.name):.2f} ms")
    print(f"  the {top} (op, first input's shape) furthest above their roofline: ms above it, calls, measured ms, "
          "roofline ms, bound")
    ranked = sorted(worst.items(), key=lambda kv: kv[1]["roof"] - kv[1]["ms"])[:top]
    for (op, shape), w in ranked:
        bound = max(("flops", "bytes", "exp", "launch"), key=lambda b: w[b])
        print(f"    {w['ms'] - w['roof']:7.3f}  {op:44s} {shape:22s} {w['n']:3d} {w['ms']:7.3f} {w['roof']:7.3f}  {bound}")
    return total


def main(argv: Optional[list[str]] = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--top", type=int, default=20,
                   help="(op, shape) groups listed per guidance, furthest above their roofline first")
    args = p.parse_args(argv)
    if not torch.cuda.is_available():
        raise SystemExit("benchmarks.gpu.guidance_roofline needs CUDA")
    rates = Rates(flops_per_ms=H100_BF16_TFLOPS * 1e9, bytes_per_ms=cuda_copy_bandwidth() * 1e-3,
                  exps_per_ms=EXP_PER_S * 1e-3, launch_ms=launch_floor_ms())
    print(f"# {torch.cuda.get_device_name(0)}: bf16 matmul {H100_BF16_TFLOPS:.0f} TFLOP/s, DRAM copy "
          f"{rates.bytes_per_ms * 1e-9:.2f} TB/s (measured), SFU {EXP_PER_S:.3g} exp/s, shortest graphed kernel "
          f"{1e3 * rates.launch_ms:.2f} us (measured)")
    _, _, ip, mv = default_cuda_guidances()
    res = 512
    renders = torch.rand(4, 3, res, res, device="cuda")
    originals = torch.rand(4, 3, res, res, device="cuda")
    views = ViewBatch(cameras=ring(4, res), originals=originals, view_ids=torch.arange(4), step=0, total_steps=4,
                      object_center=torch.zeros(3))
    draws = fixed_draws(ip, mv, res, "cuda")
    size = ip.resolution(res, res)
    cond = ip.condition_latents(originals, size, views.view_ids)
    cams = mv.camera_conditions(views)
    d_ip, d_mv = draws["ip2p"], draws["mvdream"]
    t_ip, t_mv = d_ip["t"].cuda(), d_mv["t"].cuda()  # on the device first: a copy from the host would wait for the GPU
    steps = {"ip2p_pooled": lambda: ip.step(renders, cond, t_ip, d_ip["noise"], d_ip["vae_noise"]),
             "mvdream": lambda: mv.step(renders, cams, t_mv, d_mv["noise"], d_mv["vae_noise"])}
    totals = {}
    for name, fn in steps.items():
        for _ in range(3):
            fn()
        records, span = record_ops(fn)
        totals[name] = summarise(name, records, span, rates, args.top)
    ip_t, mv_t = totals["ip2p_pooled"], totals["mvdream"]
    csd = {k: ip_t[k] + MV_FRACTION * mv_t[k] for k in ip_t}
    floor_ms = csd["flops"] / rates.flops_per_ms
    overlap = max(floor_ms, csd["bytes"] / rates.bytes_per_ms, csd["exps"] / rates.exps_per_ms)
    rows = [{"CSD step (pooled)": "measured: the ops' kernel time (eager; one after another)", "ms": f"{csd['ms']:.1f}"},
            {"CSD step (pooled)": "serial roofline: each op of today's sequence at its roofline",
             "ms": f"{csd['roof_ms']:.1f}"},
            {"CSD step (pooled)": "overlap bound: max(FLOPs, bytes, exponentials) of the whole step",
             "ms": f"{overlap:.1f}"},
            {"CSD step (pooled)": f"FLOP floor ({csd['flops'] / 1e12:.2f} TFLOP at {H100_BF16_TFLOPS:.0f} TFLOP/s)",
             "ms": f"{floor_ms:.1f}"},
            {"CSD step (pooled)": f"issue 30's target ({FLOOR_TARGET}x the FLOP floor)",
             "ms": f"{FLOOR_TARGET * floor_ms:.1f}"}]
    print_table(rows, f"CSD step = InstructPix2Pix + {MV_FRACTION} x MVDream ({csd['bytes'] / 1e9:.1f} GB of op "
                      f"tensors, {csd['exps'] / 1e9:.2f} G exponentials)")


if __name__ == "__main__":
    main()
