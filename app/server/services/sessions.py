"""Sessions: register a folder, unpack an uploaded zip safely, describe one."""

from __future__ import annotations

import shutil
import stat
import uuid
import zipfile
from pathlib import Path, PurePosixPath
from typing import BinaryIO

from sqlalchemy import select
from sqlalchemy.orm import Session as DB

from app.server import db as dbm
from app.server.errors import Conflict, Invalid, NotFound, TooLarge
from app.server.settings import Settings

__all__ = ["list_sessions", "get_session", "register_folder", "upload_zip", "describe", "unregister", "safe_extract"]


def list_sessions(db: DB) -> list[dbm.SessionRecord]:
    return list(db.scalars(select(dbm.SessionRecord).order_by(dbm.SessionRecord.id)))


def get_session(db: DB, session_id: int) -> dbm.SessionRecord:
    """Raises NotFound."""
    rec = db.get(dbm.SessionRecord, session_id)
    if rec is None:
        raise NotFound(f"no session with id {session_id}")
    return rec


def _validate(path: Path):
    from core.io import read_session

    return read_session(path)  # SessionFormatError -> 422 with the file and the problem


def register_folder(db: DB, path: str, name: str | None = None, source: str = "registered") -> dbm.SessionRecord:
    """Register an existing session folder (validated with ``core.io.read_session``).

    Raises:
        Invalid: not a directory. SessionFormatError: not a valid session.
        Conflict: the folder is registered already.
    """
    folder = Path(path).expanduser().resolve()
    if not folder.is_dir():
        raise Invalid(f"{path}: not a directory")
    _validate(folder)
    if db.scalar(select(dbm.SessionRecord).where(dbm.SessionRecord.path == str(folder))) is not None:
        raise Conflict(f"{folder} is registered already")
    rec = dbm.SessionRecord(name=name or folder.name, path=str(folder), source=source)
    db.add(rec)
    db.commit()
    return rec


def safe_extract(archive: Path, dest: Path, max_bytes: int) -> None:
    """Extract a zip into ``dest``, refusing zip-slip and zip bombs.

    Raises:
        Invalid: not a zip; a member with an absolute path, ``..``, a drive letter or a
            symlink (anything that would land outside ``dest``).
        TooLarge: the members' total uncompressed size exceeds ``max_bytes``.
    """
    dest = dest.resolve()
    try:
        zf = zipfile.ZipFile(archive)
    except zipfile.BadZipFile as exc:
        raise Invalid(f"not a zip file: {exc}") from exc
    with zf:
        total = 0
        for info in zf.infolist():
            name = info.filename
            parts = PurePosixPath(name.replace("\\", "/")).parts
            if name.startswith(("/", "\\")) or ".." in parts or (parts and ":" in parts[0]):
                raise Invalid(f"unsafe path in zip: {name!r}")
            if stat.S_ISLNK(info.external_attr >> 16):
                raise Invalid(f"symlink in zip: {name!r}")
            target = (dest / name).resolve()
            if not target.is_relative_to(dest):
                raise Invalid(f"unsafe path in zip: {name!r}")
            total += info.file_size
            if total > max_bytes:
                raise TooLarge(f"zip expands to more than {max_bytes} bytes")
        for info in zf.infolist():
            target = (dest / info.filename).resolve()
            if info.is_dir():
                target.mkdir(parents=True, exist_ok=True)
                continue
            target.parent.mkdir(parents=True, exist_ok=True)
            with zf.open(info) as src, target.open("wb") as out:
                shutil.copyfileobj(src, out, 1 << 20)


def upload_zip(db: DB, settings: Settings, stream: BinaryIO, filename: str, name: str | None) -> dbm.SessionRecord:
    """Store an uploaded zipped session under ``<data>/sessions/`` and register it.

    The zip holds ``session.json`` at its top or inside one top-level folder.

    Raises:
        TooLarge, Invalid: see :func:`safe_extract`; no ``session.json``.
        SessionFormatError: the unpacked folder is not a valid session (nothing is kept).
    """
    settings.sessions_dir.mkdir(parents=True, exist_ok=True)
    stem = Path(filename or "upload").stem
    clean = "".join(c if c.isalnum() or c in "-_." else "-" for c in (name or stem))[:64].strip(".-") or "session"
    dest = settings.sessions_dir / f"{clean}-{uuid.uuid4().hex[:8]}"
    tmp = dest.with_suffix(".zip.part")
    try:
        size = 0
        with tmp.open("wb") as out:
            while chunk := stream.read(1 << 20):
                size += len(chunk)
                if size > settings.max_upload_bytes:
                    raise TooLarge(f"upload larger than {settings.max_upload_bytes} bytes")
                out.write(chunk)
        dest.mkdir(parents=True)
        safe_extract(tmp, dest, settings.max_upload_bytes)
        root = dest
        if not (root / "session.json").exists():
            subs = [p for p in dest.iterdir() if p.is_dir() and (p / "session.json").exists()]
            if len(subs) != 1:
                raise Invalid("the zip has no session.json at its top or in one top-level folder")
            root = subs[0]
        rec = register_folder(db, str(root), name=clean, source="uploaded")
    except BaseException:
        shutil.rmtree(dest, ignore_errors=True)
        raise
    finally:
        tmp.unlink(missing_ok=True)
    return rec


def describe(rec: dbm.SessionRecord) -> dict:
    """A session's sequences, roles, frame counts and calibration state (reads the folder).

    Raises:
        SessionFormatError: the folder changed and is no longer valid.
    """
    from app.server.services.calibration import load_calibration

    s = _validate(Path(rec.path))
    return {
        "phantom_size": [float(v) for v in s.meta.phantom.size],
        "probe_radius": float(s.meta.probe.radius),
        "has_force": bool(s.has_force),
        "has_reference": s.reference_path is not None,
        "sequences": [{"name": q.name, "role": q.role, "frames": len(q)} for q in s.sequences.values()],
        "calibration": load_calibration(Path(rec.path)),
    }


def unregister(db: DB, settings: Settings, session_id: int) -> None:
    """Forget a session; an uploaded one's files (under ``<data>/sessions``) are deleted too."""
    rec = get_session(db, session_id)
    path = Path(rec.path)
    db.delete(rec)
    db.commit()
    base = settings.sessions_dir.resolve()
    if rec.source == "uploaded" and path.resolve().is_relative_to(base):
        top = base / path.resolve().relative_to(base).parts[0]
        shutil.rmtree(top, ignore_errors=True)
