"""``tissuetwin serve``: the workbench (dashboard, REST API, 3D viewer)."""

from __future__ import annotations

import sys


def cmd_serve(args) -> int:
    """Start uvicorn with the app factory; the viewer listens on ``--viewer-port``."""
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
    settings = Settings(**overrides)
    if args.host not in ("127.0.0.1", "localhost", "::1"):
        print(f"warning: serving on {args.host}: the workbench has no authentication", file=sys.stderr)
    print(f"dashboard http://{args.host}:{args.port}/   API docs http://{args.host}:{args.port}/docs   "
          f"data {settings.data_dir}   database {settings.url.split('@')[-1]}", flush=True)
    uvicorn.run(create_app(settings), host=args.host, port=args.port, log_level=args.log_level)
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
    p.add_argument("--log-level", default="warning", choices=("critical", "error", "warning", "info", "debug"))
    p.set_defaults(func=cmd_serve)
