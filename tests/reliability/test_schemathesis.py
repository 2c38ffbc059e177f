"""Schemathesis against the workbench's OpenAPI spec, on the live loopback server.

Every operation of ``/openapi.json`` gets property-based requests (schemathesis' examples,
coverage and fuzzing phases: valid and invalid bodies, boundary values, odd strings) and
every response is checked: never a 5xx, its status documented, its content type and body
as the spec says (``case.call_and_validate()``: schemathesis' default checks, except
"schema-valid data is accepted": the API answers 422, documented, to input the schema
cannot judge, such as a folder that is not a session).

Half of the schema-valid cases that address a session or a job get a real one (a private copy of the
tiny session and a finished replay job on it), so the routes behind the 404s run too.
Bounds: a job that a generated ``POST /api/jobs`` manages to create is cancelled at once
(no generated job runs for long), and ``DELETE /api/sessions/<id>`` never removes the
sessions other tests use.
"""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import httpx
import pytest
import schemathesis
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st
from schemathesis.specs.openapi.checks import positive_data_acceptance

FINAL = {"done", "failed", "cancelled", "interrupted"}


def _spec() -> dict:
    """The OpenAPI spec the live server serves, built from the same app factory (the app
    is not started: building the spec needs no database, cluster or viewer)."""
    from app.server.main import create_app
    from app.server.settings import Settings

    return create_app(Settings(viewer=False)).openapi()


# one test per operation (schemathesis' lazy fixture loader does not run on pytest 9)
schema = schemathesis.openapi.from_dict(_spec())


@pytest.fixture(scope="module")
def known(live, tiny_session, tmp_path_factory):
    """Ids of a private registered session (its copy may get picks written or cleared) and
    of a finished replay job on it; the ids that must not be deleted."""
    copy = Path(shutil.copytree(tiny_session, tmp_path_factory.mktemp("fuzz") / "tiny")).resolve()
    with httpx.Client(base_url=live.url, timeout=60) as c:
        sid = c.post("/api/sessions", json={"path": str(copy), "name": "fuzz"}).raise_for_status().json()["id"]
        job = c.post("/api/jobs", json={"type": "replay", "params": {"session_id": sid, "grid": [4, 3, 3]}}).raise_for_status().json()
        deadline = time.monotonic() + 120
        while (job := c.get(f"/api/jobs/{job['id']}").json())["status"] not in FINAL:
            assert time.monotonic() < deadline, job
            time.sleep(0.2)
        assert job["status"] == "done", job["error"]
        show = c.post("/api/viewer/show", json={"job_id": job["id"]})
        assert show.status_code == 200, show.text
    return {"session_id": sid, "job_id": job["id"], "protected": {sid, live.session_id}}


def test_the_live_server_serves_the_spec_tested_here(live):
    assert httpx.get(f"{live.url}/openapi.json").json() == _spec()


@schema.parametrize()
@schema.given(data=st.data())
@settings(max_examples=25, deadline=None, suppress_health_check=list(HealthCheck))
def test_api_honours_its_openapi_spec(case, data, live, known):
    positive = case.meta is None or case.meta.generation.mode.is_positive  # a negative case must stay invalid
    use_known = positive and data.draw(st.booleans(), label="use the real session and job")
    params = case.path_parameters or {}
    deleting_session = case.method == "DELETE" and case.path == "/api/sessions/{session_id}"
    if use_known and not deleting_session:
        for key in ("session_id", "job_id"):
            if key in params:
                params[key] = known[key]
        if case.path == "/api/jobs/{job_id}/artifacts/{path}":
            params["path"] = data.draw(st.sampled_from(["replay.json", "seq00.npz", "../replay.json", "x/../replay.json"]))
        if isinstance(case.body, dict):
            for key in ("session_id", "job_id"):
                if key in case.body:
                    case.body[key] = known[key]
    if deleting_session and params.get("session_id") in known["protected"]:
        params["session_id"] = 10**9  # another test's session: this one surely does not exist

    # every default check but "schema-valid data is accepted": this API answers 422 to input
    # the schema cannot judge (a folder that is not a session, bytes that are not a zip),
    # documented as such
    response = case.call_and_validate(base_url=live.url, excluded_checks=[positive_data_acceptance])

    if case.method == "POST" and case.path == "/api/jobs" and response.status_code == 201:
        job_id = response.json()["id"]  # a generated body that named a real type: stop it now
        with httpx.Client(base_url=live.url, timeout=60) as c:
            assert c.post(f"/api/jobs/{job_id}/cancel").status_code in (200, 409)
