"""The dashboard's analysis plots in a real headless browser: the training loss curves
of a train job (an SVG drawn by static/app.js from the job's ``losses``)."""

from __future__ import annotations

import time

import httpx
import pytest

from tests.app._server import Server
from tests.app.conftest import needs_chromium

pytestmark = [pytest.mark.slow, needs_chromium]


def _wait_done(url: str, job_id: int, timeout: float = 300.0) -> dict:
    deadline = time.monotonic() + timeout  # guards a hang only
    while True:
        job = httpx.get(f"{url}/api/jobs/{job_id}").json()
        if job["status"] in ("done", "failed", "cancelled", "interrupted"):
            return job
        assert time.monotonic() < deadline, f"job {job_id} still {job['status']}"
        time.sleep(0.5)


def test_training_loss_curves_in_chromium(small_session, tmp_path, chromium):
    (tmp_path / "data").mkdir()
    server = Server(tmp_path / "data")
    try:
        sid = httpx.post(f"{server.url}/api/sessions", json={"path": str(small_session)}).json()["id"]
        params = {"session_id": sid, "sequences": ["seq00", "seq01", "seq02"], "widths": [4, 8, 8], "epochs": 3,
                  "patience": 5, "max_points": 128, "batch_size": 8}
        job = httpx.post(f"{server.url}/api/jobs", json={"type": "train", "params": params}).json()
        done = _wait_done(server.url, job["id"])
        assert done["status"] == "done", done["error"]
        losses = done["result"]["losses"]
        page = chromium.new_page(viewport={"width": 1400, "height": 1100})
        try:
            page.goto(server.url + "/")
            page.wait_for_selector("body[data-ready='1']")
            page.click(f"#jobs-table tr[data-job-id='{job['id']}'] a.job-link")
            page.wait_for_selector("svg.loss-plot")
            assert page.get_attribute("svg.loss-plot", "data-epochs") == str(len(losses))
            for series in ("train", "validation"):  # one vertex per epoch, in epoch order
                pts = page.get_attribute(f"svg.loss-plot polyline.loss-{series}", "points").split()
                xs = [float(p.split(",")[0]) for p in pts]
                assert len(pts) == len(losses) and xs == sorted(xs) and len(set(xs)) == len(xs)
            # the plot's vertical order follows the losses (SVG y grows downwards)
            ys = [float(p.split(",")[1]) for p in page.get_attribute("svg.loss-plot polyline.loss-train", "points").split()]
            vals = [e["train_loss"] for e in losses]
            for i in range(len(vals) - 1):
                if vals[i] != vals[i + 1]:
                    assert (ys[i] > ys[i + 1]) == (vals[i] < vals[i + 1])
            table = page.inner_text("#train-table")
            assert "no network" in table and "corrected offline" in table
            page.screenshot(path=str(tmp_path / "train-losses.png"), full_page=True)
        finally:
            page.close()
    finally:
        server.stop()
