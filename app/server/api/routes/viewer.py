"""/api/viewer: where the 3D viewer is, what it shows, and remote control from the dashboard."""

from __future__ import annotations

from fastapi import APIRouter

from app.server.api.deps import DB, ViewerDep
from app.server.api.schemas import ViewerFrame, ViewerIcp, ViewerPlan, ViewerShow, errors
from app.server.errors import Conflict, Invalid, NotFound
from app.server.services import jobs as job_svc
from app.server.services import sessions as session_svc

router = APIRouter(prefix="/api/viewer", tags=["viewer"])


def _need(viewer):
    if viewer is None:
        raise Conflict("the viewer is not running (serve without --no-viewer)")
    return viewer


@router.get("", responses=errors())
def viewer_state(viewer: ViewerDep):
    """Port, what is shown, frame and time, picks; ``{"enabled": false}`` without a viewer."""
    if viewer is None:
        return {"enabled": False}
    return {"enabled": True, **viewer.state()}


@router.post("/show", responses=errors(404, 409))
def show_run(body: ViewerShow, db: DB, viewer: ViewerDep):
    """Load a finished replay job's run (once) and show a sequence in the viewer tab of
    ``tab`` (the dashboard's own iframe) or, without it, in every tab (404: no such job or
    sequence; 422: not a finished job with a viewer run)."""
    viewer = _need(viewer)
    job = job_svc.get_job(db, body.job_id)
    if job.status != "done" or not (job.result or {}).get("viewer"):
        raise Invalid(f"job {job.id} is a {job.status} {job.type} job; the viewer shows finished replay, train and diagnose jobs")
    try:
        viewer.show_run(job.id, body.sequence, tab=body.tab)
    except KeyError as exc:  # the run has no such sequence
        raise NotFound(str(exc.args[0]) if exc.args else f"job {job.id} has no sequence {body.sequence!r}") from exc
    return viewer.state(body.tab)


@router.post("/plan", responses=errors(404, 409))
def show_plan(body: ViewerPlan, db: DB, viewer: ViewerDep):
    """Draw a finished plan job's probe path over the phantom, in the viewer tab of ``tab``
    or, without it, in every tab (404: no such job; 422: not a finished plan job)."""
    viewer = _need(viewer)
    job = job_svc.get_job(db, body.job_id)
    if job.type != "plan" or job.status != "done":
        raise Invalid(f"job {job.id} is a {job.status} {job.type} job; the viewer draws finished plan jobs")
    viewer.show_plan(job.id, tab=body.tab)
    return viewer.state(body.tab)


@router.post("/frame", responses=errors(409))
def set_frame(body: ViewerFrame, viewer: ViewerDep):
    viewer = _need(viewer)
    viewer.set_frame(body.frame, tab=body.tab)
    return viewer.state(body.tab)


@router.post("/icp", responses=errors(404, 409))
def start_icp(body: ViewerIcp, db: DB, viewer: ViewerDep):
    """Open the picking mode of the viewer on a session's reference cloud, in the viewer
    tab of ``tab`` or, without it, in every tab."""
    viewer = _need(viewer)
    session_svc.get_session(db, body.session_id)
    viewer.start_icp(body.session_id, tab=body.tab)
    return viewer.state(body.tab)
