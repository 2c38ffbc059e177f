"""Crashes: a Dask worker killed under a running job, then the server process killed.

The workbench runs on an existing Dask cluster (``serve --scheduler``, the scale-out set-up
of docker-compose.yml): the test owns the cluster, so it can tell which worker process runs
a job and SIGKILL exactly that one. Then it SIGKILLs the server while another job runs and
starts a new server on the same data directory and cluster.

Expected (issue 6 and 7): the killed worker's job fails with the reason, a job running
elsewhere completes, the cluster keeps working; after the server crash, finished jobs keep
their results and artifacts byte for byte, the failed one its reason, the job that was
running says ``interrupted`` and its task, left on the cluster, is stopped by the new
server, and new jobs run.

tests/app/test_api.py covers a job that kills its own worker (``os._exit``) on the local
cluster, tests/app/test_server.py a server SIGKILL with a local cluster; this is the
external kill of a busy worker and the crash of a server on a shared cluster.
"""

from __future__ import annotations

import logging
import os
import signal
import sys
import threading
import time

import httpx
import pytest

from tests.app._server import FINAL, Server

LONG = {"grid": [48, 24, 24]}
"""Replay parameters that keep a worker busy for minutes: the jobs that get killed."""
SHORT = {"grid": [4, 3, 3]}


def _warm() -> None:
    """On a worker: import what a replay job needs (what its first job would pay for)."""
    import app.server.jobs.types  # noqa: F401
    import app.viewer.data  # noqa: F401
    import core.simulation.replay  # noqa: F401


def _busy(dask_worker) -> tuple[int, list[str]]:
    """On a worker: its process id and the keys of the tasks it is running."""
    keys = [ts.key for ts in dask_worker.state.executing] + [ts.key for ts in dask_worker.state.long_running]
    return os.getpid(), [str(k) for k in keys]


@pytest.fixture(scope="module")
def cluster():
    """A local cluster of two worker processes (one thread each), as a lab would start
    ``dask scheduler`` and ``dask worker`` by hand."""
    import cloudpickle
    import dask
    from distributed import Client, LocalCluster

    cloudpickle.register_pickle_by_value(sys.modules[__name__])  # workers cannot import tests/
    with dask.config.set({"distributed.worker.daemon": False}):
        lc = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                          silence_logs=logging.ERROR, env={"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"})
    client = Client(lc)
    try:
        yield lc, client
    finally:
        client.close()
        lc.close(timeout=20)
        cloudpickle.unregister_pickle_by_value(sys.modules[__name__])


def _worker_running(client, job_id: int, timeout: float = 60.0) -> tuple[str, int]:
    """(address, pid) of the worker running job ``job_id``'s task (key ``tt-<id>-...-job``)."""
    deadline = time.monotonic() + timeout
    while True:
        for addr, (pid, keys) in client.run(_busy).items():
            if any(k.startswith(f"tt-{job_id}-") and k.endswith("-job") for k in keys):
                return addr, pid
        assert time.monotonic() < deadline, f"job {job_id} is not running on any worker"
        time.sleep(0.2)


def _wait(c: httpx.Client, job_id: int, until=FINAL, timeout: float = 120.0) -> dict:
    deadline = time.monotonic() + timeout  # guards a hang only
    while (job := c.get(f"/api/jobs/{job_id}").json())["status"] not in until:
        assert time.monotonic() < deadline, job
        time.sleep(0.2)
    return job


def _submit(c: httpx.Client, session_id: int, params: dict) -> dict:
    r = c.post("/api/jobs", json={"type": "replay", "params": {"session_id": session_id, **params}})
    assert r.status_code == 201, r.text
    return r.json()


def test_killed_worker_then_killed_server(cluster, tiny_session, tmp_path):
    lc, dask_client = cluster
    data = tmp_path / "data"
    warming = threading.Thread(target=dask_client.run, args=(_warm,))  # the workers import while the server starts
    warming.start()
    server = Server(data, args=["--scheduler", lc.scheduler_address])
    warming.join()
    try:
        c = httpx.Client(base_url=server.url, timeout=60)
        sid = c.post("/api/sessions", json={"path": str(tiny_session)}).raise_for_status().json()["id"]

        # 1. SIGKILL the worker under a running job: that job fails with the reason
        doomed = _submit(c, sid, LONG)
        _wait(c, doomed["id"], {"running"})
        addr, pid = _worker_running(dask_client, doomed["id"])
        other = _submit(c, sid, SHORT)  # queued or running on the other worker meanwhile
        os.kill(pid, signal.SIGKILL)
        failed = _wait(c, doomed["id"])
        assert failed["status"] == "failed" and failed["error"].startswith("worker crashed: "), failed
        assert "the worker running this job died" in failed["error"]
        finished = _wait(c, other["id"])
        assert finished["status"] == "done", finished
        replay_json = c.get(f"/api/jobs/{finished['id']}/artifacts/replay.json").content
        assert b'"seq00"' in replay_json

        # 2. SIGKILL the server while a job runs
        running = _submit(c, sid, LONG)
        _wait(c, running["id"], {"running"})
        c.close()
    finally:
        server.stop(signal.SIGKILL)

    server = Server(data, args=["--scheduler", lc.scheduler_address])
    try:
        with httpx.Client(base_url=server.url, timeout=60) as c:
            again = c.get(f"/api/jobs/{finished['id']}").json()
            assert again["status"] == "done" and again["result"] == finished["result"] and again["log"] == finished["log"]
            assert c.get(f"/api/jobs/{finished['id']}/artifacts/replay.json").content == replay_json
            assert c.get(f"/api/jobs/{doomed['id']}").json()["error"] == failed["error"]
            lost = c.get(f"/api/jobs/{running['id']}").json()
            assert lost["status"] == "interrupted" and "server stopped" in lost["error"], lost
            # its task outlived the killed server on the shared cluster: the new server
            # cancelled it (the token is in the job's row), so it stops at its next report
            deadline = time.monotonic() + 60
            while any(k.startswith(f"tt-{running['id']}-") for _pid, keys in dask_client.run(_busy).values() for k in keys):
                assert time.monotonic() < deadline, "the killed server's job still runs on the cluster"
                time.sleep(0.2)
            assert c.post(f"/api/jobs/{running['id']}/cancel").status_code == 409  # final
            fresh = _wait(c, _submit(c, sid, SHORT)["id"])
            assert fresh["status"] == "done", fresh  # the cluster, with the killed worker restarted, still works
    finally:
        server.stop()
