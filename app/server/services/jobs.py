"""Jobs: create (validate, persist, submit), list, cancel, artifacts."""

from __future__ import annotations

from pathlib import Path

from sqlalchemy import select
from sqlalchemy.orm import Session as DB

from app.server import db as dbm
from app.server.errors import Conflict, NotFound
from app.server.jobs.registry import Registry
from app.server.jobs.runner import JobRunner
from app.server.services.sessions import get_session
from app.server.settings import Settings
from core.io import read_picked

__all__ = ["create_job", "list_jobs", "get_job", "cancel_job", "list_artifacts", "artifact_path"]


def create_job(db: DB, settings: Settings, registry: Registry, runner: JobRunner, type_name: str, params: dict) -> dbm.JobRecord:
    """Validate ``params`` against the type's model, store the job (queued) and submit it.

    Raises:
        NotFound: unknown type or session. pydantic.ValidationError: bad parameters (422).
    """
    job_type = registry.get(type_name)
    if job_type is None:
        raise NotFound(f"no job type {type_name!r}; available: {registry.names()}")
    model = job_type.params.model_validate(params)
    session_path = picked = None
    session_id = getattr(model, "session_id", None)
    if session_id is not None:
        rec = get_session(db, session_id)
        session_path = rec.path
        pairs = read_picked(rec.path)
        picked = None if pairs is None else (pairs[0].tolist(), pairs[1].tolist())
    job = dbm.JobRecord(type=type_name, params=model.model_dump(mode="json"), session_id=session_id, status=dbm.QUEUED)
    db.add(job)
    db.flush()
    job.artifact_dir = str((settings.jobs_dir / str(job.id)).resolve())
    job.log = ""
    db.commit()
    try:
        runner.submit(job, session_path, picked)
    except Exception as exc:  # noqa: BLE001 - a job the cluster never got must not stay queued forever
        job.status, job.error, job.finished_at = dbm.FAILED, f"could not submit to Dask: {type(exc).__name__}: {exc}", dbm.utcnow()
        db.commit()
    return job


def list_jobs(db: DB, status: str | None = None, type_name: str | None = None, limit: int = 200) -> list[dbm.JobRecord]:
    q = select(dbm.JobRecord).order_by(dbm.JobRecord.id.desc()).limit(limit)
    if status:
        q = q.where(dbm.JobRecord.status == status)
    if type_name:
        q = q.where(dbm.JobRecord.type == type_name)
    return list(db.scalars(q))


def get_job(db: DB, job_id: int) -> dbm.JobRecord:
    """Raises NotFound (also for ids no database column can hold)."""
    job = db.get(dbm.JobRecord, job_id) if dbm.valid_id(job_id) else None
    if job is None:
        raise NotFound(f"no job with id {job_id}")
    return job


def cancel_job(db: DB, runner: JobRunner, job_id: int) -> dbm.JobRecord:
    """Request cancellation; the job turns ``cancelled`` at its next progress report.

    Raises:
        NotFound. Conflict: the job is final already.
    """
    job = get_job(db, job_id)
    if job.status in dbm.FINAL:
        raise Conflict(f"job {job_id} is {job.status} already")
    job.cancel_requested = True
    db.commit()
    runner.cancel(job_id)
    return job


def list_artifacts(job: dbm.JobRecord) -> list[dict]:
    """Files in the job's artifact directory: relative path and size in bytes."""
    if not job.artifact_dir:  # never a relative "" (that would be the server's working directory)
        return []
    root = Path(job.artifact_dir)
    if not root.is_dir():
        return []
    return [{"path": p.relative_to(root).as_posix(), "size": p.stat().st_size}
            for p in sorted(root.rglob("*")) if p.is_file() and not p.is_symlink()]


def artifact_path(job: dbm.JobRecord, relative: str) -> Path:
    """The file ``relative`` inside the job's own artifact directory.

    Raises:
        NotFound: missing, a directory, or outside the artifact directory (``..``,
            absolute paths, symlinks leading out).
    """
    if not job.artifact_dir:
        raise NotFound(f"job {job.id} has no artifacts")
    root = Path(job.artifact_dir).resolve()
    try:
        target = (root / relative).resolve()
        ok = target.is_relative_to(root) and target != root and target.is_file()
    except (OSError, ValueError):  # NUL byte, name too long, symlink loop
        ok = False
    if not ok:
        raise NotFound(f"job {job.id} has no artifact {relative!r}")
    return target

