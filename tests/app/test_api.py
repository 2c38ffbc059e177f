"""The workbench's REST API through FastAPI's TestClient, with jobs on a real local Dask cluster.

One app (and one 2-worker cluster) for the module; jobs use the `small` session and
short sweeps. Results are checked against core run in this process, against truth.json
(ICP), and against the files the job wrote.
"""

from __future__ import annotations

import csv
import io
import json
import os
import shutil
import socket
import sys
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
from pydantic import BaseModel

from app.server.jobs.registry import JobType
from app.server.jobs.types import default_registry
from app.server.main import create_app
from app.server.settings import Settings

FINAL = {"done", "failed", "cancelled", "interrupted"}


class CrashParams(BaseModel):
    """Parameters of the test-only job that kills its worker process."""

    code: int = 3


def crash_worker(params, ctx):
    """Simulates a worker dying mid-job (segfault, OOM kill): the process exits at once."""
    ctx.progress(0.1, "about to crash")
    os._exit(params.code)


class HoldParams(BaseModel):
    """Parameters of the test-only job that secedes and holds until a file exists."""

    flag: str


def hold_job(params, ctx):
    """A job that secedes from its worker thread (as a sweep does while its trials run),
    reports its worker's process id and holds until ``params.flag`` exists (120 s at most)."""
    from distributed import rejoin, secede

    secede()
    ctx.progress(0.1, f"pid {os.getpid()}")
    deadline = time.monotonic() + 120.0
    while not Path(params.flag).exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    rejoin()
    return {"pid": os.getpid()}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    import cloudpickle
    from fastapi.testclient import TestClient

    cloudpickle.register_pickle_by_value(sys.modules[__name__])  # workers cannot import tests/
    registry = default_registry()
    registry.add(JobType("crash", CrashParams, crash_worker, "test only: kills its worker"))
    registry.add(JobType("hold", HoldParams, hold_job, "test only: secedes and holds until a file exists"))
    data = tmp_path_factory.mktemp("workbench")
    settings = Settings(data_dir=data, viewer_port=_free_port(), progress_interval=0.1)
    with TestClient(create_app(settings, registry)) as c:
        yield c
    cloudpickle.unregister_pickle_by_value(sys.modules[__name__])


@pytest.fixture(scope="module")
def session_id(client, small_session):
    r = client.post("/api/sessions", json={"path": str(small_session)})
    assert r.status_code == 201, r.text
    return r.json()["id"]


def wait(client, job_id: int, until=FINAL, timeout: float = 120.0) -> dict:
    """Poll a job until its status is in ``until`` (the timeout only guards a hang)."""
    deadline = time.monotonic() + timeout
    while True:
        job = client.get(f"/api/jobs/{job_id}").json()
        if job["status"] in until:
            return job
        if time.monotonic() > deadline:
            pytest.fail(f"job {job_id} still {job['status']}: {job}")
        time.sleep(0.2)


def submit(client, type_: str, **params) -> dict:
    r = client.post("/api/jobs", json={"type": type_, "params": params})
    assert r.status_code == 201, r.text
    return r.json()


# ------------------------------------------------------------------ system, job types
def test_health_config_docs_and_job_types(client):
    assert client.get("/api/health").json() == {"status": "ok"}
    cfg = client.get("/api/config").json()
    assert cfg["viewer_port"] > 0 and cfg["scheduler"] == "local cluster"
    types = {t["name"]: t for t in client.get("/api/job-types").json()}
    assert {"generate", "replay", "sweep", "fit", "diagnose", "train", "evaluate"} <= set(types)
    assert types["train"]["needs_session"] and types["evaluate"]["needs_session"]
    assert {"model", "youngs_modulus", "widths", "epochs", "patience"} <= set(types["train"]["params_schema"]["properties"])
    assert {"identified", "stiff_factor", "models"} <= set(types["evaluate"]["params_schema"]["properties"])
    assert types["diagnose"]["needs_session"]
    bad = client.post("/api/jobs", json={"type": "diagnose", "params": {"session_id": 1, "grid": [13, 5]}})
    assert bad.status_code == 422
    assert types["sweep"]["needs_session"] and not types["generate"]["needs_session"]
    assert {"e_min", "e_max", "per_decade", "youngs", "refine"} <= set(types["sweep"]["params_schema"]["properties"])
    spec = client.get("/openapi.json").json()
    assert "/api/jobs/{job_id}/artifacts/{path}" in spec["paths"]
    assert client.get("/docs").status_code == 200
    page = client.get("/")
    assert page.status_code == 200 and "Tissue Twin workbench" in page.text


# ------------------------------------------------------------------ sessions
def test_register_session_and_its_errors(client, session_id, small_session, tmp_path):
    detail = client.get(f"/api/sessions/{session_id}").json()
    assert detail["path"] == str(Path(small_session).resolve())
    assert {s["name"] for s in detail["info"]["sequences"]} == {"seq00", "seq01", "seq02", "seq03"}
    assert detail["info"]["calibration"] is None
    assert any(s["id"] == session_id for s in client.get("/api/sessions").json())

    assert client.post("/api/sessions", json={"path": str(small_session)}).status_code == 409
    assert client.post("/api/sessions", json={"path": str(tmp_path / "nowhere")}).status_code == 422
    (tmp_path / "empty").mkdir()
    r = client.post("/api/sessions", json={"path": str(tmp_path / "empty")})
    assert r.status_code == 422 and "session.json" in r.json()["detail"]
    assert client.post("/api/sessions", json={}).status_code == 422
    assert client.get("/api/sessions/99999").status_code == 404


def _zip(files: dict[str, bytes]) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for name, data in files.items():
            zf.writestr(name, data)
    return buf.getvalue()


def test_upload_zip_registers_a_copy_and_refuses_zip_slip_and_size(client, small_session):
    root = Path(small_session)
    files = {f"s3/{p.relative_to(root).as_posix()}": p.read_bytes() for p in root.rglob("*") if p.is_file()}
    r = client.post("/api/sessions/upload", files={"file": ("s3.zip", _zip(files), "application/zip")}, data={"name": "up"})
    assert r.status_code == 201, r.text
    up = r.json()
    assert up["source"] == "uploaded" and Path(up["path"]).is_dir() and Path(up["path"]) != root.resolve()
    info = client.get(f"/api/sessions/{up['id']}").json()["info"]
    assert len(info["sequences"]) == 4

    sessions_dir = Path(client.app.state.settings.sessions_dir)
    before = sorted(p.name for p in sessions_dir.iterdir())
    evil = _zip({"session.json": b"{}", "../../escaped.txt": b"x"})
    r = client.post("/api/sessions/upload", files={"file": ("evil.zip", evil, "application/zip")})
    assert r.status_code == 422 and "unsafe path" in r.json()["detail"]
    assert not (sessions_dir.parent / "escaped.txt").exists()
    r = client.post("/api/sessions/upload", files={"file": ("junk.zip", b"not a zip", "application/zip")})
    assert r.status_code == 422
    r = client.post("/api/sessions/upload", files={"file": ("bad.zip", _zip({"x/session.json": b"{not json"}), "application/zip")})
    assert r.status_code == 422
    settings = client.app.state.settings
    limit = settings.max_upload_bytes
    settings.max_upload_bytes = 10_000
    try:
        r = client.post("/api/sessions/upload", files={"file": ("big.zip", _zip({"a": os.urandom(20_000)}), "application/zip")})
        assert r.status_code == 413
    finally:
        settings.max_upload_bytes = limit
    assert sorted(p.name for p in sessions_dir.iterdir()) == before  # nothing left behind

    assert client.delete(f"/api/sessions/{up['id']}").status_code == 204
    assert not Path(up["path"]).exists()
    assert client.get(f"/api/sessions/{up['id']}").status_code == 404


# ------------------------------------------------------------------ job validation
@pytest.mark.parametrize("body, status", [
    ({"type": "nope", "params": {}}, 404),
    ({"type": "sweep", "params": {}}, 422),                                       # session_id missing
    ({"type": "sweep", "params": {"session_id": 99999}}, 404),
    ({"type": "sweep", "params": {"session_id": 0, "e_min": 1e4, "e_max": 1e2}}, 422),
    ({"type": "sweep", "params": {"session_id": 0, "youngs": [-5]}}, 422),
    ({"type": "sweep", "params": {"session_id": 0, "per_decade": 10, "e_min": 1, "e_max": 1e9}}, 422),  # > 60 values
    ({"type": "replay", "params": {"session_id": 0, "grid": [13, 5]}}, 422),
    ({"type": "replay", "params": {"session_id": 0, "poisson_ratio": 0.5}}, 422),
    ({"type": "replay", "params": {"session_id": 0, "effects": [{"kind": "magic"}]}}, 422),
    ({"type": "replay", "params": {"session_id": 0, "typo": 1}}, 422),
    ({"type": "train", "params": {"session_id": 0, "model": "4d"}}, 422),
    ({"type": "train", "params": {"session_id": 0, "widths": [8, 16]}}, 422),
    ({"type": "train", "params": {"session_id": 0, "epochs": 0}}, 422),
    ({"type": "train", "params": {"session_id": 0, "learning_rate": -1e-3}}, 422),
    ({"type": "evaluate", "params": {"session_id": 0, "models": []}}, 422),
    ({"type": "evaluate", "params": {"session_id": 0, "models": ["2d", "5d"]}}, 422),
    ({"type": "evaluate", "params": {"session_id": 0, "stiff_factor": 0.5}}, 422),
    ({"type": "evaluate", "params": {"session_id": 0, "identified": 0}}, 422),
    ({"type": "generate", "params": {"name": "../evil"}}, 422),
    ({"type": "generate", "params": {"preset": "huge"}}, 422),
])
def test_job_parameters_are_validated(client, session_id, body, status):
    body = json.loads(json.dumps(body).replace('"session_id": 0', f'"session_id": {session_id}'))
    n_before = len(client.get("/api/jobs").json())
    r = client.post("/api/jobs", json=body)
    assert r.status_code == status, r.text
    assert len(client.get("/api/jobs").json()) == n_before  # nothing queued


def test_unknown_jobs_and_artifacts_are_404(client):
    assert client.get("/api/jobs/99999").status_code == 404
    assert client.post("/api/jobs/99999/cancel").status_code == 404
    assert client.get("/api/jobs/99999/artifacts").status_code == 404


# ------------------------------------------------------------------ lifecycle
def test_sweep_job_runs_on_dask_and_matches_core_in_process(client, session_id, small_session):
    from core.identification import sweep
    from core.preparation import prepare_session
    from core.simulation.replay import ReplayConfig
    job = submit(client, "sweep", session_id=session_id, youngs=[1e3, 1e5], sequences=["seq02"])
    assert job["status"] in ("queued", "running")
    done = wait(client, job["id"])
    assert done["status"] == "done", done["error"]
    assert done["progress"] == 1.0 and done["started_at"] and done["finished_at"]
    assert "started" in done["log"] and "trials" in done["log"]
    table = {row["youngs_modulus"]: row["mean_error"] for row in done["result"]["table"]}

    expected = sweep(prepare_session(small_session, ReplayConfig()), [1e3, 1e5], sequences=["seq02"]).table()
    assert set(table) == set(expected)
    for E in expected:  # same trials; the cleaning ran single-threaded on the worker (open3d's
        assert table[E] == pytest.approx(expected[E], rel=1e-4)  # reductions differ ~1e-8 m)

    arts = {a["path"] for a in client.get(f"/api/jobs/{job['id']}/artifacts").json()}
    assert {"sweep.csv", "sweep.png"} <= arts
    text = client.get(f"/api/jobs/{job['id']}/artifacts/sweep.csv").text
    rows = list(csv.DictReader(io.StringIO(text)))
    assert {float(r["youngs_modulus"]) for r in rows} == set(expected)
    png = client.get(f"/api/jobs/{job['id']}/artifacts/sweep.png")
    assert png.status_code == 200 and png.content[:4] == b"\x89PNG"
    for bad in ("../../workbench.db", "%2e%2e/%2e%2e/workbench.db", "..%2F..%2Fworkbench.db", "/etc/passwd", "nope.csv"):
        r = client.get(f"/api/jobs/{job['id']}/artifacts/{bad}")  # the client may normalise '..' away first
        assert r.status_code in (404, 422) and b"SQLite" not in r.content, bad
    from app.server.errors import NotFound
    from app.server.services.jobs import artifact_path

    record = client.app.state.sessionmaker()
    with record as db:
        from app.server.db import JobRecord

        rec = db.get(JobRecord, job["id"])
        assert artifact_path(rec, "sweep.csv").name == "sweep.csv"
        for bad in ("../../workbench.db", "/etc/passwd", "..", "sub/../../1/../../workbench.db"):
            with pytest.raises(NotFound):
                artifact_path(rec, bad)
    assert client.post(f"/api/jobs/{job['id']}/cancel").status_code == 409  # final already
    listed = client.get("/api/jobs", params={"type": "sweep", "status": "done"}).json()
    assert any(j["id"] == job["id"] for j in listed)


def test_failed_job_keeps_reason_and_traceback(client, session_id):
    job = submit(client, "replay", session_id=session_id, sequences=["no-such-sequence"])
    done = wait(client, job["id"])
    assert done["status"] == "failed"
    assert "no-such-sequence" in done["error"] and "SessionFormatError" in done["error"]
    assert "prepare_session" in done["traceback"]


def test_train_job_without_a_test_sequence_fails_with_the_reason(client, session_id):
    job = submit(client, "train", session_id=session_id, sequences=["seq02"], widths=[4, 8, 8], epochs=1)
    done = wait(client, job["id"])
    assert done["status"] == "failed"
    assert "LearningError" in done["error"] and "missing role(s) ['test', 'validation']" in done["error"]


def test_train_job_writes_losses_checkpoint_and_trajectories(client, session_id):
    """A tiny network (widths 4 8 8, 2 epochs) on one sequence per role: the job's summary,
    its train.json and the checkpoint agree, and the corrected trajectories have the npz
    keys core.learning documents."""
    job = submit(client, "train", session_id=session_id, sequences=["seq00", "seq01", "seq02"], widths=[4, 8, 8],
                 epochs=2, max_points=128, batch_size=8)
    done = wait(client, job["id"], timeout=300)
    assert done["status"] == "done", done["error"]
    r = done["result"]
    assert [e["epoch"] for e in r["losses"]] == [1, 2]
    assert all(e["train_loss"] > 0 and e["validation_loss"] > 0 for e in r["losses"])
    on_disk = json.loads(client.get(f"/api/jobs/{job['id']}/artifacts/train.json").text)
    assert on_disk["losses"] == r["losses"] and on_disk["test_error"] == r["test_error"]
    assert set(r["sequences"]) == {"seq01"}  # the test sequence
    arts = {a["path"] for a in client.get(f"/api/jobs/{job['id']}/artifacts").json()}
    assert {"train.json", "checkpoint.pt", "trajectories/seq01_in_loop.npz", "trajectories/seq01_offline.npz"} <= arts
    npz = np.load(io.BytesIO(client.get(f"/api/jobs/{job['id']}/artifacts/trajectories/seq01_offline.npz").content))
    F, N = npz["positions"].shape[:2]
    assert N == 13 * 5 * 5 and npz["corrections"].shape == (F, 13 * 5, 3) and npz["frame_errors"].shape == (F,)

    # the viewer's corrected-mesh layer: the trajectory the job chose, beside a plain replay of the test sequence
    mode = r["corrected_shown"]["seq01"]
    assert mode in ("in_loop", "offline")
    shown = np.load(io.BytesIO(client.get(f"/api/jobs/{job['id']}/artifacts/viewer_run/corrected/seq01.npz").content))
    chosen = np.load(io.BytesIO(client.get(f"/api/jobs/{job['id']}/artifacts/trajectories/seq01_{mode}.npz").content))
    np.testing.assert_array_equal(shown["positions"], chosen["positions"])
    state = client.post("/api/viewer/show", json={"job_id": job["id"]}).json()
    assert state["sequence"] == "seq01" and state["n_frames"] == F
    assert state["layers"] == ["cloud", "fem", "corrected", "probe"]


def test_cancel_a_running_sweep(client, session_id):
    job = submit(client, "sweep", session_id=session_id, e_min=1e1, e_max=1e6, per_decade=4)  # 21 E x 2 sequences
    wait(client, job["id"], until={"running"} | FINAL)
    deadline = time.monotonic() + 60
    while client.get(f"/api/jobs/{job['id']}").json()["progress"] < 0.1 and time.monotonic() < deadline:
        time.sleep(0.2)  # until the trials run
    r = client.post(f"/api/jobs/{job['id']}/cancel")
    assert r.status_code == 200 and r.json()["cancel_requested"]
    done = wait(client, job["id"])
    assert done["status"] == "cancelled", done
    assert done["progress"] < 1.0 and done["result"] is None
    assert client.post(f"/api/jobs/{job['id']}/cancel").status_code == 409


def test_a_worker_crash_fails_only_its_job(client, session_id):
    crash = submit(client, "crash")
    other = submit(client, "sweep", session_id=session_id, youngs=[1e4], sequences=["seq03"])
    crashed = wait(client, crash["id"])
    assert crashed["status"] == "failed" and "worker crashed" in crashed["error"], crashed
    other = wait(client, other["id"])
    assert other["status"] == "done", other
    after = wait(client, submit(client, "sweep", session_id=session_id, youngs=[1e4], sequences=["seq03"])["id"])
    assert after["status"] == "done", after  # the cluster still works


def test_seceded_jobs_do_not_share_a_worker(client, tmp_path):
    """Three jobs that secede (as sweeps do) on the 2-worker cluster: two run, in two
    different worker processes, and the third waits queued until one ends. Before the
    job slot a seceded job freed its worker's thread and the third started beside it, so
    a crash of either would have failed both."""
    flag = tmp_path / "release"
    jobs = [submit(client, "hold", flag=str(flag))["id"] for _ in range(3)]
    deadline = time.monotonic() + 60.0
    while True:
        rows = [client.get(f"/api/jobs/{j}").json() for j in jobs]
        holding = [r for r in rows if r["message"].startswith("pid ")]
        if len(holding) >= 2 or time.monotonic() > deadline:
            break
        time.sleep(0.2)
    assert len(holding) == 2, rows
    time.sleep(2.0)  # time enough for a third to start, were it allowed
    rows = [client.get(f"/api/jobs/{j}").json() for j in jobs]
    holding = [r for r in rows if r["message"].startswith("pid ")]
    assert len(holding) == 2, rows
    assert len({r["message"] for r in holding}) == 2, rows  # two worker processes
    assert [r["status"] for r in rows if not r["message"].startswith("pid ")] == ["queued"], rows
    flag.write_text("go")
    done = [wait(client, j) for j in jobs]
    assert [d["status"] for d in done] == ["done"] * 3, done


# ------------------------------------------------------------------ replay + viewer
def test_replay_job_and_viewer_routes(client, session_id):
    job = submit(client, "replay", session_id=session_id, sequences=["seq01"])
    done = wait(client, job["id"])
    assert done["status"] == "done", done["error"]
    seq = done["result"]["sequences"]["seq01"]
    replay_json = json.loads(client.get(f"/api/jobs/{job['id']}/artifacts/replay.json").text)
    assert replay_json["sequences"]["seq01"]["mean_error"] == pytest.approx(seq["mean_error"])
    assert 0.3e-3 < seq["mean_error"] < 5e-3

    state = client.post("/api/viewer/show", json={"job_id": job["id"]}).json()
    assert state["sequence"] == "seq01" and state["frame"] == 0 and state["n_frames"] == seq["frames"]
    assert state["layers"] == ["cloud", "fem", "probe"]  # a plain replay has no corrected mesh
    t0 = state["time"]
    state = client.post("/api/viewer/frame", json={"frame": 20}).json()
    assert state["frame"] == 20 and state["time"] > t0
    assert client.post("/api/viewer/frame", json={"frame": 10**6}).json()["frame"] == seq["frames"] - 1
    assert client.post("/api/viewer/frame", json={"frame": -1}).status_code == 422
    sweep_job = client.get("/api/jobs", params={"type": "sweep", "status": "done"}).json()[0]
    assert client.post("/api/viewer/show", json={"job_id": sweep_job["id"]}).status_code == 422
    assert client.post("/api/viewer/show", json={"job_id": 99999}).status_code == 404
    assert client.post("/api/viewer/icp", json={"session_id": 99999}).status_code == 404


# ------------------------------------------------------------------ ICP initialisation by picked points
def _top_corner_picks(session: Path, inset: float = 0.008):
    meta = json.loads((session / "session.json").read_text())
    sx, sy, sz = meta["phantom"]["size"]
    pp = np.array([[inset, inset, sz], [sx - inset, inset, sz], [sx - inset, sy - inset, sz], [inset, sy - inset, sz]])
    T = np.array(json.loads((session / "truth.json").read_text())["T_phantom_camera"])
    T_cp = np.linalg.inv(T)
    return pp @ T_cp[:3, :3].T + T_cp[:3, 3], pp, T


def test_icp_preview_accept_and_clear(client, small_session, tmp_path):
    copy = tmp_path / "s3copy"
    shutil.copytree(small_session, copy)
    sid = client.post("/api/sessions", json={"path": str(copy)}).json()["id"]
    pc, pp, T_true = _top_corner_picks(copy)
    body = {"points_camera": pc.tolist(), "points_phantom": pp.tolist()}

    assert client.post(f"/api/sessions/{sid}/calibration/icp", json={**body, "points_phantom": pp[:2].tolist()}).status_code == 422
    far = pp.copy()
    far[0] += [0.03, 0, 0]  # not a rigid match: RegistrationError -> 422
    r = client.post(f"/api/sessions/{sid}/calibration/icp", json={**body, "points_phantom": far.tolist()})
    assert r.status_code == 422 and "rigidly" in r.json()["detail"]

    res = client.post(f"/api/sessions/{sid}/calibration/icp", json=body).json()
    T = np.array(res["T_phantom_camera"])
    angle = np.degrees(np.arccos(np.clip((np.trace(T[:3, :3].T @ T_true[:3, :3]) - 1) / 2, -1, 1)))
    assert angle < 1.0 and np.linalg.norm(T[:3, 3] - T_true[:3, 3]) < 0.003  # truth.json, independent
    assert res["rms"] < 0.002 and res["fitness"] > 0.6
    assert client.get(f"/api/sessions/{sid}/calibration").json() == {"picked": None}  # preview saves nothing

    stored = client.put(f"/api/sessions/{sid}/calibration", json=body).json()["picked"]
    on_disk = json.loads((copy / "calibration" / "picked.json").read_text())
    assert on_disk == stored and np.allclose(on_disk["points_camera"], pc)
    assert client.get(f"/api/sessions/{sid}").json()["info"]["calibration"]["rms"] == pytest.approx(res["rms"])
    assert client.delete(f"/api/sessions/{sid}/calibration").json() == {"removed": True}
    assert not (copy / "calibration" / "picked.json").exists()
