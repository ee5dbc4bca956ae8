"""Adaptive density control of 3DGS (Kerbl et al. 2023, §5.2), with optimizer surgery.

Each Gaussian accumulates the norm of the gradient of the loss w.r.t. its projected
centre, measured in NDC units as INRIA does (pixel gradient x size/2), over the views
that see it. Every ``interval`` steps Gaussians whose mean gradient exceeds the
threshold are cloned (small ones) or split in two (large ones); transparent, huge
on-screen or huge in-world ones are pruned. Adam's moments follow the Gaussians: copied
Gaussians start with zero moments, pruned ones lose theirs.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch

from tiger.scene.cameras import quat_to_rotmat
from tiger.scene.gaussian_scene import GaussianScene, inverse_sigmoid


@dataclass
class DensifyStats:
    """Per-Gaussian statistics gathered between densification steps (all [N])."""

    grad_accum: torch.Tensor
    count: torch.Tensor
    max_radii: torch.Tensor

    @classmethod
    def zeros(cls, n: int, device: torch.device) -> "DensifyStats":
        z = torch.zeros(n, device=device)
        return cls(z.clone(), z.clone(), z.clone())

    def add(self, means2d_grad: torch.Tensor, radii: torch.Tensor, width: int, height: int) -> None:
        """Record one view: ``means2d_grad`` [N, 2] (pixel units), ``radii`` [N] (0 = not seen)."""
        vis = radii > 0
        g = means2d_grad.detach()[vis].float()
        ndc = torch.stack([g[:, 0] * (0.5 * width), g[:, 1] * (0.5 * height)], -1)
        self.grad_accum[vis] += ndc.norm(dim=-1)
        self.count[vis] += 1
        self.max_radii[vis] = torch.maximum(self.max_radii[vis], radii[vis].float())

    def select(self, keep: torch.Tensor) -> None:
        for n in ("grad_accum", "count", "max_radii"):
            setattr(self, n, getattr(self, n)[keep])

    def state_dict(self) -> dict:
        return {"grad_accum": self.grad_accum, "count": self.count, "max_radii": self.max_radii}

    @classmethod
    def from_state_dict(cls, d: dict) -> "DensifyStats":
        return cls(d["grad_accum"], d["count"], d["max_radii"])


def _group(optimizer: torch.optim.Optimizer, name: str) -> Optional[dict]:
    for g in optimizer.param_groups:
        if g.get("name") == name:
            return g
    return None


def replace_params(scene: GaussianScene, optimizer: torch.optim.Optimizer, new: dict,
                   keep: Optional[torch.Tensor] = None) -> None:
    """Swap every per-Gaussian tensor of ``scene`` for ``cat(old[keep], new[name])``.

    Args:
        new: name -> tensor of the appended Gaussians (every present parameter).
        keep: [N] bool, which existing Gaussians remain (default all).
    Adam/any optimizer state tensors shaped like the parameter are selected by ``keep`` and
    zero-extended for the appended rows; non-optimised tensors are updated too.
    """
    for name, old in scene.params().items():
        add = new[name].to(old)
        kept = old.detach() if keep is None else old.detach()[keep]
        t = torch.cat([kept, add]).requires_grad_(old.requires_grad)
        g = _group(optimizer, name)
        if g is not None:
            st = optimizer.state.pop(g["params"][0], None)
            if st:
                for k, v in list(st.items()):
                    if isinstance(v, torch.Tensor) and v.shape == old.shape:
                        vk = v if keep is None else v[keep]
                        st[k] = torch.cat([vk, torch.zeros_like(add)])
                optimizer.state[t] = st
            g["params"][0] = t
        setattr(scene, name, t)


def densify_and_prune(scene: GaussianScene, optimizer: torch.optim.Optimizer, stats: DensifyStats,
                      grad_threshold: float, extent: float, percent_dense: float = 0.01,
                      min_opacity: float = 0.005, max_screen_size: Optional[float] = None,
                      max_world_size: Optional[float] = None, max_gaussians: Optional[int] = None,
                      generator: Optional[torch.Generator] = None) -> dict:
    """One round of clone / split / prune (INRIA's ``densify_and_prune``).

    Args:
        grad_threshold: mean NDC positional gradient above which a Gaussian is densified.
        extent: scene radius; a Gaussian is "large" when its largest scale exceeds
            ``percent_dense * extent``.
        min_opacity: prune below this opacity.
        max_screen_size: prune Gaussians whose screen radius exceeded this (px) since the
            last densification (None: off).
        max_world_size: prune Gaussians whose largest scale exceeds ``max_world_size *
            extent`` (None: off; INRIA turns it on, at 0.1, after the first opacity reset).
        max_gaussians: do not grow past this count (the largest gradients win).
    Returns:
        counts {"cloned", "split", "pruned", "total"}.
    """
    with torch.no_grad():
        grads = stats.grad_accum / stats.count.clamp_min(1)
        grads[stats.count == 0] = 0
        big = scene.scales.max(dim=1).values > percent_dense * extent
        want = grads >= grad_threshold
        if max_gaussians is not None:
            room = max(0, max_gaussians - len(scene))
            # a split adds one net Gaussian, a clone one: keep the strongest ``room``
            if int(want.sum()) > room:
                order = torch.argsort(torch.where(want, grads, torch.full_like(grads, -1.0)), descending=True)
                want = torch.zeros_like(want)
                want[order[:room]] = True
        clone = want & ~big
        split = want & big
        n0 = len(scene)
        params = scene.params()

        # Clones: identical copies (the optimizer then moves them apart).
        new = {k: v.detach()[clone] for k, v in params.items()}
        # Splits: two samples from the Gaussian, scales / 1.6 (INRIA's 0.8 * N with N = 2).
        idx = split.nonzero().squeeze(1)
        if idx.numel():
            rep = idx.repeat(2)
            std = scene.scales.detach()[rep]
            samples = torch.randn(std.shape, generator=generator, dtype=std.dtype).to(std.device) * std
            R = quat_to_rotmat(scene.quats.detach()[rep])
            split_new = {k: v.detach()[rep] for k, v in params.items()}
            split_new["means"] = (R @ samples.unsqueeze(-1)).squeeze(-1) + scene.means.detach()[rep]
            split_new["log_scales"] = torch.log(std / 1.6)
            new = {k: torch.cat([new[k], split_new[k]]) for k in new}
        keep = ~split
        replace_params(scene, optimizer, new, keep)
        n_new = new["means"].shape[0]
        stats.select(keep)
        for n in ("grad_accum", "count", "max_radii"):  # copies start with empty statistics
            t = getattr(stats, n)
            setattr(stats, n, torch.cat([t, t.new_zeros(n_new)]))

        prune = scene.opacities.detach() < min_opacity
        if max_screen_size is not None:
            prune |= stats.max_radii > max_screen_size
        if max_world_size is not None:
            prune |= scene.scales.detach().max(dim=1).values > max_world_size * extent
        if bool(prune.all()):
            # never delete everything: keep the most opaque Gaussian
            prune[torch.argmax(scene.opacity_logits.detach())] = False
        prune_gaussians(scene, optimizer, stats, prune)
        n_pruned = int(prune.sum())
        # a fresh accumulation window starts after every densification
        stats.grad_accum.zero_()
        stats.count.zero_()
        stats.max_radii.zero_()
    return {"cloned": int(clone.sum()), "split": int(split.sum()), "pruned": n_pruned,
            "total": len(scene), "before": n0}


def prune_gaussians(scene: GaussianScene, optimizer: torch.optim.Optimizer, stats: Optional[DensifyStats],
                    prune: torch.Tensor) -> None:
    """Remove the Gaussians where ``prune`` [N] is True (parameters, optimizer state, stats)."""
    keep = ~prune
    empty = {k: v.detach()[:0] for k, v in scene.params().items()}
    replace_params(scene, optimizer, empty, keep)
    if stats is not None:
        stats.select(keep)


def reset_opacity(scene: GaussianScene, optimizer: torch.optim.Optimizer, max_opacity: float = 0.01) -> None:
    """Clamp every opacity to at most ``max_opacity`` and zero its optimizer moments."""
    with torch.no_grad():
        op = torch.minimum(scene.opacities.detach(), torch.full_like(scene.opacity_logits, max_opacity))
        t = inverse_sigmoid(op).requires_grad_(scene.opacity_logits.requires_grad)
        g = _group(optimizer, "opacity_logits")
        if g is not None:
            st = optimizer.state.pop(g["params"][0], None)
            if st:
                for k, v in list(st.items()):
                    if isinstance(v, torch.Tensor) and v.shape == t.shape:
                        st[k] = torch.zeros_like(v)
                optimizer.state[t] = st
            g["params"][0] = t
        scene.opacity_logits = t
