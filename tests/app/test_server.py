"""A real workbench server (uvicorn, loopback) as a user starts it: `tissuetwin serve`."""

from __future__ import annotations

import os
import signal
import socket
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

ROOT = Path(__file__).resolve().parents[2]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Server:
    """``tissuetwin serve`` in its own process group (so the Dask workers go with it)."""

    def __init__(self, data: Path, viewer: bool = False):
        self.port = _free_port()
        args = [sys.executable, "-m", "app.cli", "serve", "--port", str(self.port), "--data", str(data)]
        args += ["--viewer-port", str(_free_port())] if viewer else ["--no-viewer"]
        self.log = open(data.parent / f"server-{self.port}.log", "w")
        self.proc = subprocess.Popen(args, cwd=ROOT, stdout=self.log, stderr=subprocess.STDOUT, start_new_session=True)
        self.url = f"http://127.0.0.1:{self.port}"
        deadline = time.monotonic() + 90
        while True:
            try:
                if httpx.get(f"{self.url}/api/health", timeout=1).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.stop(signal.SIGKILL)
                pytest.fail(f"server did not start: {(data.parent / f'server-{self.port}.log').read_text()[-2000:]}")
            time.sleep(0.3)

    def stop(self, sig=signal.SIGTERM) -> None:
        if self.proc.poll() is None:
            try:
                os.killpg(self.proc.pid, sig)
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()
        try:  # whatever of the group is left (Dask workers after a SIGKILL of the server)
            os.killpg(self.proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        self.log.close()


def _wait(url: str, job_id: int, until: set[str]) -> dict:
    deadline = time.monotonic() + 180
    while True:
        job = httpx.get(f"{url}/api/jobs/{job_id}").json()
        if job["status"] in until:
            return job
        assert time.monotonic() < deadline, job
        time.sleep(0.3)


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
