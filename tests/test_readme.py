"""The README's main command, run as a user would (smoke test)."""

import json
import os
import re
import signal
import socket
import sqlite3
import subprocess
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FINAL = {"done", "failed", "cancelled", "interrupted"}


def _commands() -> list[str]:
    blocks = re.findall(r"```bash\n(.*?)```", (ROOT / "README.md").read_text(), flags=re.S)
    return [b.strip() for b in blocks[:2]]


def test_readme_gives_exactly_two_setup_commands():
    main_cmd, test_cmd = _commands()
    assert "\n" not in main_cmd and "\n" not in test_cmd
    assert main_cmd.startswith("bash scripts/setup.sh && ") and "tissuetwin demo" in main_cmd
    assert test_cmd.startswith("bash scripts/setup.sh && ") and "pytest" in test_cmd
    ci = (ROOT / ".ci" / "run").read_text()
    assert test_cmd in ci


def _free_port() -> int:
    """A loopback port whose successor (the viewer's) is free too."""
    for _ in range(50):
        with socket.socket() as a:
            a.bind(("127.0.0.1", 0))
            port = a.getsockname()[1]
            try:
                with socket.socket() as b:
                    b.bind(("127.0.0.1", port + 1))
            except OSError:
                continue
        return port
    pytest.fail("no pair of free loopback ports")


def _get(url: str):
    """JSON of a GET on loopback, or None while the server does not answer."""
    import httpx

    try:
        r = httpx.get(url, timeout=5)
    except httpx.HTTPError:
        return None
    return r.json() if r.status_code == 200 else None


def _wait_for(what: str, fn, proc, log: Path, timeout: float):
    """Poll ``fn`` until it returns something truthy; fail if the command exits first."""
    deadline = time.monotonic() + timeout
    while True:
        value = fn()
        if value:
            return value
        if proc.poll() is not None:
            pytest.fail(f"the command exited ({proc.returncode}) before {what}:\n{log.read_text()[-4000:]}")
        if time.monotonic() > deadline:
            pytest.fail(f"timed out waiting for {what}:\n{log.read_text()[-4000:]}")
        time.sleep(1.0)


def _ctrl_c(proc) -> None:
    """What Ctrl-C in a terminal does to the command: SIGINT to tissuetwin and its Dask
    workers. The ``sh -c`` wrapper of the test is spared (a non-interactive sh dies of
    SIGINT at once; the user's interactive shell does not), so its exit status is the
    command's."""
    import psutil

    shell = psutil.Process(proc.pid)
    for p in [shell, *shell.children(recursive=True)]:
        try:
            if p.pid != proc.pid or p.name() not in ("sh", "dash", "bash"):  # the shell may have exec'd the command
                p.send_signal(signal.SIGINT)
        except psutil.NoSuchProcess:
            pass


@pytest.mark.slow
def test_readme_main_command_runs(tmp_path):
    """Runs the README's main command verbatim from the repository root, as a user would:
    the demo session (with its hidden effects and force columns) is made, the sample session
    replays, then the workbench opens on the demo session with its replay job run (the one
    replay of it),
    and queues the demo's analyses after it. The test waits until the dashboard answers on
    loopback, that job is done and the first analysis (the sweep) is queued or running
    (REST), then presses Ctrl-C (SIGINT to the command and its workers, as a terminal does)
    and checks the command exits cleanly, without worker tracebacks, leaving the sweep
    ``interrupted`` in the database with the reason. The demo data go to a temporary folder (TISSUETWIN_DATA) and
    the workbench to a free port (TISSUETWIN_PORT) so the checkout and port 8000 stay free."""
    main_cmd, _ = _commands()
    data = tmp_path / "data"
    port = _free_port()
    url = f"http://127.0.0.1:{port}"
    env = dict(os.environ, TISSUETWIN_DATA=str(data), TISSUETWIN_PORT=str(port))
    log = tmp_path / "demo.log"
    with open(log, "w") as out:
        proc = subprocess.Popen(main_cmd, shell=True, cwd=ROOT, env=env, stdout=out, stderr=subprocess.STDOUT,
                                text=True, start_new_session=True)
    try:
        # setup, the demo session (generated once), the sample replay, then the server; the timeouts only guard a hang
        _wait_for("the dashboard", lambda: _get(f"{url}/api/health"), proc, log, timeout=1800)
        page = httpx_get_text(f"{url}/")
        assert "Tissue Twin workbench" in page
        sessions = _wait_for("the demo session registered", lambda: [s for s in _get(f"{url}/api/sessions") or []
                                                                     if s["name"] == "demo-session"], proc, log, timeout=120)
        demo_id = sessions[0]["id"]
        assert Path(sessions[0]["path"]) == (data / "demo-session").resolve()
        job = _wait_for("the demo replay job done", lambda: [j for j in _get(f"{url}/api/jobs?type=replay") or []
                                                             if j["session_id"] == demo_id and j["status"] in FINAL],
                        proc, log, timeout=600)[0]
        assert job["status"] == "done", job
        detail = _get(f"{url}/api/jobs/{job['id']}")
        meta = json.loads((data / "demo-session" / "session.json").read_text())
        assert set(detail["result"]["sequences"]) == {sq["name"] for sq in meta["sequences"]}
        assert not (data / "runs" / "demo-replay").exists()  # the demo session is replayed once: by the job
        # the demo session hides what the README says the diagnosis will name, with force columns
        from core.lab import DEMO_EFFECTS, complete_effects

        truth = json.loads((data / "demo-session" / "truth.json").read_text())
        assert truth["effects"] == complete_effects(DEMO_EFFECTS)
        assert "fx" in next((data / "demo-session" / "sequences").glob("*/kinematics.csv")).read_text().splitlines()[0]
        if (ROOT.parent / "shared" / "sample-session" / "session.json").exists():
            assert (data / "runs" / "sample-replay" / "replay.json").exists()
            assert any(s["name"] == "sample-session" for s in _get(f"{url}/api/sessions"))
        sweep = _wait_for("the demo sweep queued after the replay", lambda: [
            j for j in _get(f"{url}/api/jobs?type=sweep") or [] if j["session_id"] == demo_id], proc, log, timeout=120)[0]
        assert sweep["params"]["refine"] and sweep["status"] in ("queued", "running"), sweep

        t0 = time.monotonic()
        _ctrl_c(proc)
        rc = proc.wait(timeout=120)
        print(f"exit {time.monotonic() - t0:.1f} s after Ctrl-C with the sweep {sweep['status']}")
        text = log.read_text()
        assert rc == 0, text[-4000:]
        assert "mean error (mm)" in text and "workbench stopped" in text
        assert "Traceback" not in text and "KeyboardInterrupt" not in text, text[-4000:]
        assert _get(f"{url}/api/health") is None  # nothing left listening
        db = sqlite3.connect(data / "workbench.db")
        try:
            status, error = db.execute("select status, error from jobs where id = ?", (sweep["id"],)).fetchone()
            active = db.execute("select count(*) from jobs where status in ('queued', 'running')").fetchone()[0]
        finally:
            db.close()
        assert status == "interrupted" and "server stopped" in error and active == 0
    finally:
        try:  # the command if still running, and whatever of its group is left (Dask workers)
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        proc.wait(timeout=30)


def httpx_get_text(url: str) -> str:
    import httpx

    return httpx.get(url, timeout=10, follow_redirects=True).text
