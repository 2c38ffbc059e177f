"""The dashboard and the 3D viewer in a real headless browser (Debian chromium + playwright).

Launch a replay from the dashboard, watch it finish, open it in the embedded viser
viewer, scrub the timeline, pick points for ICP initialisation by clicking the canvas,
accept the calibration. Screenshots go to the test's tmp dir; the 3D canvas must not be
blank (pixel variance).
"""

from __future__ import annotations

import io
import json
import shutil
import time

import httpx
import numpy as np
import pytest

from tests.app._server import Server
from tests.app.conftest import needs_chromium

pytestmark = [pytest.mark.slow, needs_chromium]


def _state(url):
    return httpx.get(f"{url}/api/viewer").json()


def _until(fn, what: str, timeout: float = 60.0):
    deadline = time.monotonic() + timeout
    while True:
        value = fn()
        if value:
            return value
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.2)


def _viewer_connected(page, server, what: str = "the viewer tab"):
    """Wait for the dashboard's viewer iframe to connect to the viewer server. Chromium
    throttles an off-screen cross-origin iframe (the viewer's websocket may then never
    open), so the iframe is scrolled into view first, as a user looking at it would."""
    page.locator("#viewer-frame").scroll_into_view_if_needed()
    page.frame_locator("#viewer-frame").locator("canvas").first.wait_for(timeout=60_000)
    return _until(lambda: _state(server.url)["clients"] >= 1, what)


def _canvas(page, frame=None):
    """The largest canvas of the viewer (the 3D view), in the dashboard's iframe or in ``frame``."""
    frame = frame or page.frame_locator("#viewer-frame")
    canvases = frame.locator("canvas")
    best, area = None, 0
    for i in range(canvases.count()):
        box = canvases.nth(i).bounding_box()
        if box and box["width"] * box["height"] > area:
            best, area = canvases.nth(i), box["width"] * box["height"]
    return best


def _variance(png: bytes) -> float:
    from PIL import Image

    return float(np.asarray(Image.open(io.BytesIO(png)).convert("L"), dtype=np.float64).var())


def _project(points: np.ndarray, cam: dict, box: dict) -> np.ndarray:
    """Pixel positions (page coordinates) of world points under the viewer's perspective camera."""
    pos, look, up = (np.asarray(cam[k], float) for k in ("position", "look_at", "up"))
    f = (look - pos) / np.linalg.norm(look - pos)
    r = np.cross(f, up)
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    v = points - pos
    x, y, z = v @ r, v @ u, v @ f
    t = np.tan(cam["fov"] / 2)
    aspect = box["width"] / box["height"]
    nx, ny = x / (z * t * aspect), y / (z * t)
    return np.stack([box["x"] + (nx + 1) / 2 * box["width"], box["y"] + (1 - ny) / 2 * box["height"]], axis=1)


def _corners(size) -> np.ndarray:
    sx, sy, sz = (float(v) for v in size)
    return np.array([[x, y, z] for x in (0.0, sx) for y in (0.0, sy) for z in (0.0, sz)])


def _span(cam: dict, size, box: dict) -> float:
    """The larger share of the canvas's width or height the phantom box covers."""
    px = _project(_corners(size), cam, box)
    return max(float(np.ptp(px[:, 0])) / box["width"], float(np.ptp(px[:, 1])) / box["height"])


def _camera_framing(url, size):
    cam = _state(url)["camera"]
    centre = 0.5 * np.asarray(size, float)
    return cam if cam and np.allclose(cam["look_at"], centre, atol=2e-3) else None


def _camera_settled(url, position):
    cam = _state(url)["camera"]
    return cam if cam and np.allclose(cam["position"], position, atol=2e-3) else None


def test_dashboard_job_viewer_and_icp_in_chromium(small_session, tmp_path, chromium):
    session = tmp_path / "s3"
    shutil.copytree(small_session, session)
    shots = tmp_path / "screenshots"
    shots.mkdir()
    server = Server(tmp_path / "data", viewer=True)
    try:
        page = chromium.new_page(viewport={"width": 1400, "height": 1500})
        try:
            page.goto(server.url + "/")
            page.wait_for_selector("body[data-ready='1']")

            # register the session, launch a replay of one sequence, wait for it
            page.fill("#session-path", str(session))
            page.click("#register-btn")
            page.wait_for_selector("#sessions-table tr[data-session-id]")
            sid = int(page.get_attribute("#sessions-table tr[data-session-id]", "data-session-id"))
            page.select_option("#job-type", "replay")
            page.fill("#f-sequences", "seq01")
            page.click("#launch-btn")
            page.wait_for_selector("#jobs-table tr[data-job-id]")
            job_id = int(page.get_attribute("#jobs-table tr[data-job-id]", "data-job-id"))
            page.wait_for_selector(f"#jobs-table tr[data-job-id='{job_id}'][data-status='done']", timeout=120_000)
            page.click(f"#jobs-table tr[data-job-id='{job_id}'] a.job-link")
            page.wait_for_selector("#replay-table")
            page.screenshot(path=str(shots / "dashboard.png"), full_page=True)

            # the viewer: show the run, the canvas is drawn, scrub the slider
            frame = page.frame_locator("#viewer-frame")
            _viewer_connected(page, server, "the viewer client")
            t0 = time.monotonic()
            page.click(f"#jobs-table tr[data-job-id='{job_id}'] .view-btn")
            _until(lambda: _state(server.url)["sequence"] == "seq01", "the run in the viewer")
            frame.get_by_text("frame 0 /", exact=False).wait_for(timeout=30_000)
            first_frame = time.monotonic() - t0
            time.sleep(1.0)  # let WebGL draw
            canvas = _canvas(page)
            # the first view frames the phantom (measured: the box spans 0.42 of the canvas; the
            # former fixed 0.2 m distance gives about 0.17 by the same projection)
            size0 = json.loads((session / "session.json").read_text())["phantom"]["size"]
            cam0 = _until(lambda: (c := _state(server.url)["camera"]) and c, "the viewer's camera")
            assert _span(cam0, size0, canvas.bounding_box()) > 0.35
            png0 = canvas.screenshot(path=str(shots / "viewer-frame0.png"))
            assert _variance(png0) > 20.0, "3D canvas is blank"

            slider = frame.get_by_role("slider").first
            slider.focus()
            for _ in range(5):
                slider.press("ArrowRight")
            st = _until(lambda: (s := _state(server.url))["frame"] == 5 and s, "frame 5 after moving the slider")
            assert st["time"] > 0
            frame.get_by_text("frame 5 /", exact=False).wait_for(timeout=10_000)
            frame.get_by_role("button", name="+1 frame").click()
            _until(lambda: _state(server.url)["frame"] == 6, "frame 6 after +1")
            png6 = canvas.screenshot(path=str(shots / "viewer-frame6.png"))
            assert _variance(png6) > 20.0

            # ICP initialisation by clicking: 4 top-face points on the reference cloud, then on the phantom
            page.click(f"#sessions-table tr[data-session-id='{sid}'] .icp-btn")
            _until(lambda: _state(server.url)["mode"] == "icp", "ICP mode")
            meta = json.loads((session / "session.json").read_text())
            sx, sy, sz = meta["phantom"]["size"]
            inset = 0.01
            pp = np.array([[inset, inset, sz], [sx - inset, inset, sz], [sx - inset, sy - inset, sz], [inset, sy - inset, sz]])
            T = np.linalg.inv(np.array(json.loads((session / "truth.json").read_text())["T_phantom_camera"]))
            pc = pp @ T[:3, :3].T + T[:3, 3]  # truth only tells the test where to click
            cam = _until(lambda: _camera_settled(server.url, [0.0, 0.0, 0.0]), "the camera at the depth camera")
            time.sleep(0.5)
            box = canvas.bounding_box()
            for x, y in _project(pc, cam, box):
                page.mouse.click(float(x), float(y))
                time.sleep(0.3)
            picks = _until(lambda: len(_state(server.url)["icp"]["picks_reference"]) == 4 and _state(server.url)["icp"],
                           "4 picks on the reference cloud", timeout=20)
            canvas.screenshot(path=str(shots / "icp-reference-picks.png"))
            frame.get_by_role("tab", name="ICP init").click()
            frame.get_by_role("button", name="phantom surface").click()
            cam = _until(lambda: _camera_framing(server.url, [sx, sy, sz]), "the camera framing the phantom")
            time.sleep(0.5)
            assert _span(cam, [sx, sy, sz], canvas.bounding_box()) > 0.35
            for x, y in _project(pp, cam, canvas.bounding_box()):
                page.mouse.click(float(x), float(y))
                time.sleep(0.3)
            picks = _until(lambda: len((s := _state(server.url)["icp"])["picks_phantom"]) == 4 and s, "4 phantom picks", timeout=20)
            err_ref = np.linalg.norm(np.asarray(picks["picks_reference"]) - pc, axis=1)
            err_ph = np.linalg.norm(np.asarray(picks["picks_phantom"]) - pp, axis=1)
            assert err_ref.max() < 0.006 and err_ph.max() < 0.006, (err_ref, err_ph)

            frame.get_by_role("button", name="Compute ICP").click()
            res = _until(lambda: _state(server.url)["icp"]["result"], "the ICP result", timeout=60)
            assert res["rms"] < 0.002 and res["rms_init"] < 0.01
            frame.get_by_text("after", exact=False).first.wait_for()
            time.sleep(1.0)
            png_icp = canvas.screenshot(path=str(shots / "icp-before-after.png"))
            assert _variance(png_icp) > 20.0
            frame.get_by_role("button", name="Accept calibration").click()
            stored = _until(lambda: httpx.get(f"{server.url}/api/sessions/{sid}/calibration").json()["picked"], "saved calibration")
            T_true = np.array(json.loads((session / "truth.json").read_text())["T_phantom_camera"])
            assert np.linalg.norm(np.array(stored["T_phantom_camera"])[:3, 3] - T_true[:3, 3]) < 0.003
            assert (session / "calibration" / "picked.json").exists()
            page.screenshot(path=str(shots / "dashboard-icp.png"), full_page=True)
            print(f"time to first frame in the viewer: {first_frame:.2f} s (server side {st['first_frame_seconds']:.2f} s)")
        finally:
            page.close()
    finally:
        server.stop()
