"""A real workbench server (uvicorn, loopback) as a user starts it: `tissuetwin serve`."""

from __future__ import annotations

import signal
import sqlite3

import httpx
import pytest

# the helpers live in tests/app/_server.py (shared with tests/reliability); re-exported
# here for the modules that import them from this one
from tests.app._server import ROOT, Server, _free_port, _wait  # noqa: F401


@pytest.mark.slow
def test_sweep_over_http_survives_restarts(small_session, tmp_path):
    data = tmp_path / "data"
    server = Server(data)
    try:
        sid = httpx.post(f"{server.url}/api/sessions", json={"path": str(small_session)}).json()["id"]
        r = httpx.post(f"{server.url}/api/jobs", json={"type": "sweep", "params": {
            "session_id": sid, "youngs": [1e2, 1e4], "sequences": ["seq02"]}})
        assert r.status_code == 201, r.text
        job = _wait(server.url, r.json()["id"], {"done", "failed", "cancelled"})
        assert job["status"] == "done", job["error"]
        long = httpx.post(f"{server.url}/api/jobs", json={"type": "sweep", "params": {
            "session_id": sid, "e_min": 10, "e_max": 1e6, "per_decade": 4}}).json()
        _wait(server.url, long["id"], {"running"})
    finally:
        server.stop(signal.SIGKILL)  # a crash: no chance to clean up

    db = sqlite3.connect(data / "workbench.db")
    rows = dict(db.execute("select id, status from jobs").fetchall())
    db.close()
    assert rows[job["id"]] == "done" and rows[long["id"]] == "running"

    server = Server(data)
    try:
        again = httpx.get(f"{server.url}/api/jobs/{job['id']}").json()
        assert again["status"] == "done" and again["result"] == job["result"]
        csv = httpx.get(f"{server.url}/api/jobs/{job['id']}/artifacts/sweep.csv")
        assert csv.status_code == 200 and csv.text.startswith("youngs_modulus,")
        lost = httpx.get(f"{server.url}/api/jobs/{long['id']}").json()
        assert lost["status"] == "interrupted" and "server stopped" in lost["error"]
    finally:
        server.stop()  # graceful this time
    db = sqlite3.connect(data / "workbench.db")
    assert db.execute("select status from jobs where id = ?", (job["id"],)).fetchone() == ("done",)
    db.close()
