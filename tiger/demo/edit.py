"""Demo stage after retrieval: "make the ball red" with the built-in ``recolor`` guidance."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import torch

from tiger.edit import EditConfig, edit, resolve_target
from tiger.edit.guidance import RecolorGuidance
from tiger.edit.pictures import before_after_grid
from tiger.edit.views import ObjectViews
from tiger.eval.edit import locality, locality_text
from tiger.render.views import orbit_cameras
from tiger.scene import GaussianScene
from tiger.utils.images import save_png

from .language import load_text_encoder
from .scene import DEMO_ORBIT


def recolor_demo(out: Path, timer, target: str = "ball", instruction: str = "make the ball red",
                 models: Optional[str] = None, steps: int = 40, size: int = 64,
                 picture_size=(480, 360)) -> dict:
    """Edit ``out/scene.ply`` (written by the language stage) and write before/after pictures.

    The edit runs the same loop as ``tiger edit`` (object-centred views, relevance-scaled updates,
    densification) with a small render size so the demo stays fast on a CPU.
    """
    scene = GaussianScene.load_ply(out / "scene.ply")
    encoder, _ = load_text_encoder(scene.metadata.get("labels", []), models)
    with timer.stage(f"edit '{instruction}' (recolor, {steps} steps at {size}x{size})"):
        tgt = resolve_target(scene, target, encoder=encoder, tau=0.5)
        cfg = EditConfig(steps=steps, width=size, height=size, lrs={"sh_dc": 0.1}, densify_every=10,
                         densify_from=10, background=(1.0, 1.0, 1.0), checkpoint_every=0)
        res = edit(scene, tgt, RecolorGuidance(instruction), config=cfg)
        res.scene.save_ply(out / "scene_ball_red.ply")
    pw, ph = picture_size
    pics = orbit_cameras(4, pw, ph, start_deg=20.0, **DEMO_ORBIT)
    white = torch.ones(3)
    with timer.stage("before/after pictures and locality"):
        grid = before_after_grid(scene, res.scene, pics, white)
        save_png(out / "edit_before_after.png", grid)
        close = ObjectViews(tgt.center, tgt.bbox_min, tgt.bbox_max, force_360=True, width=256, height=256)
        save_png(out / "edit_ball_closeup.png", before_after_grid(scene, res.scene, close.fixed(4, 35.0), white))
        loc = locality(scene, res.scene, pics, tgt.mask, res.editable, background=white)
    rgb = res.scene.rgb[res.editable].mean(0).tolist()
    print(f"  edit: {tgt.count} Gaussians of '{target}' recoloured; mean colour now "
          f"({rgb[0]:.2f}, {rgb[1]:.2f}, {rgb[2]:.2f}); {len(res.scene) - len(scene):+d} Gaussians from "
          f"densification; {locality_text(loc, 'the ball')}")
    print(f"    wrote {out / 'edit_before_after.png'} (top: before, bottom: after), "
          f"{out / 'edit_ball_closeup.png'}, {out / 'scene_ball_red.ply'}")
    return {"instruction": instruction, "target": target, "selected": tgt.count, "locality_psnr": loc["psnr"],
            "mean_rgb": rgb, "gaussians_after": len(res.scene), "time_s": res.rounds[-1]["time_s"]}
