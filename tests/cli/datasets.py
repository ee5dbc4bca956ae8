"""Small datasets on disk for the CLI tests: renders of the demo scene in the layouts users bring."""
from __future__ import annotations

import json

import torch

import tiger
from tiger.demo import tabletop_scene
from tiger.render.views import orbit_viewmats, pinhole_K
from tiger.utils.images import save_png


def tabletop_dataset(root, n_views=6, w=64, h=48):
    """Renders of the demo scene + transforms.json (OpenGL camera-to-world, as NeRF stores it)."""
    scene = tabletop_scene(density=0.15).scene
    (root / "images").mkdir(parents=True)
    K = pinhole_K(w, h)
    frames = []
    flip = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0]))  # OpenCV -> OpenGL camera axes
    for i, V in enumerate(orbit_viewmats(n_views, center=(0.0, -0.1, 0.0), radius=3.0,
                                         elevation_deg=25.0)):
        with torch.no_grad():
            img = tiger.rasterize_gaussians(scene.means, scene.quats, scene.scales, scene.opacities,
                                            scene.rgb, V, K, w, h, background=torch.ones(3))["color"]
        save_png(root / "images" / f"{i:03d}.png", img)
        c2w = torch.linalg.inv(V.double()) @ flip.double()
        frames.append({"file_path": f"images/{i:03d}.png", "transform_matrix": c2w.tolist()})
    meta = {"fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]), "cx": w / 2, "cy": h / 2, "w": w, "h": h,
            "frames": frames}
    (root / "transforms.json").write_text(json.dumps(meta))
    return root
