"""The app factory: settings -> database -> Dask runner -> viewer -> routes -> dashboard."""

from __future__ import annotations

import logging
from contextlib import asynccontextmanager
from pathlib import Path

from fastapi import FastAPI
from fastapi.responses import RedirectResponse
from fastapi.staticfiles import StaticFiles
from sqlalchemy import select

from app.server import db as dbm
from app.server.api.routes import job_types, jobs, sessions, system, viewer
from app.server.errors import JSONTooLarge, install_error_handlers
from app.server.jobs.registry import Registry
from app.server.jobs.runner import JobRunner, warm_imports
from app.server.settings import Settings

__all__ = ["create_app", "STATIC_DIR", "UPLOAD_OVERHEAD"]

STATIC_DIR = Path(__file__).resolve().parents[2] / "static"
log = logging.getLogger(__name__)


UPLOAD_OVERHEAD = 64 * 1024
"""Bytes of multipart framing and form fields allowed on top of ``max_upload_bytes``."""

VIEWER_TYPES = ("replay", "train", "diagnose")
"""Job types whose finished runs the viewer shows (their result says ``"viewer": true``)."""


class _Workbench(FastAPI):
    """FastAPI whose outermost layer turns Starlette's plain-text 413 into JSON."""

    def build_middleware_stack(self):
        return JSONTooLarge(super().build_middleware_stack())


def viewer_folder(job) -> Path:
    """The replay run folder of a job the viewer can show: a replay's artifacts, or the
    train or diagnose job's ``viewer_run`` (test sequences with the corrected mesh: the
    network's, or the model extended by the diagnosed effects)."""
    root = Path(job.artifact_dir)
    return root if job.type == "replay" else root / "viewer_run"


def _viewer_callbacks(factory):
    """The callbacks the viewer gets: runs and sessions from the database, arrays from
    run folders, ICP through the calibration service."""
    from app.server.services import calibration as cal
    from app.viewer.data import load_run, run_label
    from app.viewer.plan_data import load_plan_view
    from app.viewer.scene import ViewerCallbacks

    def runs():
        with factory() as db:
            q = (select(dbm.JobRecord).where(dbm.JobRecord.type.in_(VIEWER_TYPES), dbm.JobRecord.status == dbm.DONE)
                 .order_by(dbm.JobRecord.id.desc()))
            out = []
            for j in db.scalars(q):
                if not (j.result or {}).get("viewer"):
                    continue
                s = db.get(dbm.SessionRecord, j.session_id) if j.session_id else None
                out.append((j.id, run_label(j.type, viewer_folder(j), s.name if s else "?", j.result)))
            return out

    def load(run_id: int):
        with factory() as db:
            j = db.get(dbm.JobRecord, run_id)
            if j is None:
                raise KeyError(f"no job {run_id}")
            return load_run(viewer_folder(j), label=f"job {j.id}")

    def load_plan(job_id: int) -> dict:
        with factory() as db:
            j = db.get(dbm.JobRecord, job_id)
            if j is None or j.type != "plan" or j.status != dbm.DONE:
                raise KeyError(f"no finished plan job {job_id}")
            return load_plan_view(j.artifact_dir)

    def sessions():
        with factory() as db:
            return [(s.id, s.name) for s in db.scalars(select(dbm.SessionRecord).order_by(dbm.SessionRecord.id))]

    def path_of(session_id: int) -> str:
        with factory() as db:
            s = db.get(dbm.SessionRecord, session_id)
            if s is None:
                raise KeyError(f"no session {session_id}")
            return s.path

    return ViewerCallbacks(
        runs=runs, load_run=load, sessions=sessions,
        icp_inputs=lambda sid: cal.reference_and_surface(path_of(sid)),
        icp_preview=lambda sid, pc, pp: cal.preview(path_of(sid), pc, pp),
        icp_accept=lambda sid, pc, pp: cal.accept(path_of(sid), pc, pp),
        load_plan=load_plan,
    )


def create_app(settings: Settings | None = None, registry: Registry | None = None) -> FastAPI:
    """Build the workbench app. Start-up (in the lifespan): create the data folders and
    tables, mark jobs a previous server left behind ``interrupted``, import ``core``
    (:func:`app.server.jobs.runner.warm_imports`), start the Dask
    runner and (``settings.viewer``) the viser viewer; shut-down stops both. Request
    bodies are limited while they stream in: ``settings.max_body_bytes`` for JSON routes,
    ``settings.max_upload_bytes`` (+ :data:`UPLOAD_OVERHEAD`) for the zip upload.

    Args:
        settings: defaults from the environment (:class:`Settings`).
        registry: job types (default :func:`app.server.jobs.types.default_registry`).
    """
    settings = settings or Settings()
    if registry is None:
        from app.server.jobs.types import default_registry

        registry = default_registry()

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        Path(settings.data_dir).mkdir(parents=True, exist_ok=True)
        settings.jobs_dir.mkdir(parents=True, exist_ok=True)
        engine = dbm.make_engine(settings.url)
        factory = dbm.make_sessionmaker(engine)
        orphans = dbm.active_tokens(factory)
        n = dbm.mark_interrupted(factory)
        if n:
            log.warning("%d job(s) of a previous server marked interrupted", n)
        warm_imports()  # request threads validate job parameters with ``core`` (see WARM_IMPORTS)
        runner = JobRunner(settings, factory, registry)
        runner.start()
        if runner.cancel_orphans(orphans):
            log.warning("cancelled %d task(s) a previous server left on the cluster", len(orphans))
        app.state.settings, app.state.registry = settings, registry
        app.state.sessionmaker, app.state.runner, app.state.viewer = factory, runner, None
        try:
            if settings.viewer:
                from app.viewer.scene import WorkbenchViewer

                app.state.viewer = WorkbenchViewer(_viewer_callbacks(factory), settings.viewer_host, settings.viewer_port)
            yield
        finally:
            if app.state.viewer is not None:
                app.state.viewer.stop()
            runner.close()
            engine.dispose()

    app = _Workbench(
        title="Tissue Twin workbench",
        description="Sessions, jobs (generate, replay, sweep, fit) on Dask, artifacts, and the 3D viewer.",
        version="0.1.0",
        lifespan=lifespan,
        # request bodies are counted while they stream in: 413 as soon as one is too large
        max_body_size=settings.max_body_bytes,
    )
    install_error_handlers(app)
    for r in (system.router, sessions.router, job_types.router, jobs.router, viewer.router):
        app.include_router(r)
    app.include_router(sessions.upload_router, max_body_size=settings.max_upload_bytes + UPLOAD_OVERHEAD)
    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")

    @app.get("/", include_in_schema=False)
    def index():
        return RedirectResponse("/static/index.html")

    return app
