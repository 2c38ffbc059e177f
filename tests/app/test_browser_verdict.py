"""One verdict on E in the dashboard (issue 19): a finished sweep whose data cannot pin E
down says "not identifiable", with the reason, and shows no bold "best" value.

A real sweep job (three values of E on one sequence of the sample session, which has no
force data and no gravity) on a real workbench, read in headless chromium.
"""

from __future__ import annotations

import time

import httpx
import pytest

from tests.app._server import Server
from tests.app.conftest import needs_chromium

pytestmark = [pytest.mark.slow, needs_chromium]


def _wait_done(url: str, job_id: int, timeout: float = 120.0) -> dict:
    deadline = time.monotonic() + timeout  # guards a hang only
    while True:
        job = httpx.get(f"{url}/api/jobs/{job_id}").json()
        if job["status"] in ("done", "failed", "cancelled", "interrupted"):
            return job
        assert time.monotonic() < deadline, f"job {job_id} still {job['status']}"
        time.sleep(0.3)


def test_a_flat_sweep_says_not_identifiable_and_names_no_best_value(sample_session, tmp_path, chromium):
    (tmp_path / "data").mkdir()
    server = Server(tmp_path / "data", args=["--workers", "1"])
    try:
        sid = httpx.post(f"{server.url}/api/sessions", json={"path": str(sample_session)}).json()["id"]
        params = {"session_id": sid, "youngs": [1e3, 1e4, 1e5], "sequences": ["seq02"]}
        job = httpx.post(f"{server.url}/api/jobs", json={"type": "sweep", "params": params}).json()
        done = _wait_done(server.url, job["id"])
        assert done["status"] == "done", done["error"]
        verdict = done["result"]["youngs_modulus"]
        assert verdict["identifiable"] is False and verdict["value"] is None, verdict
        assert done["result"]["best"] in (1e3, 1e4, 1e5)  # the old key stays, for other tools
        page = chromium.new_page(viewport={"width": 1400, "height": 1100})
        try:
            page.goto(server.url + "/")
            page.wait_for_selector("body[data-ready='1']")
            page.click(f"#jobs-table tr[data-job-id='{job['id']}'] a.job-link")
            page.wait_for_selector("#sweep-table")
            text = page.inner_text("#result-body .youngs-verdict")
            assert text.startswith("E not identifiable from these data: ") and verdict["reason"] in text, text
            assert page.get_attribute("#result-body .youngs-verdict", "data-identifiable") == "false"
            assert page.locator("#sweep-table tr.best").count() == 0
            # read the cells in one evaluation once they are all attached: the dashboard's poll
            # can re-render the result between resolving the cells and styling them (a detached
            # cell's computed font weight is '', seen once in CI)
            weights = page.wait_for_function(
                "() => { const tds = [...document.querySelectorAll('#sweep-table td')];"
                " const w = tds.map((td) => td.isConnected ? getComputedStyle(td).fontWeight : '');"
                " return tds.length > 0 && w.every((x) => x) ? w : null; }").json_value()
            assert len(weights) == 6 and all(int(w) < 600 for w in weights), weights  # nothing in bold
            assert page.locator("#result-body b, #result-body strong").count() == 0
            assert "best" not in page.inner_text("#result-body").split("log")[0].lower()
            page.screenshot(path=str(tmp_path / "sweep-verdict.png"), full_page=True)
        finally:
            page.close()
    finally:
        server.stop()
