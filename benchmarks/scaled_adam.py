"""The relevance-scaled Adam step of an edit (``tiger::scaled_adam_``) against torch's Adam with
the scaling and the scatter into the scene done as the edit loop did before (clone, Adam, lerp,
copy, index_copy per tensor; ``fused=True`` on CUDA): time per step and error of the three
steps' update of the trainable rows against a float64 reference (torch's Adam in float64, the scaling
written out). Shapes: the edit benchmark's scene (317,600 Gaussians, 41,600 editable; means,
log-scales, quaternions, opacity logits and base colour optimised).

    python -m benchmarks.scaled_adam [--device cuda]
"""
from __future__ import annotations

import argparse
import math

import torch

from benchmarks.common import median_time, print_table, rel_err
from tiger.ops.scaled_adam import scaled_adam_

ROWS = {"means": (3,), "log_scales": (3,), "quats": (4,), "opacity_logits": (), "sh_dc": (3,)}
LRS = {"means": 1.6e-4, "log_scales": 5e-3, "quats": 1e-3, "opacity_logits": 5e-2, "sh_dc": 5e-2}
BETAS, EPS = (0.9, 0.999), 1e-15


def problem(n: int, m: int, device: str, dtype: torch.dtype, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    full = {k: torch.randn(n, *s, generator=g, dtype=torch.float64) for k, s in ROWS.items()}
    idx = torch.randperm(n, generator=g)[:m].sort().values
    grads = [{k: torch.randn(m, *s, generator=g, dtype=torch.float64) * 1e-3 for k, s in ROWS.items()} for _ in range(3)]
    w = torch.rand(m, generator=g, dtype=torch.float64)
    to = lambda t: t.to(device, dtype)  # noqa: E731
    return ({k: to(v) for k, v in full.items()}, idx.to(device), [{k: to(v) for k, v in gr.items()} for gr in grads],
            to(w))


class Ours:
    def __init__(self, full, idx, w):
        self.full, self.idx, self.w = full, idx, w
        self.p = [full[k][idx].clone() for k in ROWS]
        self.m = [torch.zeros_like(p) for p in self.p]
        self.v = [torch.zeros_like(p) for p in self.p]
        self.s = [torch.zeros((), dtype=torch.float32, device=idx.device) for _ in self.p]

    def step(self, grads):
        scaled_adam_(self.p, [grads[k] for k in ROWS], self.m, self.v, self.s, list(LRS.values()), BETAS, EPS,
                     weight=self.w, targets=[self.full[k] for k in ROWS], index=self.idx)


class TorchAdam:
    """The previous SceneOptimizer.update: torch Adam, then p <- lerp(p_old, p, w), then the rows
    into the scene (float64: the reference)."""

    def __init__(self, full, idx, w):
        self.full, self.idx, self.w = full, idx, w
        self.p = {k: full[k][idx].clone().requires_grad_(True) for k in ROWS}
        fused = idx.is_cuda and w.dtype != torch.float64
        self.adam = torch.optim.Adam([{"params": [p], "lr": LRS[k]} for k, p in self.p.items()], lr=0.0,
                                     betas=BETAS, eps=EPS, fused=fused)

    @torch.no_grad()
    def step(self, grads):
        for k, p in self.p.items():
            p.grad = grads[k]
        olds = {k: p.detach().clone() for k, p in self.p.items()}
        self.adam.step()
        for k, p in self.p.items():
            p.copy_(torch.lerp(olds[k], p, self.w.view(-1, *([1] * (p.dim() - 1)))))
            self.full[k].index_copy_(0, self.idx, p.detach())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--rows", type=int, default=317_600)
    ap.add_argument("--trainable", type=int, default=41_600)
    ap.add_argument("--iters", type=int, default=50)
    a = ap.parse_args()
    dev = a.device
    full64, idx, grads64, w64 = problem(a.rows, a.trainable, dev, torch.float64)
    start = {k: v[idx].clone() for k, v in full64.items()}
    ref = TorchAdam({k: v.clone() for k, v in full64.items()}, idx, w64)
    for gr in grads64:
        ref.step(gr)
    rows = []
    for name, cls in (("tiger scaled_adam_", Ours), ("torch Adam + lerp + index_copy", TorchAdam)):
        full, _, grads, w = problem(a.rows, a.trainable, dev, torch.float32)
        opt = cls(full, idx, w)
        for gr in grads:
            opt.step(gr)
        # error of the three steps' update of the trainable rows (the untouched rows are equal)
        err = max(rel_err(full[k][idx].double() - start[k], ref.full[k][idx] - start[k]) for k in ROWS)
        cuda = dev.startswith("cuda")
        ms = 1e3 * median_time(lambda: opt.step(grads[0]), repeats=a.iters if cuda else max(3, a.iters // 10),
                               warmup=5 if cuda else 1, cuda=cuda)
        rows.append({"device": dev, "who": name, "rows": a.rows, "trainable": a.trainable, "ms/step": ms,
                     "update rel err vs float64 (3 steps)": err})
    rows[0]["x peer"] = rows[0]["ms/step"] / rows[1]["ms/step"]
    elems = a.trainable * sum(math.prod(s) for s in ROWS.values())
    # floor: read p, g, m, v, w; write p, m, v and the scene's rows (float32)
    floor_ms = (elems * 4 * 8 + a.trainable * 4) / 3.35e12 * 1e3 if dev.startswith("cuda") else float("nan")
    rows[0]["HBM floor ms (3.35 TB/s)"] = floor_ms
    print_table(rows, f"relevance-scaled Adam step, {elems} elements in {len(ROWS)} tensors")


if __name__ == "__main__":
    main()
