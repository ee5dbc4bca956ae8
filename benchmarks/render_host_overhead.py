"""Host-side cost of one render on a tiny scene (CPU; the kernels are negligible there, so the
time is Python, dispatch and autograd): median us of a forward, a forward+backward, and a
forward+backward with the input checks (check_finite=True), the ATen ops of one
forward+backward that would each launch a GPU kernel (fills, copies, elementwise, reductions;
the custom ops' own kernels not counted), and a scene's SH-colour render without gradients
(GaussianScene.render: one op) against the op-by-op path (project_for_raster + composite). Usage, from the repository root:
python -m benchmarks.render_host_overhead (to compare another checkout with its own build, run
the same command from that checkout's root)."""
from __future__ import annotations

import argparse
import collections
import time

import torch

p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
p.add_argument("--n", type=int, default=64)
p.add_argument("--size", type=int, default=16)
args = p.parse_args()
import tiger  # noqa: E402
from tests.render.standard_scenes import standard_camera, standard_scene  # noqa: E402

LAUNCHING = {"aten::zero_", "aten::fill_", "aten::copy_", "aten::gt", "aten::eq", "aten::where", "aten::div",
             "aten::amax", "aten::sum", "aten::mul", "aten::add", "aten::clamp_min"}


def main() -> None:
    torch.set_num_threads(1)
    n, w = args.n, args.size
    s = standard_scene(n, 3)
    V, K = standard_camera(w, w)
    leaves = {k: v.detach().clone().requires_grad_() for k, v in s.items()}
    vc = torch.randn(w, w, 3)

    def fwd():
        with torch.no_grad():
            tiger.rasterize_gaussians(s["means"], s["quats"], s["scales"], s["opacities"],
                                      s["colors"], V, K, w, w, check_finite=False)

    def fb(check=False):
        for t in leaves.values():
            t.grad = None
        out = tiger.rasterize_gaussians(leaves["means"], leaves["quats"], leaves["scales"],
                                        leaves["opacities"], leaves["colors"], V, K, w, w,
                                        check_finite=check)
        out["color"].backward(vc)

    def median_us(f, iters=2000):
        for _ in range(50):
            f()
        ts = []
        for _ in range(iters):
            t0 = time.perf_counter()
            f()
            ts.append(time.perf_counter() - t0)
        return sorted(ts)[iters // 2] * 1e6

    best = [min(x) for x in zip(*[(median_us(fwd), median_us(fb), median_us(lambda: fb(True)))
                                  for _ in range(3)])]
    print(f"n={n} {w}x{w}, CPU, 1 thread: forward {best[0]:.0f} us, forward+backward "
          f"{best[1]:.0f} us, forward+backward with check_finite {best[2]:.0f} us")
    from torch.profiler import ProfilerActivity, profile
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        fb()
    ops = collections.Counter(e.name for e in prof.events() if e.name in LAUNCHING)
    print(f"  ATen ops that launch a kernel on a GPU, per forward+backward: {sum(ops.values())} "
          f"{dict(ops)}")
    scene_render(median_us, n, w)


def scene_render(median_us, n: int, w: int) -> None:
    """GaussianScene.render (SH degree 3, no gradient: tiger::render_forward) against the op-by-op
    render of the same inputs."""
    from tiger.render import Camera
    from tiger.render.rasterize import RasterSettings, composite, project_for_raster
    from tiger.render.views import look_at, pinhole_K
    from tiger.scene import GaussianScene

    s = GaussianScene.random_in_box(n, [-1, -1, -1], [1, 1, 1], sh_degree=3,
                                    generator=torch.Generator().manual_seed(0))
    cam = Camera(look_at((0, -1.0, -3.0), (0, 0, 0)), pinhole_K(w, w), w, w)
    st = RasterSettings(check_finite=False)

    def op_by_op():
        p = project_for_raster(s.means, s.quats, s.scales, s.opacities, s.sh_dc[:, None], cam.viewmat, cam.K, w, w,
                               sh_degree=3, sh_rest=s.sh_rest[:, :15], settings=st)
        return composite(p, w, w, st)

    with torch.no_grad():
        one, ref = s.render(cam, check_finite=False), op_by_op()
        assert torch.equal(one["color"], ref["color"])
        best = [min(x) for x in zip(*[(median_us(lambda: s.render(cam, check_finite=False)), median_us(op_by_op))
                                      for _ in range(3)])]
    print(f"  scene.render (SH degree 3), no gradient: one op {best[0]:.0f} us, op by op {best[1]:.0f} us")


if __name__ == "__main__":
    main()
