"""The plan job and the plan in 3D (issue 19, item 4): the workbench's plan job starts from a
finished diagnose job's answers, writes the planner's kinematics.csv, plan.json and the
viewer's plan_view.json; the dashboard describes it and offers its kinematics.csv; the
viewer draws the path over the phantom (checked in Debian chromium).

The plan job runs in-process here (``run_plan`` with a local context, as a Dask worker
would run it) on the ``small`` session, from a diagnosis that could tell no kind, asked
for gravity only within 8 s (one kind and one press keep the planner's replays to a few:
the friction plan of 12 s, a slide, took 66 s of the suite; the planner's own test plans
friction through the command line)."""

from __future__ import annotations

import json
import time

import httpx
import numpy as np
import pytest

from tests.app._server import Server, store_finished_jobs
from tests.app.conftest import needs_chromium


@pytest.fixture(scope="module")
def planned(small_session, tmp_path_factory):
    """(data directory, plan summary): session 1, its diagnose job 1 (a diagnosis.json that
    could tell no kind) and the finished plan job 2 made from it."""
    from app.server.jobs.context import JobContext, LocalChannel
    from app.server.jobs.types import DiagnoseParams, PlanParams, run_plan
    from core.simulation.effects import EFFECT_KINDS

    data = tmp_path_factory.mktemp("planned") / "data"
    diag_dir, plan_dir = (data / "jobs" / "1").resolve(), (data / "jobs" / "2").resolve()
    diag_dir.mkdir(parents=True)
    detect = {k: {"min_size": None, "parameters": {}, "why": "test"} for k in EFFECT_KINDS}
    diagnosis = {"session": str(small_session.resolve()), "detectability": detect,
                 "answers": {k: "cannot_tell" for k in EFFECT_KINDS}, "extended": {"effects": []}, "youngs_modulus": {}}
    (diag_dir / "diagnosis.json").write_text(json.dumps(diagnosis))
    params = PlanParams(session_id=1, diagnose_job_id=1, kinds=["gravity"], duration=8.0)
    ctx = JobContext(job_id=2, artifact_dir=plan_dir, channel=LocalChannel(), session_path=small_session.resolve())
    plan_dir.mkdir(parents=True)
    summary = run_plan(params, ctx)
    store_finished_jobs(data, small_session, "small", [
        (1, "diagnose", DiagnoseParams(session_id=1), diagnosis, diag_dir),
        (2, "plan", params, summary, plan_dir)])
    return data, summary


@pytest.mark.slow
def test_plan_job_writes_the_path_its_view_and_kinematics(planned, small_session):
    from core.lab.probing import penetration_depth

    data, summary = planned
    folder = data / "jobs" / "2"
    plan = json.loads((folder / "plan.json").read_text())
    view = json.loads((folder / "plan_view.json").read_text())
    assert summary["plan_view"] is True and summary["targets"] == {"gravity": "asked for"}
    assert "path_phantom" not in summary  # the path stays in the files
    meta = json.loads((small_session / "session.json").read_text())
    np.testing.assert_allclose(view["size"], meta["phantom"]["size"])
    np.testing.assert_allclose(view["centres"], plan["path_phantom"]["centres"])
    centres = np.asarray(view["centres"])
    depth = penetration_depth(centres, view["size"], view["radius"])
    np.testing.assert_array_equal(view["contact"], depth > 0)
    assert 0 < np.mean(view["contact"]) < 1  # presses and travels
    starts = [m["start"] for m in view["moves"]]
    assert len(starts) == len(plan["moves"]) and all(s is not None for s in starts) and starts == sorted(starts)
    for s in starts:
        assert view["contact"][s] and (s == 0 or not view["contact"][s - 1])  # each move's first touch
    rows = (folder / "kinematics.csv").read_text().splitlines()
    assert rows[0] == "t,x,y,z,qx,qy,qz,qw" and len(rows) - 1 == len(view["t"])
    assert view["units"]["gravity"] == "m/s^2" and view["predicted"]["gravity"] is not None


def test_a_plan_job_refuses_a_job_that_is_not_a_diagnosis_of_its_session(small_session, tmp_path):
    from app.server.jobs.context import JobContext, LocalChannel
    from app.server.jobs.types import PlanParams, run_plan
    from core.errors import TissueTwinError

    (tmp_path / "jobs" / "3").mkdir(parents=True)
    ctx = JobContext(job_id=4, artifact_dir=tmp_path / "jobs" / "4", channel=LocalChannel(), session_path=small_session)
    with pytest.raises(TissueTwinError, match="job 3: no usable diagnosis"):
        run_plan(PlanParams(session_id=1, diagnose_job_id=3), ctx)
    (tmp_path / "jobs" / "3" / "diagnosis.json").write_text(json.dumps({"session": "/elsewhere", "detectability": {}}))
    with pytest.raises(TissueTwinError, match="diagnosed /elsewhere, not this plan's session"):
        run_plan(PlanParams(session_id=1, diagnose_job_id=3), ctx)
    with pytest.raises(ValueError, match="unknown effect kind"):
        PlanParams(session_id=1, kinds=["tumour"])


@pytest.mark.slow
@needs_chromium
def test_plan_in_3d_and_its_kinematics_in_chromium(planned, chromium, tmp_path):
    from tests.app.test_browser import _canvas, _state, _until, _variance, _viewer_connected

    data, summary = planned
    server = Server(data, viewer=True)
    page = chromium.new_page(viewport={"width": 1400, "height": 1300})
    try:
        page.goto(server.url + "/")
        page.wait_for_selector("body[data-ready='1']")
        page.wait_for_selector("#plan-summary")  # the dashboard follows the latest finished job: the plan
        assert "gravity" in page.inner_text("#plan-summary")
        assert page.locator("#plan-description li").count() == len(summary["description"])
        href = page.get_attribute("#plan-kinematics", "href")
        csv = httpx.get(server.url + href).text
        assert csv == (data / "jobs" / "2" / "kinematics.csv").read_text()

        frame = page.frame_locator("#viewer-frame")
        _viewer_connected(page, server)
        time.sleep(1.0)
        canvas = _canvas(page)
        before = canvas.screenshot(path=str(tmp_path / "viewer-empty.png"))
        page.click("#results .plan-btn")
        st = _until(lambda: (s := _state(server.url))["mode"] == "plan" and s, "the plan in the viewer")
        view = json.loads((data / "jobs" / "2" / "plan_view.json").read_text())
        assert st["plan"]["job_id"] == 2 and st["plan"]["segments"] == 1
        assert len(st["plan"]["labels"]) == len(view["moves"])
        frame.get_by_role("tab", name="Plan").click()
        frame.get_by_text("record the probe force", exact=False).first.wait_for(timeout=10_000)
        time.sleep(1.0)
        after = canvas.screenshot(path=str(tmp_path / "viewer-plan.png"))
        assert _variance(after) > 20.0
        from PIL import Image
        import io

        a, b = (np.asarray(Image.open(io.BytesIO(x)).convert("L"), float) for x in (before, after))
        assert np.mean(np.abs(a - b) > 16) > 0.01, "the plan did not change the canvas"
        page.screenshot(path=str(tmp_path / "dashboard-plan.png"), full_page=True)
    finally:
        page.close()
        server.stop()
