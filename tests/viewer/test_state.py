"""The viewer's state in-process: asking, point prompt, edit jobs, Undo/Redo, Save."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tiger.retrieval import retrieve
from tiger.scene import GaussianScene
from tiger.viewer.camera import camera_from_pose, pose_of, quat_to_matrix
from tiger.viewer.frames import MODES, render_frame
from tiger.viewer.jobs import DeleteJob, EditJob, EditRequest, guidance_availability
from tiger.viewer.state import MAX_TEXT, ViewerError, ViewerState


def _state(tabletop, tmp_path=None, **kw):
    lab, enc = tabletop
    return ViewerState(lab.scene, enc, out_dir=(tmp_path or "unused") , **kw)


def test_ask_equals_retrieve(tabletop):
    lab, enc = tabletop
    st = _state(tabletop)
    for text in ("ball", "mug"):
        sel = st.ask(text)
        ref = retrieve(lab.scene, text, encoder=enc, tau="auto")
        assert torch.equal(sel.mask, ref.mask) and sel.count == ref.count > 0
        truth = lab.labels == lab.names.index(text)
        assert float((sel.mask & truth).sum()) / sel.count > 0.95
    sel = st.ask("ball, mug")  # several queries: the union
    both = retrieve(lab.scene, "ball", encoder=enc).mask | retrieve(lab.scene, "mug", encoder=enc).mask
    assert torch.equal(sel.mask, both) and len(sel.boxes()) == 2
    st.set_tau(0.99)  # a number: the same rule as retrieve(tau=0.99)
    assert torch.equal(st.selection.mask, retrieve(lab.scene, "ball", encoder=enc, tau=0.99).mask |
                       retrieve(lab.scene, "mug", encoder=enc, tau=0.99).mask)


def test_ask_refuses_bad_text(tabletop):
    st = _state(tabletop)
    with pytest.raises(ViewerError, match="at most"):
        st.ask("x" * (MAX_TEXT + 1))
    with pytest.raises(ViewerError, match="type a query"):
        st.ask(" , ")
    with pytest.raises(ViewerError, match="teapot"):
        st.ask("teapot")
    assert st.selection is None


def test_no_language_disables_asking(tabletop):
    lab, enc = tabletop
    scene = lab.scene.clone()
    scene.lang = None
    st = ViewerState(scene, enc)
    assert "no language features" in st.language_note()
    with pytest.raises(ViewerError, match="no language features"):
        st.ask("ball")
    with pytest.raises(ViewerError, match="no language features"):
        st.set_view(mode="relevancy")


def test_point_prompt_selects_the_object_under_the_pixel(tabletop, tabletop_camera):
    lab, _ = tabletop
    st = _state(tabletop)
    label, alpha = lab.label_image(tabletop_camera)
    ball = lab.names.index("ball")
    ys, xs = torch.nonzero((label == ball) & (alpha > 0.9), as_tuple=True)
    k = len(ys) // 2  # a pixel inside the ball's footprint
    x, y = (float(xs[k]) + 0.5) / tabletop_camera.width, (float(ys[k]) + 0.5) / tabletop_camera.height
    sel = st.point_prompt(tabletop_camera, x, y)
    truth = lab.labels == ball
    precision = float((sel.mask & truth).sum()) / max(sel.count, 1)
    recall = float((sel.mask & truth).sum()) / float(truth.sum())
    assert precision > 0.95 and recall > 0.9, (precision, recall)
    with pytest.raises(ViewerError, match="nothing under the cursor"):
        st.point_prompt(tabletop_camera, 0.01, 0.01)  # background corner


def test_browser_pose_round_trip():
    from tiger.render.views import orbit_cameras

    cam = orbit_cameras(1, 320, 180, center=(0.1, -0.2, 0.3), radius=2.0, elevation_deg=30.0, up=(0.0, -1.0, 0.0))[0]
    pose = pose_of(cam)
    c2w = cam.c2w.double()
    w, x, y, z = _quat(c2w[:3, :3])
    back = camera_from_pose((w, x, y, z), pose["position"], pose["fov"], 320, 180)
    assert torch.allclose(back.viewmat.double(), cam.viewmat.double(), atol=1e-9)
    assert torch.allclose(back.K.double(), cam.K.double(), atol=1e-9)
    assert torch.allclose(quat_to_matrix((w, x, y, z)), c2w[:3, :3], atol=1e-12)


def _quat(R):
    """Independent rotation -> quaternion (Shepperd), for the round trip."""
    t = float(R.trace())
    if t > 0:
        s = 2 * math.sqrt(t + 1)
        return (0.25 * s, float(R[2, 1] - R[1, 2]) / s, float(R[0, 2] - R[2, 0]) / s, float(R[1, 0] - R[0, 1]) / s)
    i = int(torch.argmax(torch.diagonal(R)))
    j, k = (i + 1) % 3, (i + 2) % 3
    s = 2 * math.sqrt(1 + float(R[i, i] - R[j, j] - R[k, k]))
    q = [0.0] * 4
    q[0] = float(R[k, j] - R[j, k]) / s
    q[1 + i] = 0.25 * s
    q[1 + j] = float(R[j, i] + R[i, j]) / s
    q[1 + k] = float(R[k, i] + R[i, k]) / s
    return tuple(q)


def test_frames_every_mode(tabletop, tabletop_camera):
    lab, _ = tabletop
    st = _state(tabletop)
    st.ask("ball")
    direct = lab.scene.render(tabletop_camera, background=torch.ones(3))["color"]
    for mode in MODES:
        st.set_view(mode=mode, show="off")
        img = render_frame(st.frame_inputs(), tabletop_camera)
        assert img.shape == (120, 160, 3) and img.dtype == np.uint8 and img.std() > 5, mode
        if mode == "RGB":  # the plain frame is the rasterizer's render, rounded to 8 bits
            assert np.abs(img.astype(np.float32) / 255 - direct.clamp(0, 1).numpy()).max() <= 0.5 / 255 + 1e-6
    st.set_view(mode="RGB", show="alone")
    alone = render_frame(st.frame_inputs(), tabletop_camera)
    ref = lab.scene.subset(st.selection.mask).render(tabletop_camera, background=torch.ones(3))["color"]
    assert np.abs(alone.astype(np.float32) / 255 - ref.clamp(0, 1).numpy()).max() <= 0.5 / 255 + 1e-6


def _edit(st, steps=6, **kw):
    return EditJob(st, EditRequest("make it red", "recolor", steps=steps, size=48, preview_every=2, **kw),
                   torch.device("cpu")).start()


def test_edit_job_runs_undo_redo_bit_identical(tabletop, tmp_path):
    lab, _ = tabletop
    st = _state(tabletop, tmp_path)
    before = lab.scene.clone()
    with pytest.raises(ViewerError, match="select something"):
        _edit(st)
    st.ask("ball")
    job = _edit(st)
    seen = []
    while not job.wait(0.01):
        seen.append(job.progress)
    assert job.outcome == "done", job.message
    assert job.progress == 1.0 and any(0 < p < 1 for p in seen)
    assert len(st.history) == 2 and st.index == 1
    ball = lab.labels == lab.names.index("ball")
    edited = st.scene
    red = edited.rgb[: len(lab.scene)][ball].mean(0)
    assert red[0] > lab.scene.rgb[ball].mean(0)[0] + 0.05  # redder
    assert torch.equal(edited.means[: len(lab.scene)][~ball], lab.scene.means[~ball])  # the rest untouched
    st.undo()
    assert st.scene.equal(before)  # bit for bit
    st.redo()
    assert st.scene is edited
    with pytest.raises(ViewerError, match="nothing to redo"):
        st.redo()


def test_edit_job_cancel_leaves_scene(tabletop, tmp_path):
    lab, _ = tabletop
    st = _state(tabletop, tmp_path)
    st.ask("ball")
    before = st.scene.clone()
    job = _edit(st, steps=400)
    while job.progress == 0 and not job.finished.is_set():
        job.wait(0.01)
    job.cancel()
    assert job.wait(60)
    assert job.outcome == "cancelled" and len(st.history) == 1 and st.scene.equal(before)
    assert st.preview is None


def test_failed_job_reports_and_keeps_scene(tabletop, tmp_path):
    st = _state(tabletop, tmp_path)
    st.ask("ball")
    before = st.scene.clone()
    job = EditJob(st, EditRequest("make it red", "recolor", steps=3, size=48), torch.device("cpu"))
    job.request.guidance = "no-such-guidance"  # passes the page's checks, fails inside the worker
    job.start().wait(60)
    assert job.outcome == "failed" and "no-such-guidance" in job.error
    assert len(st.history) == 1 and st.scene.equal(before)


def test_guidances_offered():
    avail = guidance_availability(None)
    assert avail["recolor"] == ""
    assert set(avail) == {"recolor", "ip2p", "ip2p+mvdream"}


def test_delete_job_removes_selection(tabletop, tmp_path):
    lab, _ = tabletop
    st = _state(tabletop, tmp_path)
    st.ask("ball")
    n_ball = st.selection.count
    job = DeleteJob(st, steps=2, views=2, size=(64, 48)).start()
    assert job.wait(300) and job.outcome == "done", job.message
    assert len(st.scene) <= len(lab.scene) - n_ball + 500
    st.undo()
    assert st.scene is lab.scene


def test_save_is_atomic_and_numbered(tabletop, tmp_path, monkeypatch):
    st = _state(tabletop, tmp_path / "out")
    p1 = st.save()
    p2 = st.save()
    assert p1.name == "scene_001.ply" and p2.name == "scene_002.ply"
    assert GaussianScene.load_ply(p1).equal(GaussianScene.load_ply(p2))
    assert sorted(x.name for x in (tmp_path / "out").iterdir()) == ["scene_001.lang_pca.npz", "scene_001.ply",
                                                                    "scene_002.lang_pca.npz", "scene_002.ply"] \
        or sorted(x.name for x in (tmp_path / "out").iterdir()) == ["scene_001.ply", "scene_002.ply"]
    # a write that fails half-way leaves no partial file behind
    import tiger.scene.ply as ply

    def broken(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(ply, "_write_body", broken, raising=False)
    monkeypatch.setattr(GaussianScene, "save_ply", lambda self, path, **k: _fail_atomic(path))
    with pytest.raises(OSError):
        st.save()
    assert not (tmp_path / "out" / "scene_003.ply").exists()
    assert not [x for x in (tmp_path / "out").iterdir() if x.name.startswith(".") or x.suffix == ".tmp"]


def _fail_atomic(path):
    from tiger.utils.io import atomic_write

    with atomic_write(path, "wb") as fh:
        fh.write(b"partial")
        raise OSError("disk full")


class _FakeScene:
    def __init__(self) -> None:
        self.sent = []

    def set_background_image(self, img, format="jpeg", jpeg_quality=None):
        self.sent.append((img.shape, format, jpeg_quality))


class _FakeClient:
    def __init__(self, cid: int) -> None:
        self.client_id, self.scene = cid, _FakeScene()


def test_frame_scheduling_latest_camera_small_while_moving(tabletop, tabletop_camera):
    """Per tab: the latest pose is drawn (small while it moves, canvas size once it rests), a
    drawn pose is not drawn again, and a scene change redraws every tab."""
    import time

    from tiger.viewer.server import ClientView, ViewerServer

    st = _state(tabletop)
    server = ViewerServer(st, device=torch.device("cpu"), moving_pixels=80 * 45, rest_s=0.05)
    server.gui = None
    pose = pose_of(tabletop_camera)
    wxyz = _quat(tabletop_camera.c2w.double()[:3, :3])
    a, b = ClientView(_FakeClient(1)), ClientView(_FakeClient(2))
    server.views = {1: a, 2: b}
    assert server._next_request() is None  # no camera yet
    now = time.perf_counter()
    a.pose, a.moved_at, a.dirty = (wxyz, pose["position"], pose["fov"], 320, 180), now, True
    a.pose = (wxyz, pose["position"], pose["fov"], 640, 360)  # a newer message replaces the older
    view, full = server._next_request()
    assert view is a and not full  # moving: small
    view.dirty = False
    server.draw(view, full)
    view.sent_version, view.sent_full = st.version, full
    assert a.client.scene.sent[-1][0] == (45, 80, 3)
    time.sleep(0.06)
    view, full = server._next_request()
    assert view is a and full  # rested: the canvas size of the latest pose
    server.draw(view, full)
    view.sent_version, view.sent_full = st.version, full
    assert a.client.scene.sent[-1][0] == (360, 640, 3)
    assert server._next_request() is None  # nothing new
    b.pose, b.moved_at, b.dirty = (wxyz, pose["position"], pose["fov"], 200, 100), now - 1, False
    st.ask("ball")  # the scene's look changed: both tabs are redrawn
    assert {server._next_request()[0].client.client_id} <= {1, 2}
    a.sent_version = st.version
    assert server._next_request()[0] is b


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_frames_and_selection_match_cpu(tabletop, tabletop_camera):
    lab, enc = tabletop
    cpu = ViewerState(lab.scene, enc)
    gpu = ViewerState(lab.scene.to("cuda"), enc)
    assert torch.equal(cpu.ask("ball").mask, gpu.ask("ball").mask.cpu())
    for mode in ("RGB", "depth", "relevancy"):
        cpu.set_view(mode=mode)
        gpu.set_view(mode=mode)
        a = render_frame(cpu.frame_inputs(), tabletop_camera).astype(np.int16)
        b = render_frame(gpu.frame_inputs(), tabletop_camera.to("cuda")).astype(np.int16)
        assert np.abs(a - b).mean() < 1.0, mode
