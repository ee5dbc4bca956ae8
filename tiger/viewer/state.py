"""The viewer's state without a browser: the scene and its history, the selection, the view settings.

Everything the web page can do goes through :class:`ViewerState`, so it is tested in-process:
asking (text queries retrieved with :func:`tiger.retrieval.retrieve`, the rule of ``tiger query``),
the point prompt (the rendered language feature under a pixel used as the query), edits and
deletions (worker jobs, :mod:`tiger.viewer.jobs`), Undo / Redo and Save.
"""
from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Union

import torch

from tiger.retrieval import Retrieval, retrieve
from tiger.retrieval.text import TextEncoder
from tiger.render import Camera
from tiger.scene import GaussianScene

from .frames import MODES, FrameInputs

log = logging.getLogger(__name__)

#: Longest text the page may send (queries, instructions).
MAX_TEXT = 200
#: Most comma-separated queries in one ask.
MAX_QUERIES = 8
HIGHLIGHT = (1.0, 0.5, 0.0)
SHOW = ("tint", "alone", "off")


class ViewerError(ValueError):
    """A request from the page that cannot be done; its message is shown in the page."""


@dataclass
class Selection:
    """The current selection.

    Attributes:
        label: what was asked (the texts, or "point (x, y)").
        queries: [Q, D] unit query vectors in the language space.
        retrievals: one :class:`Retrieval` per query (same order).
        mask: [N] bool, the union of the retrievals' masks.
    """

    label: str
    queries: torch.Tensor
    retrievals: list[Retrieval]
    mask: torch.Tensor
    sources: list = field(default_factory=list)  # texts or query vectors, re-asked after an edit

    @property
    def count(self) -> int:
        return int(self.mask.sum())

    def boxes(self) -> list[tuple[list[float], list[float]]]:
        """(lo [3], hi [3]) robust box of each retrieval that selected something."""
        return [(r.bbox_min.tolist(), r.bbox_max.tolist()) for r in self.retrievals if r.bbox_min is not None]


def split_queries(text: str) -> list[str]:
    """The comma-separated queries of ``text`` (blank ones dropped, duplicates once)."""
    if len(text) > MAX_TEXT:
        raise ViewerError(f"the query is {len(text)} characters long; at most {MAX_TEXT}")
    parts = list(dict.fromkeys(p.strip() for p in text.split(",") if p.strip()))
    if not parts:
        raise ViewerError("type a query (several: separated by commas)")
    if len(parts) > MAX_QUERIES:
        raise ViewerError(f"{len(parts)} queries; at most {MAX_QUERIES} at once")
    return parts


def feature_pca_colors(lang: torch.Tensor) -> torch.Tensor:
    """[N, 3] colours of per-Gaussian language features [N, D]: their first three principal
    components, each scaled to its 1st-99th percentile range (shared by every view)."""
    from tiger.utils.images import pca_basis

    f = lang.detach().float()
    sample = f[torch.randperm(f.shape[0], generator=torch.Generator().manual_seed(0))[:200_000].to(f.device)]
    mean = sample.mean(0)
    proj = (f - mean) @ pca_basis(sample - mean, 3)
    q = torch.quantile(proj[:: max(1, proj.shape[0] // 100_000)].cpu(), torch.tensor([0.01, 0.99]), dim=0)
    lo, hi = q[0].to(proj), q[1].to(proj)
    return ((proj - lo) / (hi - lo).clamp_min(1e-12)).clamp(0, 1)


class ViewerState:
    """Scene, history, selection and view settings of one viewer (shared by its browser tabs).

    Args:
        scene: the scene to show (kept as the first history entry; never modified in place).
        encoder: text encoder for the queries (None: text queries disabled, with ``encoder_note``).
        out_dir: the folder Save writes into.
        models: model folder/config for the diffusion guidances (None: ``$TIGER_MODELS``).
        cameras: capture cameras (``cameras.json``), for the camera list.
    """

    def __init__(self, scene: GaussianScene, encoder: Optional[TextEncoder] = None, *,
                 encoder_note: str = "", out_dir: Union[str, Path] = "outputs/view",
                 models: Optional[str] = None, cameras: Optional[list[Camera]] = None) -> None:
        self.lock = threading.RLock()
        self.history: list[tuple[str, GaussianScene]] = [("loaded", scene)]
        self.index = 0
        self.encoder, self.encoder_note = encoder, encoder_note
        self.out_dir, self.models = Path(out_dir), models
        self.cameras = list(cameras or [])
        self.selection: Optional[Selection] = None
        self.tau: Union[str, float] = "auto"
        self.show = "tint"
        self.mode = "RGB"
        self.background: tuple[float, float, float] = (1.0, 1.0, 1.0)
        self.preview: Optional[GaussianScene] = None  # a running edit's scene, shown while it runs
        self.version = 0  # bumped whenever what a frame shows changes
        # (the objects they were computed from, result): compared by identity, and holding the
        # objects keeps their ids from being reused by newer ones
        self._pca_cache: tuple = ((), None)
        self._tint_cache: tuple = ((), None)
        self._alone_cache: tuple = ((), None)

    # -- scene and history --------------------------------------------------------------------
    @property
    def scene(self) -> GaussianScene:
        """The current scene (the history entry at ``index``)."""
        return self.history[self.index][1]

    @property
    def has_language(self) -> bool:
        return self.scene.lang is not None

    def language_note(self) -> str:
        """Why the ask/select panels are disabled ('' when they are not)."""
        if not self.has_language:
            return ("this scene has no language features (lang_*): run `tiger embed` on it to ask, "
                    "select, edit and delete")
        return ""

    def _changed(self) -> None:
        self.version += 1

    def push(self, label: str, scene: GaussianScene) -> None:
        """Make ``scene`` current after the current entry (the redo entries are dropped)."""
        with self.lock:
            del self.history[self.index + 1:]
            self.history.append((label, scene))
            self.index = len(self.history) - 1
            self.preview = None
            self._reselect()
            self._changed()

    def undo(self) -> str:
        """Go back one history entry (the scene object itself: bit-identical); returns its label."""
        with self.lock:
            if self.index == 0:
                raise ViewerError("nothing to undo")
            self.index -= 1
            self._reselect()
            self._changed()
            return self.history[self.index + 1][0]

    def redo(self) -> str:
        with self.lock:
            if self.index + 1 >= len(self.history):
                raise ViewerError("nothing to redo")
            self.index += 1
            self._reselect()
            self._changed()
            return self.history[self.index][0]

    def save(self) -> Path:
        """Write the current scene as a PLY into ``out_dir`` (atomically; a new numbered name,
        nothing overwritten); returns the path."""
        with self.lock:
            scene, label = self.scene, self.history[self.index][0]
        self.out_dir.mkdir(parents=True, exist_ok=True)
        k = 1
        while (self.out_dir / f"scene_{k:03d}.ply").exists():
            k += 1
        path = self.out_dir / f"scene_{k:03d}.ply"
        scene.save_ply(path)  # atomic: temporary file in the folder + rename
        log.info("saved %s (%s)", path, label)
        return path

    # -- asking ------------------------------------------------------------------------------
    def _require_language(self) -> None:
        if not self.has_language:
            raise ViewerError(self.language_note())

    def _retrieve(self, scene: GaussianScene, query) -> Retrieval:
        try:
            # the selection is the cosine rule of `tiger query` (its default score); the LERF
            # negatives only matter for the relevancy score, so they are not embedded here
            return retrieve(scene, query, encoder=self.encoder, tau=self.tau, negatives=None)
        except (KeyError, ValueError) as e:
            raise ViewerError(str(e.args[0] if e.args else e)) from None

    def _select(self, label: str, sources: list) -> Selection:
        scene = self.scene
        rets = [self._retrieve(scene, s) for s in sources]
        mask = torch.zeros(len(scene), dtype=torch.bool, device=scene.device)
        for r in rets:
            mask |= r.mask.to(scene.device)
        from tiger.retrieval.text import embed_queries

        q = torch.cat([embed_queries(s, dim=scene.lang.shape[1], encoder=self.encoder, pca=scene) for s in sources])
        return Selection(label, q, rets, mask, list(sources))

    def ask(self, text: str) -> Selection:
        """Select what the comma-separated queries of ``text`` retrieve (their union)."""
        self._require_language()
        texts = split_queries(text)
        if self.encoder is None:
            raise ViewerError(self.encoder_note or "no text encoder: pass --models or --text-embeddings")
        with self.lock:
            sel = self._select(", ".join(texts), texts)
            self.selection = sel
            self._changed()
        return sel

    @torch.no_grad()
    def point_feature(self, camera: Camera, x: float, y: float) -> torch.Tensor:
        """The rendered language feature [D] at the pixel under (x, y) (0..1 image coordinates)."""
        self._require_language()
        scene = self.scene
        out = scene.render(camera, "lang", check_finite=False)
        px = min(max(int(x * camera.width), 0), camera.width - 1)
        py = min(max(int(y * camera.height), 0), camera.height - 1)
        if float(out["alpha"][py, px]) < 0.05:
            raise ViewerError("nothing under the cursor there (empty background): click on an object")
        return out["color"][py, px].float().cpu()

    def point_prompt(self, camera: Camera, x: float, y: float) -> Selection:
        """Select what is most like the rendered language feature under (x, y) of ``camera``."""
        feat = self.point_feature(camera, x, y)
        with self.lock:
            sel = self._select(f"point ({x:.2f}, {y:.2f})", [feat])
            self.selection = sel
            self._changed()
        return sel

    def clear_selection(self) -> None:
        with self.lock:
            self.selection = None
            self._changed()

    def set_tau(self, tau: Union[str, float]) -> None:
        """The threshold (a number, or 'auto'); the current selection is asked again with it."""
        with self.lock:
            self.tau = tau
            self._reselect()
            self._changed()

    def _reselect(self) -> None:
        """Ask the current selection's queries again (after a scene or threshold change)."""
        sel = self.selection
        if sel is None:
            return
        if not self.has_language:
            self.selection = None
            return
        try:
            self.selection = self._select(sel.label, sel.sources)
        except ViewerError as e:
            log.warning("selection dropped: %s", e)
            self.selection = None

    # -- frames -------------------------------------------------------------------------------
    def set_view(self, *, mode: Optional[str] = None, show: Optional[str] = None,
                 background: Optional[tuple[float, float, float]] = None) -> None:
        with self.lock:
            if mode is not None:
                if mode not in MODES:
                    raise ViewerError(f"unknown view mode {mode!r}")
                if mode in ("language features", "relevancy") and not self.has_language:
                    raise ViewerError(self.language_note())
                self.mode = mode
            if show is not None:
                if show not in SHOW:
                    raise ViewerError(f"unknown highlight {show!r}")
                self.show = show
            if background is not None:
                self.background = tuple(min(max(float(c), 0.0), 1.0) for c in background)
            self._changed()

    @staticmethod
    def _hit(cache: tuple, *objs) -> bool:
        return len(cache[0]) == len(objs) and all(a is b for a, b in zip(cache[0], objs))

    def _pca_colors(self, scene: GaussianScene) -> torch.Tensor:
        key = (scene,)
        if not self._hit(self._pca_cache, *key):
            self._pca_cache = (key, feature_pca_colors(scene.lang))
        return self._pca_cache[1]

    def _tint(self, scene: GaussianScene, mask: torch.Tensor) -> torch.Tensor:
        key = (scene, mask)
        if not self._hit(self._tint_cache, *key):
            rgb = scene.rgb.detach()
            grey = rgb.mean(1, keepdim=True).expand(-1, 3) * 0.6 + 0.2
            hl = torch.tensor(HIGHLIGHT, dtype=rgb.dtype, device=rgb.device)
            self._tint_cache = (key, torch.where(mask[:, None], 0.45 * rgb + 0.55 * hl, grey).contiguous())
        return self._tint_cache[1]

    def _alone(self, scene: GaussianScene, mask: torch.Tensor) -> GaussianScene:
        key = (scene, mask)
        if not self._hit(self._alone_cache, *key):
            self._alone_cache = (key, scene.subset(mask))
        return self._alone_cache[1]

    def frame_inputs(self) -> FrameInputs:
        """A snapshot of what to draw (taken under the lock; rendering happens outside it)."""
        with self.lock:
            scene = self.preview if self.preview is not None else self.scene
            sel = self.selection if self.preview is None else None
            mode, colors, queries = self.mode, None, None
            if mode == "language features" and scene.lang is not None:
                colors = self._pca_colors(scene)
            if sel is not None and sel.mask.shape[0] == len(scene):
                queries = sel.queries
                if self.show == "alone":
                    colors = None if colors is None else colors[sel.mask]
                    scene = self._alone(scene, sel.mask)
                elif self.show == "tint" and mode == "RGB":
                    colors = self._tint(scene, sel.mask)
            return FrameInputs(scene, colors, queries, self.background, mode)
