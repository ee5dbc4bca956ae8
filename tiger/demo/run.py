"""``tiger demo``: build the tabletop scene, render it, and write pictures."""
from __future__ import annotations

import logging
from pathlib import Path

import torch

from tiger.render.views import orbit_cameras
from tiger.scene.labelled import LabelledScene
from tiger.train import StageTimer
from tiger.utils.images import colorize, feature_pca_image, pca_basis, save_png

from .scene import DEMO_ORBIT, tabletop_scene

log = logging.getLogger(__name__)


def _print_stage(name: str, seconds: float) -> None:
    print(f"  [{seconds:6.2f} s] {name}", flush=True)


def label_features(scene: LabelledScene, dim: int = 64, seed: int = 0,
                   noise: float = 0.05) -> torch.Tensor:
    """Per-Gaussian 64-d features: a fixed unit vector per label plus a little noise → [N, dim]."""
    g = torch.Generator().manual_seed(seed)
    table = torch.randn(len(scene.names), dim, generator=g)
    table = table / table.norm(dim=1, keepdim=True)
    f = table[scene.labels] + noise * torch.randn(len(scene), dim, generator=g)
    return f / f.norm(dim=1, keepdim=True)


def render_pictures(scene: LabelledScene, features: torch.Tensor, out: Path, width: int,
                    height: int, n_views: int, timer: StageTimer) -> list[dict]:
    """Colour, depth, alpha and a PCA picture of ``features`` [N, D] from ``n_views`` orbit views."""
    colors = torch.cat([scene.scene.rgb, features], dim=1).contiguous()  # 67 channels, one pass
    bg = torch.cat([torch.ones(3), torch.zeros(features.shape[1])])
    results, basis = [], None
    for i, cam in enumerate(orbit_cameras(n_views, width, height, start_deg=20.0, names="view{}", **DEMO_ORBIT)):
        with timer.stage(f"render view {i} ({width}x{height}, C=67, one pass)"):
            with torch.no_grad():
                r = scene.scene.render(cam, colors, background=bg)
        mask = r["alpha"] > 0.5
        feats = r["color"][..., 3:] / r["alpha"].clamp_min(1e-6)[..., None]
        if basis is None:
            f = feats[mask].reshape(-1, feats.shape[-1])
            basis = pca_basis(f, 3)
        files = {
            "color": save_png(out / f"view{i}_color.png", r["color"][..., :3]),
            "depth": save_png(out / f"view{i}_depth.png", colorize(r["depth"], mask, "turbo")),
            "alpha": save_png(out / f"view{i}_alpha.png", r["alpha"]),
            "features": save_png(out / f"view{i}_features_pca.png",
                                 feature_pca_image(feats, mask, basis)),
        }
        for kind, path in files.items():
            print(f"    wrote {path}  ({kind}; coverage {float(mask.float().mean()):.0%}, "
                  f"depth {float(r['depth'][mask].min()):.2f}-{float(r['depth'][mask].max()):.2f})")
        results.append({"viewmat": cam.viewmat, "K": cam.K, "render": r, "files": files})
    return results



DEFAULT_QUERIES = ("mug", "ball", "plant")


def run_demo(out_dir: str = "outputs/demo", width: int = 480, height: int = 360,
             n_views: int = 4, density: float = 1.0, queries=DEFAULT_QUERIES,
             models: str | None = None, steps: int = 300, edit_steps: int = 40) -> dict:
    """Run the demo end to end: build, render, language-embed, query, and (when "ball" is among the
    queries and ``edit_steps`` > 0) recolour the ball red. Returns what it did."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    timer = StageTimer(on_stage=_print_stage)  # the demo renders on the CPU
    print(f"TIGER demo → {out}/")
    with timer.stage("build procedural tabletop scene"):
        scene = tabletop_scene(density)
        feats = label_features(scene)
    counts = {n: int((scene.labels == i).sum()) for i, n in enumerate(scene.names)}
    print(f"  scene: {len(scene)} Gaussians " + ", ".join(f"{k}={v}" for k, v in counts.items()))
    views = render_pictures(scene, feats, out, width, height, n_views, timer)
    found = []
    if queries:
        from .language import embed_and_query

        found = embed_and_query(scene, out, list(queries), timer, models=models, steps=steps,
                                picture_size=(width, height))
    edited = None
    if found and "ball" in queries and edit_steps > 0:
        from .edit import recolor_demo

        edited = recolor_demo(out, timer, models=models, steps=edit_steps)
    deleted = _delete_demo(out, timer, models) if found and "mug" in queries else None
    print("\nstage timings\n" + timer.table())
    if found:
        print("\nqueries")
        for r in found:
            print(f"  {r['query']!r:>14} -> {r['object']:<8} {r['selected']:6d} Gaussians, "
                  f"precision {r['precision']:.3f}, recall {r['recall']:.3f}")
    print(f"\npictures in {out}/: view*_{{color,depth,alpha,features_pca}}.png, "
          "relevancy/*.png, highlight_*.png, retrieved_*.png" + (", edit_before_after.png" if edited else "")
          + (", delete_mug.png (before above after), delete_mug/" if deleted else ""))
    return {"timer": list(timer.summary().items()), "views": views, "scene": scene, "queries": found, "edit": edited,
            "delete": deleted}


def _delete_demo(out: Path, timer: StageTimer, models) -> dict:
    """"delete the mug" on the language-embedded scene (tiger.demo.delete)."""
    from .delete import delete_stage

    return delete_stage(out, timer, "mug", models=models)
