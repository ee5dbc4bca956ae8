"""Edits and deletions started from the page, run in one worker thread each.

A job reports its progress (0..1) and a message, shows the scene being edited every
``preview_every`` steps (through ``ViewerState.preview``), can be cancelled between steps, and
on success pushes its result onto the viewer's history. A job that fails or is cancelled
leaves the scene as it was (the edit works on a copy) and keeps its error for the page.
"""
from __future__ import annotations

import abc
import logging
import threading
import time
from dataclasses import dataclass
from typing import Optional

import torch

from tiger.scene import GaussianScene

from .state import MAX_TEXT, ViewerError, ViewerState

log = logging.getLogger(__name__)

#: The guidances the page offers, in the order shown.
GUIDANCES = ("recolor", "ip2p+mvdream", "ip2p")


class Cancelled(Exception):
    """The user pressed Cancel."""


def guidance_availability(models: Optional[str] = None) -> dict[str, str]:
    """{guidance: '' when usable, else why not}: ``recolor`` always; the diffusion guidances when
    their weights are found (``--models`` / ``$TIGER_MODELS``)."""
    out = {"recolor": ""}
    try:
        from tiger.edit.build import _model_config  # --models as build_guidance reads it
        from tiger.models.paths import ModelNotFoundError, resolve_model_path
    except ImportError as e:  # transformers / diffusers missing
        reason = f"needs the optional model packages ({e})"
        return {**out, "ip2p+mvdream": reason, "ip2p": reason}
    missing = {}
    for name in ("ip2p", "mvdream"):
        try:
            resolve_model_path(name, config=_model_config(models))
            missing[name] = ""
        except (ModelNotFoundError, FileNotFoundError, ValueError) as e:
            missing[name] = str(e).split(". ")[0]  # 'model ... not found'; the details are in the log
    out["ip2p"] = missing["ip2p"] and f"InstructPix2Pix weights not found: {missing['ip2p']}"
    out["ip2p+mvdream"] = out["ip2p"] or (missing["mvdream"] and f"MVDream weights not found: {missing['mvdream']}")
    return out


@dataclass
class EditRequest:
    """An edit from the page: ``instruction`` applied by ``guidance`` for ``steps`` steps at
    ``size`` x ``size`` edit renders, showing a preview every ``preview_every`` steps."""

    instruction: str
    guidance: str = "recolor"
    steps: int = 100
    size: int = 128
    preview_every: int = 10
    seed: int = 0


class Job(abc.ABC):
    """A worker thread with progress, message, cancellation and an error slot; a subclass says
    what it computes in :meth:`run`."""

    kind = "job"

    def __init__(self, state: ViewerState) -> None:
        self.state = state
        self.progress = 0.0
        self.message = "starting"
        self.error: Optional[str] = None
        self.finished = threading.Event()
        self.cancelled = threading.Event()
        self.outcome = "running"  # running | done | cancelled | failed
        self.started = time.perf_counter()
        self._thread = threading.Thread(target=self._main, name=f"tiger-viewer-{self.kind}", daemon=True)

    def start(self) -> "Job":
        self._thread.start()
        return self

    def cancel(self) -> None:
        self.cancelled.set()

    def wait(self, timeout: Optional[float] = None) -> bool:
        return self.finished.wait(timeout)

    def _check_cancel(self) -> None:
        if self.cancelled.is_set():
            raise Cancelled()

    def _main(self) -> None:
        try:
            label, scene = self.run()
            self.state.push(label, scene)
            self.outcome, self.progress = "done", 1.0
            self.message = f"{label} ({time.perf_counter() - self.started:.1f} s)"
        except Cancelled:
            self.outcome, self.message = "cancelled", "cancelled; the scene is unchanged"
        except Exception as e:  # reported in the page; the scene stays as it was
            log.exception("viewer %s failed", self.kind)
            self.outcome, self.error = "failed", f"{type(e).__name__}: {e}"
            self.message = f"failed, the scene is unchanged: {self.error}"
        finally:
            with self.state.lock:
                self.state.preview = None
                self.state.version += 1
            self.finished.set()

    @abc.abstractmethod
    def run(self) -> tuple[str, GaussianScene]:
        """The work, in the worker thread: (a label for the history, the new scene). Call
        :meth:`_check_cancel` between steps; the scene in the viewer is replaced only on return."""


def _target_of(state: ViewerState):
    """The current selection as an edit/delete target: the Retrieval of a single query (its
    relevance weights), or the union mask of several."""
    sel = state.selection
    if sel is None or sel.count == 0:
        raise ViewerError("select something first (ask a query or click with the point prompt)")
    return sel.retrievals[0] if len(sel.retrievals) == 1 else sel.mask


class EditJob(Job):
    """The edit loop of ``tiger edit`` (:class:`tiger.edit.loop.EditSession`) on the selection."""

    kind = "edit"

    def __init__(self, state: ViewerState, request: EditRequest, device: torch.device) -> None:
        super().__init__(state)
        if not request.instruction.strip():
            raise ViewerError("type an instruction, e.g. 'make it red'")
        if len(request.instruction) > MAX_TEXT:
            raise ViewerError(f"the instruction is {len(request.instruction)} characters long; at most {MAX_TEXT}")
        if request.guidance not in GUIDANCES:
            raise ViewerError(f"unknown guidance {request.guidance!r}")
        if not 1 <= request.steps <= 10_000 or not 32 <= request.size <= 1024:
            raise ViewerError("steps must be in 1..10000 and the edit size in 32..1024")
        why = guidance_availability(state.models)[request.guidance]
        if why:
            raise ViewerError(f"{request.guidance}: {why}")
        with state.lock:
            self.scene, self.target = state.scene, _target_of(state)
        self.request, self.device = request, device

    def run(self) -> tuple[str, GaussianScene]:
        from tiger.edit import EditConfig
        from tiger.edit.build import build_guidance
        from tiger.edit.loop import EditSession
        from tiger.edit.target import resolve_target

        req = self.request
        self.message = "loading the guidance"
        guidance = build_guidance(req.guidance, req.instruction, models=self.state.models, device=self.device,
                                  seed=req.seed)
        target = resolve_target(self.scene, self.target)
        bg = self.state.background
        # recolor moves only the base colour far: the demo's learning rate (tiger.demo.edit)
        lrs = {"sh_dc": 0.1} if req.guidance == "recolor" else {}
        cfg = EditConfig(steps=req.steps, width=req.size, height=req.size, seed=req.seed, background=bg,
                         checkpoint_every=0, progress=False, lrs=lrs)
        session = EditSession(self.scene, target, guidance, None, cfg)  # the instruction is the guidance's
        while session.step < cfg.steps:
            self._check_cancel()
            session.step_once()
            self.progress = session.step / cfg.steps
            self.message = f"step {session.step} of {cfg.steps}"
            if req.preview_every and session.step % req.preview_every == 0 and session.step < cfg.steps:
                with self.state.lock:
                    self.state.preview = session.scene.detach().clone()
                    self.state.version += 1
        self._check_cancel()
        out, _ = session.result_scene()
        record = {"instruction": req.instruction, "target": target.description, "guidance": req.guidance,
                  "steps": session.step, "editable": target.count, "gaussians_before": len(self.scene),
                  "gaussians_after": len(out), "source": "tiger view"}
        out.metadata["tiger_edits"] = list(self.scene.metadata.get("tiger_edits", [])) + [record]
        return f"edit '{req.instruction}' ({req.guidance}, {req.steps} steps)", out


class DeleteJob(Job):
    """``tiger delete`` on the selection: remove, inpaint (OpenCV), refit ``steps`` steps."""

    kind = "delete"

    def __init__(self, state: ViewerState, steps: int = 100, views: int = 8, size: tuple[int, int] = (320, 240)) -> None:
        super().__init__(state)
        if not 0 <= steps <= 10_000:
            raise ViewerError("refit steps must be in 0..10000")
        with state.lock:
            self.scene, self.target, self.tau = state.scene, _target_of(state), state.tau
        self.steps, self.views, self.size = steps, views, size

    def run(self) -> tuple[str, GaussianScene]:
        from tiger.delete import DeleteConfig, delete, views_around
        from tiger.retrieval import Retrieval

        self.message = "removing, inpainting and refitting"
        target = self.target
        if isinstance(target, Retrieval):
            cams = views_around(target, self.views, *self.size)
        else:
            from tiger.retrieval import robust_bounds

            c, lo, hi = robust_bounds(self.scene.means.detach()[target])
            cams = views_around(Retrieval(target.float(), target.float(), None, target, 0.5, "cosine", c, lo, hi),
                                self.views, *self.size)
        self._check_cancel()
        cfg = DeleteConfig(tau=self.tau, steps=self.steps, background=self.state.background)
        res = delete(self.scene, target, [c.to(self.scene.device) for c in cams], inpainter="opencv", config=cfg,
                     progress=False)
        self._check_cancel()
        return f"delete ({res.counts['removed']} Gaussians removed)", res.scene
