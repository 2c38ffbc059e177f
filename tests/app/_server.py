"""A real workbench server for tests: ``tissuetwin serve`` in its own process on loopback.

Shared by tests/app (test_server, test_browser, test_postgres) and tests/reliability.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterable, Mapping
from pathlib import Path

import httpx
import pytest

ROOT = Path(__file__).resolve().parents[2]
FINAL = {"done", "failed", "cancelled", "interrupted"}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Server:
    """``tissuetwin serve`` in its own process group (so the Dask workers go with it).

    Args:
        data: the data directory (``--data``); the log goes to ``data.parent/server-<port>.log``.
        viewer: start the viser viewer on a free port.
        args: more ``serve`` arguments (``["--scheduler", address]``, ``["--workers", "1"]``).
        env: environment overrides for the server process.
    """

    def __init__(self, data: Path, viewer: bool = False, args: Iterable[str] = (), env: Mapping[str, str] | None = None):
        # A port found free here may be taken before the server binds it (its own Dask
        # workers pick ephemeral ports first): then start again on another port.
        for _ in range(3):
            if self._start(data, viewer, args, env):
                return
        pytest.fail(f"server did not start: {self.log_path.read_text()[-2000:]}")

    def _start(self, data: Path, viewer: bool, args: Iterable[str], env: Mapping[str, str] | None) -> bool:
        """Start ``serve`` on a fresh port; False when a port it was given was taken meanwhile."""
        self.port = _free_port()
        cmd = [sys.executable, "-m", "app.cli", "serve", "--port", str(self.port), "--data", str(data)]
        cmd += ["--viewer-port", str(_free_port())] if viewer else ["--no-viewer"]
        cmd += list(args)
        self.log_path = data.parent / f"server-{self.port}.log"
        self.log = open(self.log_path, "w")
        self.proc = subprocess.Popen(cmd, cwd=ROOT, stdout=self.log, stderr=subprocess.STDOUT, start_new_session=True,
                                     env={**os.environ, **(env or {})})
        self.url = f"http://127.0.0.1:{self.port}"
        deadline = time.monotonic() + 90
        while True:
            try:
                if httpx.get(f"{self.url}/api/health", timeout=1).status_code == 200:
                    return True
            except httpx.HTTPError:
                pass
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.stop(signal.SIGKILL)
                if "address already in use" in self.log_path.read_text():
                    return False
                pytest.fail(f"server did not start: {self.log_path.read_text()[-2000:]}")
            time.sleep(0.3)

    def stop(self, sig=signal.SIGTERM) -> None:
        """Stop the server: SIGTERM (graceful) or SIGKILL (a crash, no clean-up); then
        SIGKILL whatever of its process group is left (its local Dask workers)."""
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


def _wait(url: str, job_id: int, until: set[str], timeout: float = 180.0) -> dict:
    """Poll ``GET /api/jobs/<id>`` until its status is in ``until`` (the timeout only guards a hang)."""
    deadline = time.monotonic() + timeout
    while True:
        job = httpx.get(f"{url}/api/jobs/{job_id}").json()
        if job["status"] in until:
            return job
        assert time.monotonic() < deadline, job
        time.sleep(0.3)


def listening_addresses(port: int) -> set[str]:
    """Local addresses (hex as in /proc/net/tcp[6], e.g. ``0100007F`` = 127.0.0.1) of the
    sockets listening on ``port`` on this machine (Linux)."""
    found = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            fields = line.split()
            addr, hex_port = fields[1].split(":")
            if int(hex_port, 16) == port and fields[3] == "0A":  # TCP_LISTEN
                found.add(addr)
    return found


def store_finished_jobs(data: Path, session: Path, name: str, jobs) -> None:
    """Store in ``data``'s SQLite database the session ``session`` (id 1, named ``name``) and
    finished jobs of it, as the runner stores a finished job, so a test serves files made
    by the core library without running Dask jobs.

    Args:
        jobs: ``(id, type, params model (its session_id is 1), result dict, folder)`` each.
    """
    from app.server import db as dbm

    engine = dbm.make_engine(f"sqlite:///{(data / 'workbench.db').resolve()}")
    try:
        factory = dbm.make_sessionmaker(engine)
        with factory.begin() as db:
            rec = dbm.SessionRecord(name=name, path=str(session.resolve()), source="registered")
            db.add(rec)
            db.flush()
            now = dbm.utcnow()
            for job_id, job_type, params, result, folder in jobs:
                db.add(dbm.JobRecord(id=job_id, type=job_type, params=params.model_dump(mode="json"), session_id=rec.id,
                                     status=dbm.DONE, progress=1.0, message="done", result=result,
                                     artifact_dir=str(Path(folder).resolve()), created_at=now, started_at=now,
                                     finished_at=now, log="made by the test from the core library\n"))
    finally:
        engine.dispose()
