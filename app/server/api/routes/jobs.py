"""/api/jobs: submit, list, watch, cancel, download artifacts and the exported twin."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Query
from fastapi.responses import FileResponse

from app.server.api.deps import DB, RegistryDep, RunnerDep, SettingsDep
from app.server.api.schemas import Artifact, JobCreate, JobDetail, JobOut, errors
from app.server.services import export as export_svc
from app.server.services import jobs as svc

router = APIRouter(prefix="/api/jobs", tags=["jobs"])


@router.post("", response_model=JobDetail, status_code=201, responses=errors(404))
def create_job(body: JobCreate, db: DB, settings: SettingsDep, registry: RegistryDep, runner: RunnerDep):
    """Validate the parameters against the type's schema and queue the job on Dask
    (404: unknown type or session; 422: bad parameters; nothing is queued then)."""
    return svc.create_job(db, settings, registry, runner, body.type, body.params)


@router.get("", response_model=list[JobOut], responses=errors())
def list_jobs(db: DB, status: str | None = None, type: str | None = None, limit: int = 200):
    return svc.list_jobs(db, status, type, min(max(limit, 1), 1000))


@router.get("/{job_id}", response_model=JobDetail, responses=errors(404))
def get_job(job_id: int, db: DB):
    return svc.get_job(db, job_id)


@router.post("/{job_id}/cancel", response_model=JobDetail, responses=errors(404, 409))
def cancel_job(job_id: int, db: DB, runner: RunnerDep):
    """Request cancellation (409 if the job is final already)."""
    return svc.cancel_job(db, runner, job_id)


@router.get("/{job_id}/artifacts", response_model=list[Artifact], responses=errors(404))
def list_artifacts(job_id: int, db: DB):
    return svc.list_artifacts(svc.get_job(db, job_id))


_FILE = {200: {"description": "the file, as it is (its media type guessed from its name)", "content": {"*/*": {}}}}


@router.get("/{job_id}/artifacts/{path:path}", responses={**_FILE, **errors(404)}, response_class=FileResponse)
def download_artifact(job_id: int, path: str, db: DB):
    """A file of the job's own artifact directory (nothing outside it: ``..``, absolute
    paths and symlinks leading out are 404)."""
    target = svc.artifact_path(svc.get_job(db, job_id), path)
    return FileResponse(target, filename=target.name)


_ZIP = {200: {"description": "a zip of the exported files, under one folder job-<id>-<format>/",
              "content": {"application/zip": {}}}}
ExportFormat = Annotated[Literal["vtu", "sofa", "mjcf"], Query(
    alias="format", description="vtu (ParaView), sofa (a SOFA Python3 scene) or mjcf (MuJoCo)")]


@router.get("/{job_id}/export", responses={**_ZIP, **errors(404, 409)}, response_class=FileResponse)
def export_job(job_id: int, fmt: ExportFormat, db: DB):
    """The calibrated twin of a finished replay or diagnose job as VTU, a SOFA scene or
    MuJoCo MJCF (``tissuetwin export``), zipped as ``job-<id>-<format>.zip``. Made on the
    first request into the job's folder (``export/<format>/``) and reused after.
    404: no such job; 409: not a finished replay or diagnose job (or its folder is gone,
    or the export failed); 422: an unknown format, or a run the export cannot read (the
    message says why). Nothing else of the job is changed."""
    target = export_svc.export_job(db, job_id, fmt)
    return FileResponse(target, filename=target.name, media_type="application/zip")
