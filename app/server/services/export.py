"""Export of a finished job's calibrated twin (issue 19, item 5): the job's own run folder
through :func:`app.export.export_run`, zipped for download.

The export goes into the job's folder, ``export/<format>/`` (and the zip beside it,
``export/job-<id>-<format>.zip``), and is reused by later requests. Both are made under
temporary names and renamed into place when complete, so a failed or concurrent export
never leaves a half-written folder or zip behind; nothing else in the job's folder is
touched.
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
import threading
import zipfile
from pathlib import Path

from sqlalchemy.orm import Session as DB

from app.server import db as dbm
from app.server.errors import Conflict, Invalid
from app.server.services.jobs import get_job
from core.errors import TissueTwinError

__all__ = ["EXPORT_FORMATS", "EXPORT_TYPES", "EXPORT_DIR", "export_job", "export_zip", "zip_name"]

log = logging.getLogger(__name__)

EXPORT_FORMATS = ("vtu", "sofa", "mjcf")
"""As :data:`app.export.FORMATS` (repeated so that the server imports the writers only when exporting)."""

EXPORT_TYPES = ("replay", "diagnose")
"""Job types with a calibrated model to export: a replay (``replay.json`` and its
trajectories) and a diagnosis (``diagnosis.json``: the base model plus the claimed causes)."""

EXPORT_DIR = "export"
"""The subfolder of a job's folder that holds its exports."""

_locks: dict[tuple[str, str], threading.Lock] = {}
_locks_guard = threading.Lock()


def _lock(folder: Path, fmt: str) -> threading.Lock:
    """One lock per (job folder, format): concurrent requests for one export wait for the first."""
    with _locks_guard:
        return _locks.setdefault((str(folder), fmt), threading.Lock())


def zip_name(job: dbm.JobRecord, fmt: str) -> str:
    """The download's file name, ``job-<id>-<format>.zip``."""
    return f"job-{job.id}-{fmt}.zip"


def _check(job: dbm.JobRecord, fmt: str) -> Path:
    """The job's folder, if ``job`` can be exported as ``fmt``.

    Raises:
        Invalid: an unknown format. Conflict: a job of a type without a model, one that
            is not finished, or whose folder is gone.
    """
    if fmt not in EXPORT_FORMATS:
        raise Invalid(f"unknown export format {fmt!r}; expected one of {', '.join(EXPORT_FORMATS)}")
    if job.type not in EXPORT_TYPES:
        raise Conflict(f"job {job.id} is a {job.type} job; only finished {' and '.join(EXPORT_TYPES)} jobs have a "
                       f"calibrated twin to export")
    if job.status != dbm.DONE:
        raise Conflict(f"job {job.id} is {job.status}; only a finished (done) {job.type} job can be exported")
    folder = Path(job.artifact_dir) if job.artifact_dir else None
    if folder is None or not folder.is_dir():
        raise Conflict(f"job {job.id} has no output folder any more ({job.artifact_dir or 'none recorded'})")
    return folder


def _run_options(job: dbm.JobRecord, session_path: str | None) -> dict:
    """Keyword arguments of :func:`app.export.export_run` for the job: the session folder
    the database knows (when it is still a session), and a diagnosis's node grid."""
    options: dict = {}
    if session_path and (Path(session_path) / "session.json").is_file():
        options["session"] = session_path
    grid = (job.params or {}).get("grid")
    if job.type == "diagnose" and isinstance(grid, list) and len(grid) == 3:
        options["grid"] = tuple(int(g) for g in grid)
    return options


def _export_folder(job: dbm.JobRecord, folder: Path, fmt: str, session_path: str | None) -> Path:
    """``export/<fmt>/`` of the job's folder, written now unless a complete one is there
    (``twin.json`` is written last)."""
    from app.export import export_run

    root = folder / EXPORT_DIR
    target = root / fmt
    if (target / "twin.json").is_file():
        return target
    fresh = not root.exists()
    root.mkdir(exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{fmt}-", dir=root))
    try:
        export_run(folder, fmt, tmp, **_run_options(job, session_path))
        if target.exists() and not (target / "twin.json").is_file():
            shutil.rmtree(target)  # incomplete (no twin.json, so not an export of ours): replaced
        try:
            os.rename(tmp, target)
        except OSError:
            if not (target / "twin.json").is_file():  # else another server process made it meanwhile
                raise
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
        if fresh and not any(root.iterdir()):  # a failed first export leaves no empty export/ behind
            root.rmdir()
    return target


def _zip(source: Path, dest: Path, top: str) -> None:
    """Zip the files under ``source`` into ``dest`` (atomically), each under ``top/``."""
    fd, tmp_name = tempfile.mkstemp(prefix=f".{dest.name}-", dir=dest.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED) as zf:
            for f in sorted(source.rglob("*")):
                if f.is_file() and not f.is_symlink():
                    zf.write(f, f"{top}/{f.relative_to(source).as_posix()}")
        os.replace(tmp, dest)
    finally:
        if tmp.exists():
            tmp.unlink()


def export_zip(job: dbm.JobRecord, fmt: str, session_path: str | None = None) -> Path:
    """The zip of the job's twin exported as ``fmt`` (made now, or reused), inside the
    job's folder: ``export/job-<id>-<fmt>.zip`` of ``export/<fmt>/``, whose files it
    holds under one folder, ``job-<id>-<fmt>/``.

    Args:
        job: a finished replay or diagnose job.
        fmt: one of :data:`EXPORT_FORMATS`.
        session_path: the folder of the job's session as the database has it (used when
            it holds a session; else the one the run names).

    Raises:
        Invalid: an unknown format, or the run cannot be exported (the
            :class:`TissueTwinError`'s message, e.g. a diagnosis without a Young's modulus).
        Conflict: not a finished replay or diagnose job, its folder is gone, or the export
            failed for another reason (the message says which).
    """
    folder = _check(job, fmt)
    name = zip_name(job, fmt)
    dest = folder / EXPORT_DIR / name
    with _lock(folder, fmt):
        if dest.is_file() and (folder / EXPORT_DIR / fmt / "twin.json").is_file():
            return dest
        try:
            source = _export_folder(job, folder, fmt, session_path)
            _zip(source, dest, name.removesuffix(".zip"))
        except TissueTwinError as exc:
            raise Invalid(f"job {job.id} cannot be exported as {fmt}: {exc}") from exc
        except Exception as exc:  # noqa: BLE001 - the service stays up; the client gets the reason
            log.exception("export of job %s as %s failed", job.id, fmt)
            raise Conflict(f"export of job {job.id} as {fmt} failed: {type(exc).__name__}: {exc}") from exc
    return dest


def export_job(db: DB, job_id: int, fmt: str) -> Path:
    """:func:`export_zip` of job ``job_id``, with the folder of its session as the
    database has it (a job whose session was forgotten uses the path its run names).

    Raises:
        NotFound: no such job. Invalid, Conflict: as :func:`export_zip`.
    """
    job = get_job(db, job_id)
    rec = db.get(dbm.SessionRecord, job.session_id) if job.session_id is not None else None
    return export_zip(job, fmt, rec.path if rec is not None else None)
