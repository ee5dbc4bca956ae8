"""Does an edit touch anything but its editable Gaussians? One edit of the demo scene, then: every
frozen Gaussian's parameters before/after (they must be bit-identical), the locality parts, and
the worst pixel that no edited Gaussian reaches by its composited footprint, with that footprint
in float32 on the device and float64 on the CPU (the probe that found the walks an edited
Gaussian ends without being drawn; see tiger.eval.edit.edited_reach).

    python -m benchmarks.gpu.edit_frozen_probe GUIDANCE STEPS POOL [DEVICE DENSITY SIZE]
    python -m benchmarks.gpu.edit_frozen_probe ip2p+mvdream 300 64            # H100: ~1 min
"""
import argparse, dataclasses, sys
import torch
from benchmarks.edit import build, demo_scene
from tiger.edit import EditConfig, edit
from tiger.edit.target import resolve_target
from tiger.edit.views import ObjectViews
from tiger.eval.edit import locality, render_rgb

guid, steps, pool = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
dev = sys.argv[4] if len(sys.argv) > 4 else "cuda"
dens = float(sys.argv[5]) if len(sys.argv) > 5 else 16
size = int(sys.argv[6]) if len(sys.argv) > 6 else 512
args = argparse.Namespace(device=dev, density=dens, random_models="full", dtype="bf16", cuda_graph=dev.startswith("cuda"),
                          fused_norms="auto", sequential_guidance=False, size=size, guidance=guid)
scene, query = demo_scene(dens, dev)
tgt = resolve_target(scene, query, tau=0.5)
guidance, truth = build(guid, scene, tgt.mask, args)
cfg = EditConfig(steps=steps, width=size, height=size, lrs={"sh_dc": 0.05}, densify_every=25, densify_from=25,
                 background=(1.0, 1.0, 1.0), progress=False, checkpoint_every=0, view_pool=pool)
before = scene.clone()
res = edit(scene, tgt, guidance, config=cfg)
assert all(torch.equal(getattr(scene, k), getattr(before, k)) for k in ("means", "sh_dc")), "edit changed its input"
scene = before
after = res.scene
fb, fa = ~tgt.mask, ~res.editable
print(f"{guid} steps={steps} pool={pool}: N {len(scene)} -> {len(after)}, frozen {int(fb.sum())} -> {int(fa.sum())}")
for name in ("means", "quats", "scales", "opacities", "sh_dc", "sh_rest"):
    a = getattr(scene, name)[fb]
    b = getattr(after, name)[fa]
    if a.shape != b.shape:
        print(name, "shape", a.shape, b.shape); continue
    d = (a - b).abs()
    print(f"  frozen {name}: max|diff| {float(d.max()):.3g}, rows changed {int((d.reshape(d.shape[0], -1).amax(1) > 0).sum())}")
white = torch.ones(3, device=dev)
cams = ObjectViews(tgt.center, tgt.bbox_min, tgt.bbox_max, force_360=True, width=128, height=128).fixed(6, 15.0)
loc = locality(scene, after, cams, tgt.mask, res.editable, background=white)
print("  locality", {k: (round(v["psnr"], 2), v["pixels"], v["max_abs_err"]) for k, v in loc["parts"].items()})
rb, fpb = render_rgb(scene, cams, white, footprint=tgt.mask)
ra, fpa = render_rgb(after, cams, white, footprint=res.editable)
rest = (fpb == 0) & (fpa == 0)
diff = (ra - rb).abs().amax(-1) * rest
v, i = diff.flatten().max(0)
vi, rem = divmod(int(i), 128 * 128); y, x = divmod(rem, 128)
print(f"  worst rest pixel view {vi} ({x},{y}) diff {float(v):.3g}; fp before {float(fpb[vi, y, x]):.3g} after {float(fpa[vi, y, x]):.3g}")
print(f"  rest pixels with diff > 1e-6: {int((diff > 1e-6).sum())}, > 1e-4: {int((diff > 1e-4).sum())}")
# footprint in float64 on the CPU at the worst pixel's view: does an edited Gaussian reach it?
for nm, sc, m in (("before", scene, tgt.mask), ("after", after, res.editable)):
    s64 = sc.to("cpu") if hasattr(sc, "to") else sc
    try:
        _, fp64 = render_rgb(s64.to(dtype=torch.float64) if hasattr(s64, "to") else s64, [cams[vi].to("cpu")], white.cpu().double(), footprint=m.cpu())
        print(f"  {nm} footprint float64 CPU at the pixel: {float(fp64[0, y, x]):.3g}, {dev}: {float((fpb if nm == 'before' else fpa)[vi, y, x]):.3g}")
    except Exception as e:
        print("  cpu footprint failed", repr(e)[:200])
