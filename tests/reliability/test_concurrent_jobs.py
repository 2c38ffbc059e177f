"""Fifty job submissions at once over HTTP to a real server on loopback: every one is
stored (one row each, distinct ids, its own parameters), every one reaches a final state,
none is lost or mixed up with another.

The jobs are real replays of the tiny session on a coarse 4 x 3 x 3 grid (under a second
each on a warm, idle worker), each at its own Young's modulus so a result can be traced
to its request. Two of every three are cancelled at once right after submission (33
concurrent requests racing the workers): those end ``cancelled`` (or ``done`` if they
finished first), the others ``done``.
"""

from __future__ import annotations

import sqlite3
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import httpx

N = 50
FINAL = {"done", "failed", "cancelled", "interrupted"}


def _all_at_once(n: int, call) -> list:
    """Run ``call(i)`` for i < n in n threads released together by a barrier."""
    barrier = threading.Barrier(n)

    def run(i):
        barrier.wait()
        return call(i)

    with ThreadPoolExecutor(max_workers=n) as pool:
        return list(pool.map(run, range(n)))


def test_fifty_concurrent_submissions_are_all_stored_and_all_finish(live):
    youngs = [1000.0 + 10.0 * i for i in range(N)]
    before = {j["id"] for j in httpx.get(f"{live.url}/api/jobs", params={"limit": 1000}).json()}

    def submit(i):
        with httpx.Client(base_url=live.url, timeout=120) as c:
            return c.post("/api/jobs", json={"type": "replay", "params": {
                "session_id": live.session_id, "youngs_modulus": youngs[i], "grid": [4, 3, 3]}})

    t0 = time.monotonic()
    responses = _all_at_once(N, submit)
    assert [r.status_code for r in responses] == [201] * N, [r.text for r in responses if r.status_code != 201][:3]
    jobs = [r.json() for r in responses]
    ids = [j["id"] for j in jobs]
    assert len(set(ids)) == N and not set(ids) & before
    assert [j["params"]["youngs_modulus"] for j in jobs] == youngs  # each row holds its own request
    assert all(j["status"] in ("queued", "running") for j in jobs)

    to_cancel = [j for k, j in enumerate(ids) if k % 3]

    def cancel(i):
        with httpx.Client(base_url=live.url, timeout=120) as c:
            return c.post(f"/api/jobs/{to_cancel[i]}/cancel")

    cancels = _all_at_once(len(to_cancel), cancel)
    assert all(r.status_code in (200, 409) for r in cancels), [r.text for r in cancels if r.status_code not in (200, 409)]

    deadline = time.monotonic() + 100  # guards a hang only; measured below
    pending = set(ids)
    final: dict[int, dict] = {}
    with httpx.Client(base_url=live.url, timeout=60) as c:
        while pending:
            listed = {j["id"]: j for j in c.get("/api/jobs", params={"type": "replay", "limit": 1000}).json()}
            for i in list(pending):
                if listed[i]["status"] in FINAL:
                    final[i] = c.get(f"/api/jobs/{i}").json()
                    pending.discard(i)
            assert time.monotonic() < deadline, {i: listed[i]["status"] for i in pending}
            time.sleep(0.3)
    elapsed = time.monotonic() - t0

    statuses = {i: final[i]["status"] for i in ids}
    cancelled_ok = {to_cancel[i] for i, r in enumerate(cancels) if r.status_code == 200}
    for i in ids:
        job = final[i]
        if i in cancelled_ok:
            # a cancel can lose the race to the finish
            assert job["status"] in ("cancelled", "done"), (job["status"], job["error"], job["log"])
        else:
            assert job["status"] == "done", (job["status"], job["error"], job["log"])
        if job["status"] == "done":
            seq = job["result"]["sequences"]["seq00"]
            assert seq["status"] == "ok" and 0 < seq["mean_error"] < 0.01, job["result"]
            arts = {a["path"] for a in httpx.get(f"{live.url}/api/jobs/{i}/artifacts").json()}
            assert "replay.json" in arts
        else:
            assert job["result"] is None and job["error"]
        assert job["params"]["youngs_modulus"] == youngs[ids.index(i)]

    # the database holds exactly one row per request, each final
    db = sqlite3.connect(f"file:{live.data / 'workbench.db'}?mode=ro", uri=True)
    try:
        rows = dict(db.execute(f"select id, status from jobs where id in ({','.join('?' * N)})", ids).fetchall())
    finally:
        db.close()
    assert rows == statuses
    n_done = sum(s == "done" for s in statuses.values())
    print(f"\n{N} concurrent replay jobs: {n_done} done, {N - n_done} cancelled, all final in {elapsed:.1f} s")
    assert n_done >= N - len(to_cancel)
