"""``GET /api/jobs/{id}/export?format=vtu|sofa|mjcf``: the calibrated twin of a finished
replay or diagnose job, zipped (issue 19, item 5), through FastAPI's TestClient.

A real replay job runs on the `small` session (one sequence) on a local Dask cluster. A
diagnose job takes minutes, so its finished row and folder (a ``diagnosis.json`` naming
the session, E and the claimed effect) are written here, as the runner would store them;
so are the rows of the jobs the export refuses (a sweep, a running or failed replay).
"""

from __future__ import annotations

import hashlib
import io
import json
import time
import zipfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from app.server import db as dbm
from app.server.main import create_app
from app.server.settings import Settings
from tests.app._server import FINAL, _free_port

GRAVITY = {"kind": "gravity", "g": [0.0, 0.0, -9.81]}


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    from fastapi.testclient import TestClient

    data = tmp_path_factory.mktemp("workbench")
    settings = Settings(data_dir=data, viewer=False, viewer_port=_free_port(), workers=1, progress_interval=0.1)
    with TestClient(create_app(settings)) as c:
        yield c


@pytest.fixture(scope="module")
def session_id(client, small_session):
    r = client.post("/api/sessions", json={"path": str(small_session)})
    assert r.status_code == 201, r.text
    return r.json()["id"]


def _wait(client, job_id: int, timeout: float = 180.0) -> dict:
    """Poll a job until it is final (the timeout only guards a hang)."""
    deadline = time.monotonic() + timeout
    while True:
        job = client.get(f"/api/jobs/{job_id}").json()
        if job["status"] in FINAL:
            return job
        if time.monotonic() > deadline:
            pytest.fail(f"job {job_id} still {job['status']}: {job}")
        time.sleep(0.2)


@pytest.fixture(scope="module")
def replay_job(client, session_id) -> dict:
    r = client.post("/api/jobs", json={"type": "replay", "params": {"session_id": session_id, "sequences": ["seq01"]}})
    assert r.status_code == 201, r.text
    job = _wait(client, r.json()["id"])
    assert job["status"] == "done", job["error"]
    return client.get(f"/api/jobs/{job['id']}").json()


def _folder(client, job_id: int) -> Path:
    with client.app.state.sessionmaker() as db:
        return Path(db.get(dbm.JobRecord, job_id).artifact_dir)


def _add_job(client, type_: str, status: str, session_id: int | None, diagnosis: dict | None = None,
             params: dict | None = None) -> int:
    """A job row as the runner stores it (``status``), with its folder under the data
    directory; ``diagnosis``: the ``diagnosis.json`` written into that folder."""
    settings = client.app.state.settings
    with client.app.state.sessionmaker.begin() as db:
        now = dbm.utcnow()
        job = dbm.JobRecord(type=type_, params=params or {"session_id": session_id}, session_id=session_id, status=status,
                            progress=1.0 if status == dbm.DONE else 0.5, message=status, result={"made_by": "test"},
                            created_at=now, started_at=now, finished_at=now if status in dbm.FINAL else None, log="")
        db.add(job)
        db.flush()
        folder = (settings.jobs_dir / str(job.id)).resolve()
        folder.mkdir(parents=True)
        job.artifact_dir = str(folder)
        if diagnosis is not None:
            (folder / "diagnosis.json").write_text(json.dumps(diagnosis))
        return job.id


def _diagnosis(session: Path, youngs: float | None = 6000.0) -> dict:
    """The fields of a ``tissue-diagnosis/1`` file the export reads."""
    ym = {"value": youngs} if youngs is not None else {"value": None, "reason": "not identifiable"}
    return {"format": "tissue-diagnosis/1", "session": str(session), "youngs_modulus": ym,
            "causes": [{"kind": "gravity", "parameters": {"g": GRAVITY["g"]}}],
            "extended": {"kinds": ["gravity"], "effects": [GRAVITY]}}


def _snapshot(folder: Path) -> dict[str, str]:
    """{relative path: sha256} of the files in a job's folder outside ``export/``."""
    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file() and p.relative_to(folder).parts[0] != "export"}


def _zip_names(r, job_id: int, fmt: str) -> set[str]:
    """The files of the export's zip (relative to its one top folder), after checking the response."""
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "application/zip"
    assert f'filename="job-{job_id}-{fmt}.zip"' in r.headers["content-disposition"]
    with zipfile.ZipFile(io.BytesIO(r.content)) as zf:
        assert zf.testzip() is None
        names = zf.namelist()
    top = f"job-{job_id}-{fmt}/"
    assert all(n.startswith(top) for n in names), names
    return {n.removeprefix(top) for n in names}


def test_formats_match_the_export_package():
    from app.export import FORMATS
    from app.server.services.export import EXPORT_FORMATS

    assert EXPORT_FORMATS == FORMATS


def test_export_a_replay_job_in_each_format(client, replay_job):
    job_id = replay_job["id"]
    folder = _folder(client, job_id)
    before = _snapshot(folder)
    frames = replay_job["result"]["sequences"]["seq01"]["frames"]

    vtu = _zip_names(client.get(f"/api/jobs/{job_id}/export", params={"format": "vtu"}), job_id, "vtu")
    assert {"rest.vtu", "seq01.pvd", "twin.json"} <= vtu
    assert len([n for n in vtu if n.startswith("seq01/frame_") and n.endswith(".vtu")]) == frames
    sofa = _zip_names(client.get(f"/api/jobs/{job_id}/export?format=sofa"), job_id, "sofa")
    assert sofa == {"scene.py", "probe_path.csv", "twin.json"}
    r = client.get(f"/api/jobs/{job_id}/export?format=mjcf")
    assert _zip_names(r, job_id, "mjcf") == {"twin.xml", "probe_path.csv", "twin.json"}

    with zipfile.ZipFile(io.BytesIO(r.content)) as zf:
        twin = json.loads(zf.read(f"job-{job_id}-mjcf/twin.json"))
    replay = json.loads((folder / "replay.json").read_text())
    assert twin["kind"] == "replay" and twin["export"]["format"] == "mjcf"
    assert twin["youngs_modulus_pa"] == pytest.approx(replay["youngs_modulus"])
    assert sorted(twin["export"]["files"]) == ["probe_path.csv", "twin.xml"]

    # written into the job's own folder, export/<format>/ and the zips beside them; nothing else changed
    assert _snapshot(folder) == before
    assert sorted(p.name for p in (folder / "export").iterdir()) == sorted(
        ["mjcf", "sofa", "vtu"] + [f"job-{job_id}-{f}.zip" for f in ("mjcf", "sofa", "vtu")])
    assert (folder / "export" / "sofa" / "scene.py").is_file()
    # the artifact listing shows them like any other file of the job
    assert f"export/job-{job_id}-sofa.zip" in {a["path"] for a in client.get(f"/api/jobs/{job_id}/artifacts").json()}


def test_a_second_request_reuses_the_export(client, replay_job):
    job_id = replay_job["id"]
    first = client.get(f"/api/jobs/{job_id}/export?format=sofa")
    zip_path = _folder(client, job_id) / "export" / f"job-{job_id}-sofa.zip"
    stamp = zip_path.stat().st_mtime_ns
    second = client.get(f"/api/jobs/{job_id}/export?format=sofa")
    assert second.status_code == 200 and second.content == first.content
    assert zip_path.stat().st_mtime_ns == stamp


def test_export_a_diagnose_job(client, session_id, small_session):
    job_id = _add_job(client, "diagnose", dbm.DONE, session_id, _diagnosis(small_session),
                      params={"session_id": session_id, "grid": [9, 4, 4]})
    folder = _folder(client, job_id)
    with ThreadPoolExecutor(2) as ex:  # two clicks at once: one export, both get it
        responses = list(ex.map(lambda _: client.get(f"/api/jobs/{job_id}/export?format=mjcf"), range(2)))
    assert responses[0].content == responses[1].content
    assert _zip_names(responses[0], job_id, "mjcf") == {"twin.xml", "probe_path.csv", "twin.json"}
    assert _zip_names(client.get(f"/api/jobs/{job_id}/export?format=sofa"), job_id, "sofa") == {
        "scene.py", "probe_path.csv", "twin.json"}
    assert {"rest.vtu", "twin.json"} <= _zip_names(client.get(f"/api/jobs/{job_id}/export?format=vtu"), job_id, "vtu")
    twin = json.loads((folder / "export" / "sofa" / "twin.json").read_text())
    assert twin["kind"] == "diagnosis" and twin["youngs_modulus_pa"] == pytest.approx(6000.0)
    assert [e["kind"] for e in twin["effects"]] == ["gravity"]
    assert twin["grid"] == [9, 4, 4]  # the job's grid, not the export's default
    assert sorted(p.name for p in folder.iterdir()) == ["diagnosis.json", "export"]
    assert not [p for p in (folder / "export").iterdir() if p.name.startswith(".")]  # no temporaries left


def test_export_errors(client, session_id, replay_job, small_session):
    job_id = replay_job["id"]
    r = client.get("/api/jobs/99999/export?format=vtu")
    assert r.status_code == 404 and "no job" in r.json()["detail"]
    assert client.get(f"/api/jobs/{2**70}/export?format=vtu").status_code == 404

    for query in ("?format=stl", "?format=VTU", ""):
        r = client.get(f"/api/jobs/{job_id}/export{query}")
        assert r.status_code == 422, (query, r.text)
        assert isinstance(r.json()["detail"], list)

    sweep = _add_job(client, "sweep", dbm.DONE, session_id)
    r = client.get(f"/api/jobs/{sweep}/export?format=sofa")
    assert r.status_code == 409 and "sweep job" in r.json()["detail"]
    for type_ in ("fit", "train", "generate"):
        assert client.get(f"/api/jobs/{_add_job(client, type_, dbm.DONE, session_id)}/export?format=vtu").status_code == 409
    for status in (dbm.RUNNING, dbm.QUEUED, dbm.FAILED, dbm.CANCELLED):
        other = _add_job(client, "replay", status, session_id)
        r = client.get(f"/api/jobs/{other}/export?format=mjcf")
        assert r.status_code == 409 and f"is {status}" in r.json()["detail"], r.text
        assert not (_folder(client, other) / "export").exists()

    # the run cannot be exported: 422 with the export's own message; nothing is left behind
    no_e = _add_job(client, "diagnose", dbm.DONE, session_id, _diagnosis(small_session, youngs=None))
    r = client.get(f"/api/jobs/{no_e}/export?format=sofa")
    assert r.status_code == 422 and "Young's modulus" in r.json()["detail"], r.text
    assert sorted(p.name for p in _folder(client, no_e).iterdir()) == ["diagnosis.json"]
    missing = _add_job(client, "diagnose", dbm.DONE, None, _diagnosis(small_session.parent / "gone"))
    r = client.get(f"/api/jobs/{missing}/export?format=vtu")
    assert r.status_code == 422 and "session" in r.json()["detail"], r.text
    empty = _add_job(client, "replay", dbm.DONE, session_id)  # a folder without replay.json
    r = client.get(f"/api/jobs/{empty}/export?format=vtu")
    assert r.status_code == 422 and "replay.json" in r.json()["detail"], r.text

    # the service is still up, and a good export still works
    assert client.get("/api/health").json() == {"status": "ok"}
    assert client.get(f"/api/jobs/{job_id}/export?format=sofa").status_code == 200


def test_export_is_in_the_openapi_spec(client):
    spec = client.get("/openapi.json").json()
    op = spec["paths"]["/api/jobs/{job_id}/export"]["get"]
    fmt = next(p for p in op["parameters"] if p["name"] == "format")
    assert fmt["in"] == "query" and fmt["required"] and fmt["schema"]["enum"] == ["vtu", "sofa", "mjcf"]
    assert {"200", "404", "409", "422"} <= set(op["responses"])
