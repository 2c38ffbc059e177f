"""Fixtures of the reliability suite: one tiny virtual-lab session for the whole run.

The session is real (rendered by ``core.lab``, so cleaning, ICP and replay work on it)
but as small as the lab allows: one 6 s test sequence at 5 Hz (30 frames of ~1k points at
160 x 120), a 10 x 5 x 5 truth mesh. It takes ~8 s to make and a replay of it ~1 s, so
fifty jobs fit the suite's budget. Tests copy it before changing anything.

:func:`live` is one real server for the modules that talk HTTP (concurrent jobs,
malformed sessions, schemathesis, security): starting one costs a Dask cluster and the
workers' first replay (imports, numba compilation), paid once.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

import httpx
import pytest

from tests.app._server import Server

TINY_PRESET = dict(
    sequence_durations=(6.0,),
    sequence_roles=("test",),
    camera_rate_hz=5.0,
    kinematics_rate_hz=50.0,
    grid=(10, 5, 5),
    dt=1.0 / 60.0,
    newton_iterations=1,
    reference_frames=1,
    workers=0,
)


@pytest.fixture(scope="session")
def tiny_session(tmp_path_factory) -> Path:
    """A valid one-sequence session (seed 1); read-only for tests (copy it to change it)."""
    from core.lab import Intrinsics, LabConfig, generate_session

    config = LabConfig(intrinsics=Intrinsics.from_fov(160, 120, 64.0), **TINY_PRESET)
    return generate_session(tmp_path_factory.mktemp("lab") / "tiny", preset=config, seed=1)


@pytest.fixture
def tiny_copy(tiny_session, tmp_path) -> Path:
    """A private copy of :func:`tiny_session`."""
    return Path(shutil.copytree(tiny_session, tmp_path / "tiny"))


@dataclass
class Live:
    """The suite's shared workbench: ``tissuetwin serve`` on loopback (local Dask cluster of
    two workers, viewer on), with the tiny session registered.

    Attributes:
        url: ``http://127.0.0.1:<port>``.
        data: its data directory (``workbench.db``, ``sessions/``, ``jobs/``).
        session_id, session: the registered copy of the tiny session (do not change it).
        roots: the only folders sessions may be registered from (``--session-root``).
        max_upload_bytes: its upload limit.
        server: the :class:`tests.app._server.Server`.
    """

    url: str
    data: Path
    session_id: int
    session: Path
    roots: list[Path]
    max_upload_bytes: int
    server: Server


@pytest.fixture(scope="package")  # stopped after the last reliability test, not at the end of the run
def live(tiny_session, tmp_path_factory) -> Live:
    base = tmp_path_factory.getbasetemp().resolve()  # every test's tmp_path is under it
    data = tmp_path_factory.mktemp("live") / "data"
    limit = 2_000_000
    server = Server(data, viewer=True, args=["--session-root", str(base)],
                    env={"TISSUETWIN_MAX_UPLOAD_BYTES": str(limit), "TISSUETWIN_PROGRESS_INTERVAL": "0.1"})
    try:
        session = Path(shutil.copytree(tiny_session, data.parent / "tiny-registered")).resolve()
        r = httpx.post(f"{server.url}/api/sessions", json={"path": str(session), "name": "tiny"})
        assert r.status_code == 201, r.text
        yield Live(server.url, data, r.json()["id"], session, [base], limit, server)
    finally:
        server.stop()
