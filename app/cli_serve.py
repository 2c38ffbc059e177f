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


def _replay_job(client, session_id: int, params: dict) -> tuple[int, bool]:
    """A replay job of the session with exactly these parameters: a finished (or still
    active) one is reused, else one is submitted. Returns (job id, reused)."""
    from app.server.jobs.types import ReplayParams

    wanted = ReplayParams.model_validate({**params, "session_id": session_id}).model_dump(mode="json")
    for status in ("done", "running", "queued"):
        for job in client.get("/api/jobs", params={"type": "replay", "status": status}).raise_for_status().json():
            if job["session_id"] == session_id and job["params"] == wanted:
                return job["id"], True
    r = client.post("/api/jobs", json={"type": "replay", "params": wanted})
    return r.raise_for_status().json()["id"], False


def _prepare_demo(url: str, sessions: list[tuple[Path, str]], replay_params: dict, ready: threading.Event,
                  stop: threading.Event) -> None:
    """Over the REST API, once the server answers: register the sessions, get the demo
    replay job (the first session's), show it in the viewer when done. Prints what it does."""
    import httpx

    try:
        if not ready.wait(timeout=300) or stop.is_set():
            return
        with httpx.Client(base_url=url, timeout=60) as client:
            ids = [_register(client, path, name) for path, name in sessions]
            job_id, reused = _replay_job(client, ids[0], replay_params)
            print(f"demo session = session {ids[0]}; replay job {job_id} "
                  f"({'reused' if reused else 'submitted'}): {url}/#job-{job_id}", flush=True)
            while not stop.wait(0.5):
                job = client.get(f"/api/jobs/{job_id}").raise_for_status().json()
                if job["status"] in ("done", "failed", "cancelled", "interrupted"):
                    break
            else:
                return
            if job["status"] != "done":
                print(f"demo replay job {job_id} {job['status']}: {job['error']}", file=sys.stderr, flush=True)
                return
            if client.get("/api/viewer").json().get("enabled"):
                client.post("/api/viewer/show", json={"job_id": job_id})
            print(f"demo replay job {job_id} done; open {url}/ (Ctrl-C stops the workbench)", flush=True)
    except Exception as exc:  # noqa: BLE001 - the server keeps running; the user sees why the demo job is missing
        print(f"could not prepare the demo job: {type(exc).__name__}: {exc}", file=sys.stderr, flush=True)


def serve_demo(data_dir: Path, sessions: list[tuple[Path, str]], replay_params: dict, *,
               host: str = "127.0.0.1", port: int | None = None) -> int:
    """Serve the workbench on ``data_dir`` until Ctrl-C (or SIGTERM), with ``sessions``
    (folder, name) registered and a replay job of the first one run (or reused).

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
