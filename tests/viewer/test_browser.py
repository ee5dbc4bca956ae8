"""`tiger view` in a real browser: headless Chromium (selenium, the system's chromedriver) asks for
"ball", the highlighted pixels must fall on the ball's footprint in a direct render of the same
camera, then a 20-step recolor edit from the page must change the ball's pixels and nothing else.

Needs Debian's chromium + chromium-driver and selenium (`make test` installs them when root).
"""
from __future__ import annotations

import io
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from .conftest import demo_scene

pytest.importorskip("viser", reason="the viewer needs viser: pip install viser==1.1.1")

CHROMIUM, DRIVER = shutil.which("chromium") or shutil.which("chromium-browser"), shutil.which("chromedriver")
webdriver = pytest.importorskip("selenium.webdriver", reason="pip install selenium (browser test)")
pytestmark = [
    pytest.mark.skipif(not (CHROMIUM and DRIVER), reason="no system browser: apt-get install chromium "
                                                          "chromium-driver (make test does it as root)"),
    pytest.mark.timeout(180),
]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _browser(width=1100, height=700):
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    for a in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", f"--window-size={width},{height}",
              "--force-device-scale-factor=1", "--hide-scrollbars"):
        opts.add_argument(a)
    opts.binary_location = CHROMIUM
    return webdriver.Chrome(service=Service(DRIVER), options=opts)


def _shot(driver) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(driver.get_screenshot_as_png())).convert("RGB")).astype(np.float32)


def _field(driver, label: str):
    from selenium.webdriver.common.by import By

    for el in driver.find_elements(By.TAG_NAME, "label"):
        if el.text.strip() == label:
            found = driver.find_elements(By.ID, el.get_attribute("for"))
            if found:
                return found[0]
            row = el.find_element(By.XPATH, "./../../..")  # viser's row: <p><label> box, the field's box
            fields = [f for f in row.find_elements(By.CSS_SELECTOR, "input, textarea")
                      if f.get_attribute("type") != "hidden"]
            if fields:
                return fields[0]
    raise AssertionError(f"no field labelled {label!r} in the page")


def _button(driver, text: str):
    from selenium.webdriver.common.by import By

    return next(b for b in driver.find_elements(By.TAG_NAME, "button") if b.text.strip() == text)


def _wait_text(driver, needle: str, timeout: float) -> str:
    t0 = time.time()
    while time.time() - t0 < timeout:
        body = driver.find_element("tag name", "body").text
        if needle in body:
            return body
        time.sleep(0.2)
    raise AssertionError(f"{needle!r} did not appear in the page within {timeout} s; page says:\n{body}")


def _frame_number(driver) -> int:
    import re

    m = re.search(r"\(#(\d+)\)", driver.find_element("tag name", "body").text)
    return int(m.group(1)) if m else -1


def _wait_new_full_frame(driver, after: int, timeout: float = 30.0) -> None:
    t0 = time.time()
    while time.time() - t0 < timeout:
        if _frame_number(driver) > after:
            time.sleep(0.5)  # the image decoded and drawn
            return
        time.sleep(0.1)
    raise AssertionError("no new full-size frame reached the page")


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    folder = tmp_path_factory.mktemp("view")
    lab, enc = demo_scene()
    lab.scene.save_ply(folder / "scene.ply")
    enc.save(folder / "text_embeddings.pt")
    port = _free_port()
    proc = subprocess.Popen([sys.executable, "-m", "tiger.cli.main", "view", str(folder / "scene.ply"),
                             "--port", str(port), "--device", "cpu", "--out", str(folder / "saved")],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    t0 = time.time()
    while time.time() - t0 < 60:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                break
        assert proc.poll() is None, proc.stdout.read()
        time.sleep(0.2)
    yield lab, folder, port, proc
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)  # Ctrl-C
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
            raise


def _direct(lab, driver):
    """The browser camera's render (RGB, white background) and the ball's footprint [H, W]."""
    from tiger.render.views import orbit_cameras_around
    from tiger.viewer.camera import camera_from_pose, pose_of

    w, h = driver.execute_script("return [window.innerWidth, window.innerHeight]")
    start = orbit_cameras_around(lab.scene.means, 1, 640, 480, elevation_deg=25.0, up=(0.0, -1.0, 0.0))[0]
    cam = start.resized(w, h) if hasattr(start, "resized") else start
    pose = pose_of(start)
    from tiger.viewer.camera import quat_to_matrix  # noqa: F401  (same convention as the server)

    c2w = start.c2w.double()
    cam = camera_from_pose(_wxyz(c2w[:3, :3]), pose["position"], pose["fov"], w, h)
    with torch.no_grad():
        rgb = lab.scene.render(cam, background=torch.ones(3))["color"].clamp(0, 1).numpy() * 255
    label, alpha = lab.label_image(cam)
    ball = ((label == lab.names.index("ball")) & (alpha > 0.5)).numpy()
    return rgb, ball


def _keep(img: np.ndarray, path: Path) -> np.ndarray:
    """Save a screenshot as a test artefact (pytest keeps the last runs' tmp folders)."""
    from PIL import Image

    Image.fromarray(img.astype(np.uint8)).save(path)
    return img


def _wxyz(R):
    from tests.viewer.test_state import _quat

    return _quat(R)


#: Screenshots are kept here (outputs/ is not tracked); README's docs/images/viewer.png is copied from it.
ARTEFACTS = Path(__file__).resolve().parents[2] / "outputs" / "test-artefacts" / "viewer"


def test_browser_ask_highlight_and_edit(served):
    from scipy.ndimage import binary_dilation

    lab, folder, port, proc = served
    tmp_path = ARTEFACTS
    tmp_path.mkdir(parents=True, exist_ok=True)
    t_start = time.time()
    driver = _browser()
    try:
        driver.get(f"http://127.0.0.1:{port}")
        _wait_text(driver, "(#", 60)  # the first frame
        _wait_new_full_frame(driver, -1)
        _field(driver, "Draw box").click()  # the box lines would count as highlighted pixels
        n = _frame_number(driver)
        _wait_new_full_frame(driver, n - 1)
        plain = _keep(_shot(driver), tmp_path / "viewer_plain.png")
        rgb, ball = _direct(lab, driver)
        h, w = ball.shape
        plain = plain[:h, :w]
        # the page shows our render (JPEG) wherever no panel covers it
        panel_left = min(b.rect["x"] for b in driver.find_elements("tag name", "button") if b.text.strip() == "Ask")
        shown = np.abs(plain - rgb).max(-1) < 40
        shown[:, max(int(panel_left) - 40, 0):] = False  # the control panel (white like the background)
        assert shown.mean() > 0.5, f"only {shown.mean():.0%} of the page matches a direct render"
        assert (shown & ball).sum() > 0.8 * ball.sum(), "the ball is covered or the camera differs"

        n = _frame_number(driver)
        _field(driver, "Query").send_keys("ball")
        _button(driver, "Ask").click()
        _wait_text(driver, "Gaussians selected", 30)
        _wait_new_full_frame(driver, n)
        lit = _keep(_shot(driver), tmp_path / "viewer_ball_selected.png")[:h, :w]
        orange = (lit[..., 0] - lit[..., 2] > 30) & shown  # tint: 0.45 rgb + 0.55 orange; the rest grey
        near = binary_dilation(ball, iterations=3)
        precision = (orange & near).sum() / max(orange.sum(), 1)
        recall = (orange & ball).sum() / max((ball & shown).sum(), 1)
        assert precision > 0.95 and recall > 0.85, (precision, recall)

        n = _frame_number(driver)
        _field(driver, "Instruction").send_keys("make it red")
        steps = _field(driver, "Steps")
        steps.send_keys("\ue009a")  # Ctrl-A
        steps.send_keys("20\t")
        time.sleep(0.5)
        _button(driver, "Run edit").click()
        _wait_text(driver, "edit done", 120)
        _wait_new_full_frame(driver, n)
        time.sleep(1.0)
        after = _keep(_shot(driver), tmp_path / "viewer_ball_recolored.png")[:h, :w]
        diff = np.abs(after - lit).max(-1)
        core = ball & shown & ~binary_dilation(~ball, iterations=2)
        rest = shown & ~binary_dilation(ball, iterations=6)
        _keep(np.where(rest[..., None], diff[..., None], 0).repeat(3, -1) * 4, tmp_path / "diff_rest.png")
        assert np.median(diff[core]) > 30, np.median(diff[core])  # the ball changed
        assert (diff[rest] > 30).mean() < 0.01 and np.median(diff[rest]) < 4  # the rest did not
        assert after[core][:, 0].mean() > lit[core][:, 0].mean()  # redder
        _field(driver, "Draw box").click()  # the page as a user sees it: selection, box, panels
        driver.execute_script(  # headless Chromium's "software WebGL" notice is not the viewer's
            "document.querySelectorAll('.mantine-Notification-root').forEach(e => e.remove())")
        time.sleep(1.0)
        _keep(_shot(driver), tmp_path / "viewer.png")
        print(f"screenshots in {tmp_path}; browser test {time.time() - t_start:.1f} s")
    finally:
        driver.quit()
    proc.send_signal(signal.SIGINT)  # Ctrl-C stops the server cleanly
    assert proc.wait(30) == 0, proc.stdout.read()
