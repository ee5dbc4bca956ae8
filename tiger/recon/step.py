"""One optimisation step over a Gaussian scene, for any loss and any trainable region.

:class:`SceneOptimizer` owns a :class:`GaussianScene` and an Adam optimizer over the
*trainable* rows of the chosen per-Gaussian tensors. Gaussians outside the trainable mask
are not parameters: the optimizer holds no tensor row for them (no gradient tensor, no
Adam moments, no update), so they stay bit-identical. What a step renders and what it
minimises are the caller's: ``step(loss, batch, render)`` calls ``render(scene, batch)``
then ``loss(renders, batch)``, back-propagates and updates. The reconstruction recipe
(:class:`tiger.recon.Trainer`) and the edit loop both sit on it; densification
(:mod:`tiger.recon.strategy`) changes the rows through :meth:`SceneOptimizer.edit_rows`
and :meth:`SceneOptimizer.set_rows`, which keep Adam's moments aligned with the Gaussians.

Relevance-scaled updates (TIGER §3.3): ``update_weight`` [N] multiplies each trainable
Gaussian's *Adam update*, ``p <- p_old + w_i (p_adam - p_old)``. Scaling the gradient
instead would be undone by Adam's normalisation; the moments themselves are not scaled.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Callable, Generic, Mapping, Optional, Sequence, TypeVar

import torch

from tiger.ops.scaled_adam import scaled_adam_
from tiger.scene.gaussian_scene import PARAM_NAMES, GaussianScene

R = TypeVar("R")
B = TypeVar("B")
STATE_FORMAT = "tiger.scene_optimizer/1"


@dataclass
class StepOutput(Generic[R]):
    """What :meth:`SceneOptimizer.step` returns: the loss (detached 0-d tensor) and the
    renders as ``render`` returned them (gradients of retained tensors, e.g.
    ``renders["means2d"].grad``, are still readable)."""

    loss: torch.Tensor
    renders: R


def _rows_view(w: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    return w.view(-1, *([1] * (like.dim() - 1)))


class SceneOptimizer:
    """Adam over the trainable Gaussians of ``scene`` (the scene is modified in place).

    Args:
        scene: the Gaussians; its per-Gaussian tensors are replaced by this object's (with a
            trainable mask they are cloned first, so the caller's tensors are never written).
        lrs: learning rate by parameter name (``means``, ``log_scales``, ``quats``,
            ``opacity_logits``, ``sh_dc``, ``sh_rest``, ``lang``); only these are optimised,
            one Adam group each, in :data:`PARAM_NAMES` order.
        trainable: [N] bool, the Gaussians that are parameters (default: all). With a mask,
            rendering goes through :meth:`render_scene`, whose tensors are the frozen rows
            with the trainable rows scattered in (gradients reach only the trainable rows).
        update_weight: [N] float, multiplies each Gaussian's Adam update (see module doc);
            None: 1. Entries of frozen Gaussians are ignored.
        extras: other per-Gaussian tensors ([N, ...]) that must follow every row change
            (relevance, labels, ...); children of densification inherit their parent's row.
        betas, eps: Adam's (INRIA: eps 1e-15).
    """

    def __init__(self, scene: GaussianScene, lrs: Mapping[str, float], *,
                 trainable: Optional[torch.Tensor] = None, update_weight: Optional[torch.Tensor] = None,
                 extras: Optional[Mapping[str, torch.Tensor]] = None,
                 betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-15) -> None:
        present = scene.params()
        unknown = [n for n in lrs if n not in present]
        if unknown:
            raise ValueError(f"tiger.recon: SceneOptimizer: no per-Gaussian parameter {unknown} in the scene "
                             f"(has {list(present)})")
        self.scene = scene
        self.names = [n for n in PARAM_NAMES if n in lrs]
        self.betas, self.eps = (float(betas[0]), float(betas[1])), float(eps)
        self.extras: dict[str, torch.Tensor] = {}
        for k, v in (extras or {}).items():
            self.extras[k] = self._check_rows(f"extras['{k}']", v)
        self._set_trainable(trainable)
        self._build({n: float(lrs[n]) for n in self.names})
        self.set_update_weight(update_weight)

    # -- set-up -------------------------------------------------------------------------------
    def _check_rows(self, what: str, t: torch.Tensor, dtype_bool: bool = False) -> torch.Tensor:
        n = len(self.scene)
        if not isinstance(t, torch.Tensor) or t.ndim < 1 or t.shape[0] != n:
            got = list(t.shape) if isinstance(t, torch.Tensor) else type(t).__name__
            raise ValueError(f"tiger.recon: SceneOptimizer {what} must have one row per Gaussian [N={n}, ...], "
                             f"got {got}")
        if dtype_bool and (t.dtype != torch.bool or t.ndim != 1):
            raise ValueError(f"tiger.recon: SceneOptimizer {what} must be a [N] bool mask, got {t.dtype} "
                             f"{list(t.shape)}")
        return t.to(self.scene.device)

    def _set_trainable(self, trainable: Optional[torch.Tensor]) -> None:
        if trainable is None:
            self.trainable: Optional[torch.Tensor] = None
            self._idx: Optional[torch.Tensor] = None
        else:
            self.trainable = self._check_rows("trainable", trainable, dtype_bool=True).clone()
            self._idx = torch.nonzero(self.trainable).reshape(-1)

    def _build(self, lrs: Mapping[str, float]) -> None:
        """Make the leaf tensors and the optimizer (fresh Adam state)."""
        s = self.scene
        self._leaves: dict[str, torch.Tensor] = {}
        groups = []
        for n, t in s.params().items():
            if self._idx is None:
                t = t.detach().requires_grad_(n in lrs)
                setattr(s, n, t)
                leaf = t
            else:
                full = t.detach().clone() if n in lrs else t.detach()
                setattr(s, n, full)
                leaf = full[self._idx].requires_grad_(True)
            if n in lrs:
                self._leaves[n] = leaf
                groups.append({"params": [leaf], "lr": float(lrs[n]), "name": n})
        # On CUDA, the fused Adam: one multi-tensor kernel per step instead of foreach's several
        # (1.04 ms for 59M parameters on the H100: benchmarks/gpu/train_vs_gsplat.py).
        fused = bool(groups) and all(g["params"][0].is_cuda for g in groups)
        self.optimizer: Optional[torch.optim.Adam] = (
            torch.optim.Adam(groups, lr=0.0, betas=self.betas, eps=self.eps, fused=fused) if groups else None)

    # -- inspection ---------------------------------------------------------------------------
    @property
    def num_trainable(self) -> int:
        return len(self.scene) if self._idx is None else int(self._idx.numel())

    @property
    def trainable_index(self) -> Optional[torch.Tensor]:
        """[M] sorted rows of the trainable Gaussians (None: every row trains); row j of each
        :attr:`leaves` tensor is Gaussian ``trainable_index[j]``."""
        return self._idx

    @property
    def leaves(self) -> Mapping[str, torch.Tensor]:
        """The optimised tensors by name: [M, ...] (the trainable rows only) with a trainable
        mask, else the scene's own [N, ...] tensors. Read-only: row changes go through
        :meth:`edit_rows` / :meth:`set_rows`."""
        return dict(self._leaves)

    def trainable_mask(self) -> torch.Tensor:
        """[N] bool, True for the Gaussians that are parameters."""
        if self.trainable is None:
            return torch.ones(len(self.scene), dtype=torch.bool, device=self.scene.device)
        return self.trainable

    def lr(self, name: str) -> float:
        return float(self._group(name)["lr"])

    def set_lr(self, name: str, lr: float) -> None:
        """Set the learning rate of parameter group ``name`` (e.g. a decaying position rate)."""
        self._group(name)["lr"] = float(lr)

    def _group(self, name: str) -> dict:
        for g in self.optimizer.param_groups if self.optimizer is not None else ():
            if g["name"] == name:
                return g
        raise KeyError(f"tiger.recon: SceneOptimizer optimises {self.names}, not '{name}'")

    def set_update_weight(self, weight: Optional[torch.Tensor]) -> None:
        """[N] per-Gaussian factor on the Adam update (None: plain Adam)."""
        if weight is None:
            self.update_weight: Optional[torch.Tensor] = None
            return
        w = self._check_rows("update_weight", weight)
        if w.ndim != 1:
            raise ValueError(f"tiger.recon: SceneOptimizer update_weight must be [N], got {list(w.shape)}")
        w = w.to(self.scene.dtype)
        self.update_weight = (w if self._idx is None else w[self._idx]).clone()

    def optimizer_state_bytes(self) -> int:
        """Bytes of the per-row optimizer state (Adam's two moments of every trainable row)."""
        if self.optimizer is None:
            return 0
        return sum(v.numel() * v.element_size() for st in self.optimizer.state.values() for v in st.values()
                   if isinstance(v, torch.Tensor) and v.dim() > 0)

    # -- the step -----------------------------------------------------------------------------
    def render_scene(self) -> GaussianScene:
        """The scene to render for a step: the scene itself when every Gaussian trains, else a
        shallow copy whose optimised tensors are the frozen rows with the trainable leaves
        scattered in (differentiable w.r.t. the leaves only)."""
        if self._idx is None:
            return self.scene
        view = copy.copy(self.scene)
        for n, leaf in self._leaves.items():
            setattr(view, n, getattr(self.scene, n).index_put((self._idx,), leaf))
        return view

    def step(self, loss: Callable[[R, B], torch.Tensor], batch: B,
             render: Callable[[GaussianScene, B], R]) -> StepOutput[R]:
        """``renders = render(scene, batch)``; ``loss(renders, batch).backward()``; :meth:`update`.

        ``render`` may render any number of views with any channels (and may call
        ``retain_grad`` on what it wants to read afterwards); ``loss`` must return a scalar.
        """
        if self.optimizer is None:
            raise ValueError("tiger.recon: SceneOptimizer.step: nothing to optimise (no learning rates given)")
        renders = render(self.render_scene(), batch)
        value = loss(renders, batch)
        if not isinstance(value, torch.Tensor) or value.numel() != 1:
            raise ValueError(f"tiger.recon: the loss must return a scalar tensor, got "
                             f"{list(value.shape) if isinstance(value, torch.Tensor) else type(value).__name__}")
        value.backward()
        self.update()
        return StepOutput(loss=value.detach().reshape(()), renders=renders)

    @torch.no_grad()
    def update(self) -> None:
        """Apply Adam to the gradients accumulated on the trainable rows (by :meth:`step` or by
        the caller's own ``backward``), scale the updates, write them into the scene and clear
        the gradients."""
        if self.optimizer is None:
            return
        if self.update_weight is None and self._idx is None:
            self.optimizer.step()  # every row trains: torch's (fused on CUDA) Adam on the scene's own tensors
        else:
            self._rows_update()
        self.optimizer.zero_grad(set_to_none=True)

    def _rows_update(self) -> None:
        """Adam on the trainable rows, each row's update scaled by :attr:`update_weight` (if
        any), the rows written into the scene's tensors as well: one
        :func:`tiger.ops.scaled_adam.scaled_adam_` call over every parameter with a gradient, on
        the optimizer's own state (``exp_avg``, ``exp_avg_sq``, ``step`` as ``torch.optim.Adam``
        keeps them, so checkpoints and row surgery see no difference). On CUDA that is two
        launches where torch's fused Adam gave a region of a few ten thousand rows only a few
        blocks per tensor and the scatter into the scene one launch per tensor."""
        params, grads, m, v, steps, lrs, targets = [], [], [], [], [], [], []
        for group in self.optimizer.param_groups:
            p = group["params"][0]
            if p.grad is None:
                continue  # as Adam: no gradient, no step
            st = self.optimizer.state[p]
            if not st:  # Adam's fresh state, as its fused CUDA and CPU implementations lay it out
                st["step"] = torch.zeros((), dtype=torch.float32, device=p.device)
                st["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                st["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
            elif st["step"].device != p.device:  # a state loaded for a CPU step: the kernel reads it here
                st["step"] = st["step"].to(p.device)
            params.append(p.detach())
            grads.append(p.grad.detach().contiguous())
            m.append(st["exp_avg"])
            v.append(st["exp_avg_sq"])
            steps.append(st["step"])
            lrs.append(float(group["lr"]))
            if self._idx is not None:
                targets.append(getattr(self.scene, group["name"]))
        if params:
            scaled_adam_(params, grads, m, v, steps, lrs, self.betas, self.eps, weight=self.update_weight,
                         targets=targets, index=self._idx)

    # -- row surgery (used by tiger.recon.strategy) --------------------------------------------
    @torch.no_grad()
    def edit_rows(self, keep: Optional[torch.Tensor] = None, parents: Optional[torch.Tensor] = None,
                  overrides: Optional[Mapping[str, torch.Tensor]] = None,
                  state: Optional[dict[str, torch.Tensor]] = None) -> None:
        """Keep the rows ``keep`` [N] bool (default all), then append one child per entry of
        ``parents`` [K] (indices into the current rows).

        A child copies every per-Gaussian tensor of its parent (scene parameters including
        ``lang``, ``extras``, the trainable flag, the update weight, and the rows of
        ``state``, a dict of [N, ...] tensors updated in place), except the tensors named in
        ``overrides`` ([K, ...] each). Kept rows keep their Adam moments; trainable children
        start with zero moments. New order: kept rows in order, then the children.
        """
        s = self.scene
        n = len(s)
        dev = s.device
        keep = torch.ones(n, dtype=torch.bool, device=dev) if keep is None else keep.to(dev)
        parents = torch.zeros(0, dtype=torch.long, device=dev) if parents is None else parents.to(dev).long()
        overrides = dict(overrides or {})
        if keep.shape != (n,) or keep.dtype != torch.bool:
            raise ValueError(f"tiger.recon: edit_rows keep must be [N={n}] bool, got {keep.dtype} {list(keep.shape)}")
        if parents.ndim != 1 or (parents.numel() and (int(parents.min()) < 0 or int(parents.max()) >= n)):
            raise ValueError(f"tiger.recon: edit_rows parents must be 1-D indices in [0, {n}), got "
                             f"{list(parents.shape)}")
        k = parents.numel()
        for name, v in overrides.items():
            if name not in s.params() or v.shape[0] != k:
                raise ValueError(f"tiger.recon: edit_rows override '{name}' must be a scene parameter with "
                                 f"{k} rows, got {list(v.shape)}")
        tr = self.trainable_mask()
        keep_t = keep if self._idx is None else keep[self._idx]          # [M] kept trainable rows
        child_t = tr[parents]                                            # [K] trainable children
        # the masks as indices once (each boolean index would read its count back from the device)
        keep_idx, keep_t_idx, child_t_idx = (torch.nonzero(m).reshape(-1) for m in (keep, keep_t, child_t))
        n_child_t = int(child_t_idx.numel())
        for name, old in s.params().items():
            add = overrides[name].to(old) if name in overrides else old.detach()[parents]
            full = torch.cat([old.detach().index_select(0, keep_idx), add])
            leaf = self._leaves.get(name)
            if leaf is None:
                setattr(s, name, full)
                continue
            if self._idx is None:
                new_leaf = full.requires_grad_(True)
                setattr(s, name, new_leaf)
            else:
                new_leaf = torch.cat([leaf.detach().index_select(0, keep_t_idx),
                                      add.index_select(0, child_t_idx)]).requires_grad_(True)
                setattr(s, name, full)
            self._swap_leaf(name, new_leaf, lambda v: torch.cat(
                [v.index_select(0, keep_t_idx), v.new_zeros((n_child_t,) + tuple(v.shape[1:]))]))
        for d in (self.extras, state if state is not None else {}):
            for key, v in list(d.items()):
                d[key] = torch.cat([v.index_select(0, keep_idx), v[parents]])
        if self.update_weight is not None:
            pos = torch.cumsum(tr.long(), 0) - 1                         # row -> trainable position
            self.update_weight = torch.cat([self.update_weight.index_select(0, keep_t_idx),
                                            self.update_weight[pos[parents.index_select(0, child_t_idx)]]])
        if self._idx is not None:
            self.trainable = torch.cat([tr.index_select(0, keep_idx), child_t])
            self._idx = torch.nonzero_static(self.trainable, size=int(keep_t_idx.numel()) + n_child_t).reshape(-1)

    @torch.no_grad()
    def set_rows(self, name: str, rows: torch.Tensor, values: torch.Tensor, reset_moments: bool = True) -> None:
        """Overwrite parameter ``name`` at ``rows`` [N] bool with ``values`` (shaped like the
        whole parameter, [N, ...]; only the ``rows`` entries are used) and, when
        ``reset_moments``, zero Adam's moments of those rows."""
        s = self.scene
        old = getattr(s, name)
        if old is None or values.shape != old.shape:
            raise ValueError(f"tiger.recon: set_rows '{name}' needs values shaped like the parameter "
                             f"{None if old is None else list(old.shape)}, got {list(values.shape)}")
        rows = rows.to(s.device)
        new = torch.where(_rows_view(rows, old), values.to(old), old.detach())
        leaf = self._leaves.get(name)
        if leaf is None:
            setattr(s, name, new)
            return
        rows_t = rows if self._idx is None else rows[self._idx]
        if self._idx is None:
            new_leaf = new.requires_grad_(True)
            setattr(s, name, new_leaf)
        else:
            new_leaf = new[self._idx].requires_grad_(True)
            setattr(s, name, new)
        self._swap_leaf(name, new_leaf, (lambda v: torch.where(_rows_view(rows_t, v), torch.zeros_like(v), v))
                        if reset_moments else (lambda v: v))

    def _swap_leaf(self, name: str, new_leaf: torch.Tensor,
                   map_rows: Callable[[torch.Tensor], torch.Tensor]) -> None:
        """Replace the leaf of group ``name``; its row-shaped optimizer state goes through ``map_rows``."""
        old_leaf = self._leaves[name]
        g = self._group(name)
        st = self.optimizer.state.pop(old_leaf, None)
        if st:
            for key, v in list(st.items()):
                if isinstance(v, torch.Tensor) and v.shape == old_leaf.shape:
                    st[key] = map_rows(v)
            self.optimizer.state[new_leaf] = st
        g["params"][0] = new_leaf
        self._leaves[name] = new_leaf

    # -- exact resume -------------------------------------------------------------------------
    def state_dict(self) -> dict:
        """Everything needed to continue bit for bit: the scene, the trainable mask, the update
        weights, the extras and Adam's state (plain tensors, loadable with ``weights_only``)."""
        return {"format": STATE_FORMAT, "scene": self.scene.state_dict(), "names": list(self.names),
                "trainable": None if self.trainable is None else self.trainable.clone(),
                "update_weight": None if self.update_weight is None else self.update_weight.clone(),
                "extras": {k: v.clone() for k, v in self.extras.items()},
                "betas": list(self.betas), "eps": self.eps,
                "optimizer": None if self.optimizer is None else self.optimizer.state_dict()}

    def load_state_dict(self, d: Mapping) -> None:
        """Restore a :meth:`state_dict` (the scene object stays the same, its tensors change)."""
        if d.get("format") != STATE_FORMAT:
            raise ValueError(f"tiger.recon: not a SceneOptimizer state (format {d.get('format')!r}, "
                             f"expected {STATE_FORMAT!r})")
        dev = self.scene.device
        src = GaussianScene.from_state_dict(d["scene"]).to(dev)
        for n in PARAM_NAMES + ("lang_pca_basis", "lang_pca_mean"):
            setattr(self.scene, n, getattr(src, n))
        self.scene.metadata = dict(src.metadata)
        self.names = list(d["names"])
        self.betas, self.eps = (float(d["betas"][0]), float(d["betas"][1])), float(d["eps"])
        self.extras = {k: v.to(dev) for k, v in d["extras"].items()}
        self._set_trainable(d["trainable"])
        opt = d["optimizer"]
        lrs = {g["name"]: g["lr"] for g in opt["param_groups"]} if opt is not None else {}
        self._build({n: lrs[n] for n in self.names})
        if opt is not None:
            self.optimizer.load_state_dict(opt)
        w = d["update_weight"]
        self.update_weight = None if w is None else w.to(dev, self.scene.dtype).clone()


__all__: Sequence[str] = ("SceneOptimizer", "StepOutput")
