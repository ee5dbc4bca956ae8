"""Demo stage: "delete the mug" from the language-embedded tabletop, with before/after pictures."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import torch

from tiger.utils.images import save_png


def delete_stage(out: Path, timer, text: str = "mug", models: Optional[str] = None,
                 n_views: int = 8, size: tuple[int, int] = (240, 180), steps: int = 100) -> dict:
    """Delete ``text`` from ``out/scene.ply`` (written by the language stage) with the built-in
    OpenCV inpainting and views around the object. Writes ``out/delete_<text>/`` (scene.ply,
    before_k/after_k.png for 4 views, holes/, inpainted/, delete.json) and
    ``out/delete_<text>.png`` (before above after). Returns the deletion's report."""
    from tiger.delete import DeleteConfig, delete, views_around
    from tiger.eval.reprojection import evaluate_delete
    from tiger.retrieval import retrieve
    from tiger.scene import GaussianScene
    from tiger.utils.io import file_slug

    from .language import load_text_encoder

    slug = file_slug(text, default="object", max_len=None)
    folder = out / f"delete_{slug}"
    with timer.stage(f"delete '{text}': retrieve"):
        scene = GaussianScene.load_ply(out / "scene.ply")
        encoder, _ = load_text_encoder(scene.metadata.get("labels", []), models)
        # the demo's cosine cut (see the language stage)
        r = retrieve(scene, text, encoder=encoder, score="cosine", tau=0.5, negatives=None)
        cfg = DeleteConfig(tau=0.5, steps=steps, background=(1.0, 1.0, 1.0))
        cams = views_around(r, n_views, *size)
    with timer.stage(f"delete '{text}': remove, inpaint (OpenCV), refit {steps} steps"):
        res = delete(scene, r, cams, inpainter="opencv", config=cfg, progress=False)
    with timer.stage(f"delete '{text}': metrics"):
        evaluate_delete(res, cfg.background)
    with timer.stage(f"delete '{text}': pictures"):
        res.save(folder, extra={"text": text})
        best = res.best_views(4)
        grid = torch.cat([torch.cat([res.before[i] for i in best], 1),
                          torch.cat([res.after[i] for i in best], 1)], 0)
        save_png(out / f"delete_{slug}.png", grid)
    c, m = res.counts, res.metrics
    print(f"  delete '{text}': removed {c['removed']} Gaussians ({c['retrieved']} retrieved + "
          f"{c['floaters']} floaters + {c['unseen']} unseen + {c['similar']} similar), refit {c['trainable']} (+{c['seeded']} seeds); locality "
          f"{m['locality_psnr']:.1f} dB; {out / f'delete_{slug}.png'} (before above after)")
    return res.report()
