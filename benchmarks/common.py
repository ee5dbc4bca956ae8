"""The standard benchmark scene (defined once) and timing/error helpers.

Scene: N Gaussians, means uniform in [-1, 1]^3, scales log-uniform in [0.003, 0.03],
uniformly random rotations, opacities uniform in [0.05, 0.95], colours uniform in [0, 1],
64-d features standard normal; camera 3.5 units from the origin looking at it, vertical
field of view 50 degrees.
"""
from __future__ import annotations

import math
import statistics
import time
from dataclasses import dataclass
from typing import Callable

import torch


@dataclass
class StandardScene:
    means: torch.Tensor      # [N, 3]
    quats: torch.Tensor      # [N, 4] (w, x, y, z), unit
    scales: torch.Tensor     # [N, 3]
    opacities: torch.Tensor  # [N]
    rgb: torch.Tensor        # [N, 3]
    features: torch.Tensor   # [N, 64]
    viewmat: torch.Tensor    # [4, 4] world->camera, OpenCV axes
    K: torch.Tensor          # [3, 3]
    width: int
    height: int

    def colors(self, channels: int) -> torch.Tensor:
        """[N, C] channels: 3 = RGB, 64 = features, 67 = both."""
        if channels == 3:
            return self.rgb
        if channels == 64:
            return self.features
        if channels == 67:
            return torch.cat([self.rgb, self.features], dim=1).contiguous()
        g = torch.Generator(device="cpu").manual_seed(channels)
        return torch.rand(self.rgb.shape[0], channels, generator=g).to(self.rgb)

    def to(self, device=None, dtype=None) -> "StandardScene":
        f = lambda t: t.to(device=device, dtype=dtype)  # noqa: E731
        return StandardScene(f(self.means), f(self.quats), f(self.scales), f(self.opacities),
                             f(self.rgb), f(self.features), f(self.viewmat), f(self.K),
                             self.width, self.height)


def look_at(eye: torch.Tensor, target: torch.Tensor, up: torch.Tensor) -> torch.Tensor:
    """World->camera [4,4] in OpenCV axes for a camera at eye looking at target."""
    f = target - eye
    f = f / f.norm()
    r = torch.linalg.cross(f, up)
    r = r / r.norm()
    d = torch.linalg.cross(f, r)
    R = torch.stack([r, d, f])
    V = torch.eye(4, dtype=eye.dtype)
    V[:3, :3] = R
    V[:3, 3] = -R @ eye
    return V


def standard_scene(n: int, width: int, height: int, seed: int = 0,
                   dtype: torch.dtype = torch.float32) -> StandardScene:
    g = torch.Generator().manual_seed(seed)
    d = torch.float64
    means = torch.rand(n, 3, generator=g, dtype=d) * 2 - 1
    quats = torch.randn(n, 4, generator=g, dtype=d)
    quats = quats / quats.norm(dim=1, keepdim=True)
    lo, hi = math.log(0.003), math.log(0.03)
    scales = torch.exp(torch.rand(n, 3, generator=g, dtype=d) * (hi - lo) + lo)
    opac = torch.rand(n, generator=g, dtype=d) * 0.9 + 0.05
    rgb = torch.rand(n, 3, generator=g, dtype=d)
    feats = torch.randn(n, 64, generator=g, dtype=d)
    eye = torch.tensor([0.0, 0.0, -3.5], dtype=d)
    V = look_at(eye, torch.zeros(3, dtype=d), torch.tensor([0.0, -1.0, 0.0], dtype=d))
    fy = 0.5 * height / math.tan(math.radians(50.0) / 2)
    K = torch.tensor([[fy, 0, width / 2], [0, fy, height / 2], [0, 0, 1]], dtype=d)
    return StandardScene(means, quats, scales, opac, rgb, feats, V, K, width,
                         height).to(dtype=dtype)


def median_time(fn: Callable[[], object], repeats: int = 5, warmup: int = 1,
                cuda: bool = False) -> float:
    """Median wall time of fn() in seconds (CUDA events when cuda=True)."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        if cuda:
            s, e = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            s.record()
            fn()
            e.record()
            torch.cuda.synchronize()
            times.append(s.elapsed_time(e) / 1e3)
        else:
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
    return statistics.median(times)


def rel_err(a: torch.Tensor, b: torch.Tensor) -> float:
    """Norm-wise relative error ||a - b|| / ||b|| computed in float64."""
    a, b = a.detach().double().cpu(), b.detach().double().cpu()
    return float((a - b).norm() / b.norm().clamp_min(1e-300))


def print_table(rows: list[dict], title: str = "") -> str:
    """Format a list of dicts as an aligned text table; prints and returns it."""
    if not rows:
        return ""
    keys = list(rows[0].keys())
    fmt = lambda v: f"{v:.3g}" if isinstance(v, float) else str(v)  # noqa: E731
    cols = [[k] + [fmt(r.get(k, "")) for r in rows] for k in keys]
    widths = [max(len(c) for c in col) for col in cols]
    lines = [title] if title else []
    lines.append("  ".join(k.rjust(w) for k, w in zip(keys, widths)))
    for i in range(len(rows)):
        lines.append("  ".join(cols[j][i + 1].rjust(widths[j]) for j in range(len(keys))))
    text = "\n".join(lines)
    print(text, flush=True)
    return text
