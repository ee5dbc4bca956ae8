"""The viewer's frame path: camera message -> frame sent (render + JPEG encode), and query -> highlight.

Per frame, as the server does it (``tiger.viewer.server.ViewerServer.draw``): the browser pose ->
Camera, ``render_frame`` (rasterizer + uint8 on the device + one host copy), and viser's
``set_background_image`` (JPEG encode with OpenCV, message queued) on a live viser server with no
tab open (nothing waits on a network). Also the render alone and the JPEG encode alone, the
small frame drawn while the camera moves, and "query -> highlight": ``ViewerState.ask`` (the
retrieval, ``tiger query``'s rule) + the tinted frame drawn and encoded at the largest size.

Scenes:
  demo    the demo tabletop (~20k Gaussians) with per-object language features, the viewer's start
          camera (CPU acceptance: >= 5 frames/s at 640x360 on 2 cores)
  heavy   benchmarks.common.heavy_tailed_scene (real-scene scale statistics, a long tail of
          large Gaussians near the camera), --n Gaussians, 64-d random language features, the
          standard camera (GPU acceptance, 1M: >= 30 fps at 1920x1080, >= 60 at 1280x720,
          query -> highlight <= 100 ms)

    python -m benchmarks.viewer --scene demo --threads 2            # CPU, from the repo root
    python -m benchmarks.viewer --scene heavy --n 1000000 --device cuda --out benchmarks/gpu/results/viewer.json
"""
from __future__ import annotations

import argparse
import json
import socket
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.common import heavy_tailed_scene, print_table, standard_camera

SIZES = ((640, 360), (1280, 720), (1920, 1080))


def demo_state(device: torch.device):
    from tiger.demo.run import label_features
    from tiger.demo.scene import tabletop_scene
    from tiger.retrieval.text import EmbeddingTable
    from tiger.viewer.state import ViewerState

    lab = tabletop_scene(1.0)
    lab.scene.lang = label_features(lab)
    table = {n: lab.scene.lang[lab.labels == i].mean(0) for i, n in enumerate(lab.names)}
    return ViewerState(lab.scene.to(device), EmbeddingTable(table)), "ball"


def heavy_state(n: int, device: torch.device):
    from tiger.retrieval.text import EmbeddingTable
    from tiger.scene import GaussianScene
    from tiger.viewer.state import ViewerState

    s = heavy_tailed_scene(n, 3, device="cpu")
    scene = GaussianScene.from_values(s["means"], s["quats"], s["scales"], s["opacities"], s["colors"].clamp(0, 1))
    g = torch.Generator().manual_seed(3)
    centers = torch.randn(8, 64, generator=g)
    obj = (s["means"][:, 0] > 0.5) & (s["means"][:, 1] > 0.2)  # a corner of the cube: "the object"
    lang = centers[torch.randint(1, 8, (n,), generator=g)]
    lang[obj] = centers[0]
    scene.lang = lang + 0.1 * torch.randn(n, 64, generator=g)
    return ViewerState(scene.to(device), EmbeddingTable({"object": centers[0]})), "object"


def start_pose(state, scene_kind: str):
    """(wxyz, position, fov_y) of the camera the frames are drawn from."""
    from tiger.viewer.camera import pose_of

    if scene_kind == "heavy":
        from tiger.render import Camera

        V, K = standard_camera(640, 480)
        cam = Camera(V.double(), K.double(), 640, 480)
    else:
        from tiger.render.views import orbit_cameras_around

        cam = orbit_cameras_around(state.scene.means.cpu(), 1, 640, 480, elevation_deg=25.0, up=(0.0, -1.0, 0.0))[0]
    R = cam.c2w.double()[:3, :3]
    return _wxyz(R), pose_of(cam)["position"], cam.fov_y


def _wxyz(R: torch.Tensor) -> tuple[float, float, float, float]:
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(R.numpy()).as_quat()
    return (w, x, y, z)


def _median_ms(fn, iters: int, device: torch.device, cpu_time: bool = False):
    """Median wall ms of ``fn`` (and, with ``cpu_time``, median process CPU ms: on a shared
    machine the CPU time a frame costs, which the wall time overstates under contention)."""
    times, cpu = [], []
    for _ in range(iters + 1):
        if device.type == "cuda":
            torch.cuda.synchronize()
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        if device.type == "cuda":
            torch.cuda.synchronize()
        times.append(1e3 * (time.perf_counter() - t0))
        cpu.append(1e3 * (time.process_time() - c0))
    wall = statistics.median(times[1:])  # the first: warm-up
    return (wall, statistics.median(cpu[1:])) if cpu_time else wall


class _Client:
    """What ViewerServer.draw needs of a browser tab: ``client.scene.set_background_image``; here
    the live server's scene API (the same encoder, the message queued for no tab)."""

    def __init__(self, scene_api) -> None:
        self.scene = scene_api


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scene", choices=("demo", "heavy"), default="demo")
    p.add_argument("--n", type=int, default=1_000_000, help="Gaussians of the heavy scene")
    p.add_argument("--device", default="cpu")
    p.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    p.add_argument("--iters", type=int, default=10)
    p.add_argument("--out", default=None, help="write the rows as JSON here")
    args = p.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    import viser
    from viser._image_encoding import cv2_imencode_with_fallback

    try:  # viser encodes with OpenCV when it is installed, else with imageio (Pillow)
        import cv2  # noqa: F401

        encoder_name = "opencv"
    except ImportError:
        encoder_name = "imageio (no OpenCV)"

    from tiger.viewer.camera import camera_from_pose
    from tiger.viewer.frames import render_frame
    from tiger.viewer.server import ClientView, ViewerServer

    dev = torch.device(args.device)
    state, query = demo_state(dev) if args.scene == "demo" else heavy_state(args.n, dev)
    wxyz, pos, fov = start_pose(state, args.scene)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    vs = viser.ViserServer(host="127.0.0.1", port=port, verbose=False)
    server = ViewerServer(state, "127.0.0.1", port, device=dev)
    server.server, server.gui = vs, None
    rows = []
    try:
        for w, h in SIZES:
            view = ClientView(_Client(vs.scene), pose=(wxyz, pos, fov, w, h))
            cam = camera_from_pose(wxyz, pos, fov, w, h).to(dev)
            img = render_frame(state.frame_inputs(), cam)
            render_ms = _median_ms(lambda: render_frame(state.frame_inputs(), cam), args.iters, dev)
            encode_ms = _median_ms(lambda: cv2_imencode_with_fallback("jpeg", img, jpeg_quality=90,
                                                                      channel_ordering="rgb"), args.iters, dev)
            frame_ms, frame_cpu = _median_ms(lambda: server.draw(view, full=True), args.iters, dev, cpu_time=True)
            moving_ms = _median_ms(lambda: server.draw(view, full=False), args.iters, dev)
            small = server.browser_camera(view, full=False)
            rows.append({"scene": args.scene, "N": len(state.scene), "device": str(dev), "size": f"{w}x{h}",
                         "render ms": render_ms, "encode ms": encode_ms, "message->sent ms": frame_ms,
                         "fps": 1e3 / frame_ms, "CPU ms": frame_cpu, f"moving ({small.width}x{small.height}) ms": moving_ms})
        rows_q = []
        w, h = SIZES[-1]
        view = ClientView(_Client(vs.scene), pose=(wxyz, pos, fov, w, h))

        def ask_and_draw() -> None:
            state.clear_selection()
            state.ask(query)
            server.draw(view, full=True)

        q_ms = _median_ms(ask_and_draw, args.iters, dev)
        ask_ms = _median_ms(lambda: (state.clear_selection(), state.ask(query)), args.iters, dev)
        rows_q.append({"scene": args.scene, "N": len(state.scene), "query": query, "selected": state.selection.count,
                       "ask ms": ask_ms, f"query->highlight sent ({w}x{h}) ms": q_ms})
    finally:
        vs.stop()
    import os

    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print_table(rows, f"viewer frames ({torch.get_num_threads()} torch threads, {os.cpu_count()} CPUs, load {load:.1f}, "
                      f"JPEG by {encoder_name})")
    print_table(rows_q, "query -> highlight")
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps({"frames": rows, "query": rows_q}, indent=2))


if __name__ == "__main__":
    main()
