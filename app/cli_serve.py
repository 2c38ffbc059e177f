"""``tissuetwin serve``: the workbench (dashboard, REST API, 3D viewer)."""

from __future__ import annotations

import os
import sys
import threading
from pathlib import Path


def is_loopback(host: str) -> bool:
    """True if binding ``host`` keeps the server reachable from this machine only
    (``localhost``, 127.0.0.0/8, ``::1``). ``0.0.0.0``, ``::``, names and other addresses
    are not."""
    import ipaddress

    if host.strip("[]").lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def bind_warning(host: str, session_roots=()) -> str | None:
    """The warning to print when serving on ``host``, or None on loopback."""
    if is_loopback(host):
        return None
    roots = "" if session_roots else (" and any folder the server can read may be registered as a session"
                                      " (restrict with --session-root)")
    return (f"warning: serving on {host}, reachable from other machines: the workbench has no "
            f"authentication{roots}; put it behind an authenticating proxy or use 127.0.0.1")


def cmd_serve(args) -> int:
    """Start uvicorn with the app factory; the viewer listens on ``--viewer-port``.
    Binds ``--host`` (loopback by default) and warns on stderr when that is not loopback."""
    import uvicorn

    from app.server.main import create_app
    from app.server.settings import Settings

    overrides = {"viewer": not args.no_viewer,
                 "viewer_port": args.viewer_port or args.port + 1, "viewer_host": args.host}
    if args.data:
        overrides["data_dir"] = args.data
    if args.scheduler:
        overrides["scheduler"] = args.scheduler
    if args.workers is not None:
        overrides["workers"] = args.workers
    if getattr(args, "session_root", None):
        overrides["session_roots"] = args.session_root
    settings = Settings(**overrides)
    warning = bind_warning(args.host, settings.session_roots)
    if warning:
        print(warning, file=sys.stderr, flush=True)
    print(f"dashboard http://{args.host}:{args.port}/   API docs http://{args.host}:{args.port}/docs   "
          f"data {settings.data_dir}   database {settings.url.split('@')[-1]}", flush=True)
    uvicorn.run(create_app(settings), host=args.host, port=args.port, log_level=args.log_level)
    return 0


class _Stop(Exception):
    """SIGTERM, turned into an ordinary exception once uvicorn has shut down."""


def _raise_stop(signum, frame):  # noqa: ARG001 - signal handler signature
    raise _Stop()


def demo_port() -> int:
    """Port of ``tissuetwin demo``'s workbench: ``TISSUETWIN_PORT`` or 8000."""
    return int(os.environ.get("TISSUETWIN_PORT", "8000"))


def _register(client, path: Path, name: str) -> int:
    """Id of the session registered at ``path`` (registered now if it is not yet)."""
    folder = str(path.expanduser().resolve())
    for s in client.get("/api/sessions").raise_for_status().json():
        if s["path"] == folder:
            return s["id"]
    return client.post("/api/sessions", json={"path": folder, "name": name}).raise_for_status().json()["id"]


FINAL = ("done", "failed", "cancelled", "interrupted")


def demo_analyses(replay_params: dict) -> list[tuple[str, dict]]:
    """The analyses ``tissuetwin demo`` runs on the demo session after its replay, in
    order, as (job type, parameters without ``session_id``); the quick ones first:

    * sweep: the paper's grid search (Wu et al. 2020, Tables 1-2): the decades 1e1-1e6 Pa,
      then the 2.5/5/7.5 fine grid around the best, on the train sequences;
    * train: the 2D correction network at the replay's E with narrow widths (16 32 64
      instead of the paper's 64 128 256), at most 6 epochs (patience 3), 512 measured
      points per frame in the loss; its test sequences give the viewer's corrected mesh;
    * fit: E with its 95 % interval, or the reason it cannot be identified (the defaults);
    * diagnose: what the base model lacks, with the E fit (the defaults).

    Measured on the idle 2-core development machine with the demo session of
    :data:`core.lab.DEMO_EFFECTS` (6 x 10 s, force): replay job 15 s, sweep 12 s, train 18 s,
    fit 24 s, diagnose 311 s (it names gravity and the robot offset); 6.8 min from the
    command to the diagnosis. (With the earlier 6 x 20 s demo session on a machine loaded
    15-19: sweep 2.0 min, train 2.2, fit 3.7, diagnose 24.)

    The model options of the demo's replay (Poisson's ratio, grid, effects) carry over.
    """
    model = {k: replay_params[k] for k in ("poisson_ratio", "grid", "effects") if replay_params.get(k) is not None}
    return [
        ("sweep", {**model, "e_min": 10.0, "e_max": 1e6, "per_decade": 1, "refine": True}),
        ("train", {**model, "model": "2d", "youngs_modulus": replay_params.get("youngs_modulus", 5000.0),
                   "widths": [16, 32, 64], "epochs": 6, "patience": 3, "max_points": 512}),
        ("fit", dict(model)),
        ("diagnose", {k: v for k, v in model.items() if k == "grid"}),
    ]


def _job(client, job_type: str, session_id: int, params: dict) -> tuple[dict, str]:
    """The job of this type on the session with exactly these parameters: one that is
    done, failed, running or queued is reused; else (none, or only interrupted or
    cancelled ones) one is submitted. Returns (job, how) with how "reused",
    "submitted", or "resubmitted" when an earlier one was interrupted or cancelled."""
    from app.server.jobs.types import default_registry

    model = default_registry().get(job_type).params
    wanted = model.model_validate({**params, "session_id": session_id}).model_dump(mode="json")
    same = [j for j in client.get("/api/jobs", params={"type": job_type}).raise_for_status().json()
            if j["session_id"] == session_id and j["params"] == wanted]
    for status in ("done", "running", "queued", "failed"):
        for job in same:
            if job["status"] == status:
                return job, "reused"
    job = client.post("/api/jobs", json={"type": job_type, "params": wanted}).raise_for_status().json()
    lost = [j for j in same if j["status"] in ("interrupted", "cancelled")]
    if lost:
        return job, f"resubmitted: job {lost[0]['id']} was {lost[0]['status']} ({lost[0]['error']})"
    return job, "submitted"


def _wait_final(client, job_id: int, stop: threading.Event) -> dict | None:
    """Poll a job until it ends; None when the workbench stops first."""
    while not stop.wait(0.5):
        job = client.get(f"/api/jobs/{job_id}").raise_for_status().json()
        if job["status"] in FINAL:
            return job
    return None


def _outcome(job: dict) -> str:
    """One line on what a finished demo analysis found."""
    r = job.get("result") or {}
    if job["status"] != "done":
        return f"{job['status']}: {job['error']}"
    if job["type"] == "sweep":
        if "youngs_modulus" not in r:  # a sweep from before the verdict
            return f"lowest error at E {r.get('best'):g} Pa of {len(r.get('table', []))} values" if r.get("best") else "no finite error"
    if job["type"] in ("sweep", "fit"):  # one verdict on E (core.identification.verdict)
        y = r.get("youngs_modulus") or {}
        if y.get("identifiable"):
            lo, hi = y["interval"]
            return f"E = {y['value']:.4g} Pa (95 % interval {lo:.4g}-{hi:.4g} Pa)"
        return f"E not identifiable: {y.get('reason')}"
    if job["type"] == "diagnose":
        kinds = [c.get("kind") for c in r.get("causes") or []]
        return "causes: " + ", ".join(kinds) if kinds else "no effect found"
    if job["type"] == "train":
        te = r.get("test_error") or {}
        mm = {k: "N/A" if te.get(k) is None else f"{te[k] * 1e3:.3f} mm" for k in ("no_network", "corrected", "corrected_offline")}
        return (f"test error {mm['no_network']} without the network, {mm['corrected']} corrected in the loop, "
                f"{mm['corrected_offline']} offline")
    return "done"


def _prepare_demo(url: str, sessions: list[tuple[Path, str]], replay_params: dict, ready: threading.Event,
                  stop: threading.Event) -> None:
    """Over the REST API, once the server answers: register the sessions, get the demo
    replay job (the first session's) and show it in the viewer when done, then run the
    :func:`demo_analyses` one after another (each reused when an identical one exists),
    showing the train job's corrected mesh when it is done. Prints what it does."""
    import httpx

    try:
        if not ready.wait(timeout=300) or stop.is_set():
            return
        with httpx.Client(base_url=url, timeout=60) as client:
            ids = [_register(client, path, name) for path, name in sessions]
            job, how = _job(client, "replay", ids[0], replay_params)
            print(f"demo session = session {ids[0]}; replay job {job['id']} ({how}); dashboard {url}/", flush=True)
            job = _wait_final(client, job["id"], stop)
            if job is None:
                return
            if job["status"] != "done":
                print(f"demo replay job {job['id']} {job['status']}: {job['error']}", file=sys.stderr, flush=True)
                return
            viewer = client.get("/api/viewer").json().get("enabled")
            if viewer:
                client.post("/api/viewer/show", json={"job_id": job["id"]})
            print(f"demo replay job {job['id']} done; open {url}/ (Ctrl-C stops the workbench)", flush=True)
            plan = demo_analyses(replay_params)
            print("demo analyses, one after another: " + ", ".join(t for t, _ in plan)
                  + " (the dashboard shows each result as it finishes)", flush=True)
            for job_type, params in plan:
                job, how = _job(client, job_type, ids[0], params)
                print(f"demo {job_type} job {job['id']} ({how})", flush=True)
                if job["status"] not in FINAL:
                    job = _wait_final(client, job["id"], stop)
                    if job is None:
                        return
                print(f"demo {job_type} job {job['id']}: {_outcome(job)}", flush=True)
                if viewer and job["status"] == "done" and job_type == "train" and (job.get("result") or {}).get("viewer"):
                    client.post("/api/viewer/show", json={"job_id": job["id"]})
                    print(f"the viewer now shows job {job['id']}'s corrected mesh", flush=True)
            print("demo analyses finished", flush=True)
    except Exception as exc:  # noqa: BLE001 - the server keeps running; the user sees why the demo job is missing
        if not stop.wait(5):  # a request cut by Ctrl-C is no error: the shut-down sets ``stop`` soon after
            print(f"could not prepare the demo jobs: {type(exc).__name__}: {exc}", file=sys.stderr, flush=True)


def serve_demo(data_dir: Path, sessions: list[tuple[Path, str]], replay_params: dict, *,
               host: str = "127.0.0.1", port: int | None = None) -> int:
    """Serve the workbench on ``data_dir`` until Ctrl-C (or SIGTERM), with ``sessions``
    (folder, name) registered, a replay job of the first one run (or reused) and shown in
    the viewer, then the :func:`demo_analyses` of it run one after another. Ctrl-C leaves
    unfinished jobs ``interrupted``; the next demo runs them again and says so.

    Args:
        replay_params: parameters of the replay job (``ReplayParams`` without ``session_id``).
        port: dashboard port (default :func:`demo_port`); the viewer listens on port + 1.

    Returns:
        0 after a clean shut-down.
    """
    import signal

    import uvicorn

    from app.server.main import create_app
    from app.server.settings import Settings

    port = demo_port() if port is None else port
    settings = Settings(data_dir=data_dir, viewer_port=port + 1, viewer_host=host)
    warning = bind_warning(host, settings.session_roots)
    if warning:
        print(warning, file=sys.stderr, flush=True)
    server = uvicorn.Server(uvicorn.Config(create_app(settings), host=host, port=port, log_level="warning"))
    url = f"http://{'127.0.0.1' if host in ('0.0.0.0', '::') else host}:{port}"
    ready, stop = threading.Event(), threading.Event()

    def watch_startup():
        while not server.started and not stop.wait(0.1):
            pass
        ready.set()

    threading.Thread(target=watch_startup, daemon=True).start()
    helper = threading.Thread(target=_prepare_demo, args=(url, sessions, replay_params, ready, stop), daemon=True)
    helper.start()
    print(f"workbench: dashboard {url}/   API docs {url}/docs   data {settings.data_dir}   (Ctrl-C stops it)", flush=True)
    # uvicorn re-raises the signal that stopped it after its shut-down: SIGINT arrives as
    # KeyboardInterrupt, SIGTERM as _Stop; both are a normal end of the demo.
    previous = signal.signal(signal.SIGTERM, _raise_stop)
    try:
        server.run()
    except (KeyboardInterrupt, _Stop):
        pass
    finally:
        stop.set()
        ready.set()
        signal.signal(signal.SIGTERM, previous)
    helper.join(timeout=5)
    if not server.started:
        print(f"error: the workbench did not start on {host}:{port} (port in use? set TISSUETWIN_PORT)", file=sys.stderr)
        return 2
    print("workbench stopped", flush=True)
    return 0


def register(subparsers) -> None:
    """Add ``serve`` to the ``tissuetwin`` subcommands."""
    p = subparsers.add_parser("serve", help="start the workbench: dashboard, REST API (/docs) and 3D viewer")
    p.add_argument("--host", default="127.0.0.1", help="bind address (default loopback)")
    p.add_argument("--port", type=int, default=8000, help="dashboard and API port (default 8000)")
    p.add_argument("--viewer-port", type=int, default=None, help="viser viewer port (default PORT + 1)")
    p.add_argument("--no-viewer", action="store_true", help="run without the 3D viewer")
    p.add_argument("--data", default=None, help="data directory: database, uploads, job artifacts (default ./data, env TISSUETWIN_DATA)")
    p.add_argument("--scheduler", default=None, help="existing Dask scheduler, e.g. tcp://host:8786 (default: a local cluster; env TISSUETWIN_SCHEDULER)")
    p.add_argument("--workers", type=int, default=None, help="worker processes of the local cluster (default 2)")
    p.add_argument("--session-root", action="append", default=None, metavar="DIR",
                   help="only register session folders under DIR (repeatable; default: any folder; "
                        "env TISSUETWIN_SESSION_ROOTS as a JSON list)")
    p.add_argument("--log-level", default="warning", choices=("critical", "error", "warning", "info", "debug"))
    p.set_defaults(func=cmd_serve)
