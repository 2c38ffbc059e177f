"""Sessions: register a folder, unpack an uploaded zip safely, describe one.

What registration checks (upload and ``POST /api/sessions`` alike), before anything is
stored: the folder is a real directory inside the allowed roots (``Settings.session_roots``,
after resolving ``..`` and symlinks); no symlink inside it leads out of it; it reads as a
session with ``core.io.read_session(check_clouds=True)`` (every CSV, and every PLY's
header and size: a truncated cloud anywhere is refused); the reference cloud and the
first, middle and last cloud of each sequence parse and are in metres (all of them would
mean reading every point of a long session); ``phantom.stl`` and
``calibration/picked.json`` parse when present; it lists at least one sequence. Errors
name the file and the problem; a refused folder leaves the database as it was.
"""

from __future__ import annotations

import os
import shutil
import stat
import uuid
import zipfile
import zlib
from pathlib import Path, PurePosixPath
from typing import BinaryIO

from sqlalchemy import select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session as DB

from app.server import db as dbm
from app.server.errors import Conflict, Forbidden, Invalid, NotFound, TooLarge
from app.server.settings import Settings

__all__ = ["list_sessions", "get_session", "register_folder", "check_session", "upload_zip", "describe",
           "unregister", "safe_extract", "MAX_ZIP_MEMBERS"]

MAX_ZIP_MEMBERS = 200_000
"""Most entries an uploaded zip may hold (a paper-scale session has ~22k files)."""


def list_sessions(db: DB) -> list[dbm.SessionRecord]:
    return list(db.scalars(select(dbm.SessionRecord).order_by(dbm.SessionRecord.id)))


def get_session(db: DB, session_id: int) -> dbm.SessionRecord:
    """Raises NotFound (also for ids no database column can hold)."""
    rec = db.get(dbm.SessionRecord, session_id) if dbm.valid_id(session_id) else None
    if rec is None:
        raise NotFound(f"no session with id {session_id}")
    return rec


def _escaping_symlink(root: Path) -> Path | None:
    """The first symlink under ``root`` (files and folders, not followed) whose target
    resolves outside ``root``, or None."""
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            if p.is_symlink() and not p.resolve().is_relative_to(root):
                return p
    return None


def check_session(folder: Path):
    """Validate a session folder for registration (see the module docstring).

    Args:
        folder: an absolute, resolved directory.

    Returns:
        the ``core.io.Session``.

    Raises:
        SessionFormatError (and its subclasses MissingFileError, PlyError, ColumnError,
        TimestampError, UnitsError): the file and the problem; also for a symlink leading
        out of the folder and a session without sequences.
        Invalid: the folder cannot be read (permissions).
    """
    from core.errors import SessionFormatError
    from core.io import read_picked, read_session

    try:
        link = _escaping_symlink(folder)
        if link is not None:
            raise SessionFormatError(link, "is a symlink leading out of the session folder; copy the data in instead")
        session = read_session(folder, check_clouds=True)
        if not session.sequences:
            raise SessionFormatError(folder / "session.json", "lists no sequences; a session needs at least one")
        session.reference_cloud()  # parse, finite points, metres
        for seq in session.sequences.values():
            for i in sorted({0, len(seq) // 2, len(seq) - 1}):  # first, middle, last: a units switch mid-recording
                seq.cloud(i)
        session.phantom_mesh()
        read_picked(folder)
    except PermissionError as exc:
        raise Invalid(f"{exc.filename or folder}: cannot be read by the server ({exc.strerror})") from exc
    return session


def _resolve_folder(path: str) -> Path:
    try:
        folder = Path(path).expanduser().resolve()
        is_dir = folder.is_dir()
    except (OSError, ValueError, RuntimeError) as exc:  # NUL byte, name too long, unknown ~user, loops
        raise Invalid(f"{path!r}: not a usable path ({exc})") from exc
    if not is_dir:
        raise Invalid(f"{path}: not a directory")
    return folder


def _check_allowed(folder: Path, settings: Settings | None) -> None:
    if settings is None or not settings.session_roots:
        return
    roots = [Path(r).expanduser().resolve() for r in settings.session_roots]
    roots += [settings.sessions_dir.resolve(), settings.jobs_dir.resolve()]
    if not any(folder.is_relative_to(r) for r in roots):
        raise Forbidden(f"{folder}: outside the folders sessions may be registered from "
                        f"({', '.join(str(r) for r in roots[:-2])})")


def register_folder(db: DB, path: str, name: str | None = None, source: str = "registered",
                    settings: Settings | None = None) -> dbm.SessionRecord:
    """Register an existing session folder after :func:`check_session`.

    Args:
        path: the folder on the server (``~``, ``..`` and symlinks are resolved first).
        name: display name (default: the folder's name).
        source: ``registered``, ``uploaded`` or ``generated``.
        settings: its ``session_roots`` restrict where folders may be (None: anywhere).

    Raises:
        Invalid: not a usable path or not a directory. Forbidden: outside the allowed
        roots. SessionFormatError: not a valid session (the file and the problem).
        Conflict: the folder is registered already.
    """
    folder = _resolve_folder(path)
    _check_allowed(folder, settings)
    check_session(folder)
    if db.scalar(select(dbm.SessionRecord).where(dbm.SessionRecord.path == str(folder))) is not None:
        raise Conflict(f"{folder} is registered already")
    rec = dbm.SessionRecord(name=name or folder.name, path=str(folder), source=source)
    db.add(rec)
    try:
        db.commit()
    except IntegrityError as exc:  # the same folder registered concurrently
        db.rollback()
        raise Conflict(f"{folder} is registered already") from exc
    return rec


def _unsafe(name: str) -> bool:
    parts = PurePosixPath(name.replace("\\", "/")).parts
    return (not name or "\x00" in name or name.startswith(("/", "\\")) or ".." in parts
            or (bool(parts) and ":" in parts[0]))


def safe_extract(archive: Path, dest: Path, max_bytes: int, max_members: int = MAX_ZIP_MEMBERS) -> None:
    """Extract a zip into ``dest``, refusing zip-slip, zip bombs and malformed archives.

    Everything is checked on the central directory before the first byte is written;
    the declared sizes bound what is written (``zipfile`` stops at a member's declared
    size and checks its CRC).

    Raises:
        Invalid: not a zip; more than ``max_members`` entries; a member with an absolute
            path, ``..``, a drive letter, a NUL byte or a symlink (anything that would land
            outside ``dest``); an encrypted member; a name used twice or both as a file and
            a folder; a member that cannot be decompressed (bad CRC, truncated data,
            unsupported compression).
        TooLarge: the members' total uncompressed size exceeds ``max_bytes``.
    """
    dest = dest.resolve()
    try:
        zf = zipfile.ZipFile(archive)
    except (zipfile.BadZipFile, zipfile.LargeZipFile, EOFError, ValueError) as exc:
        raise Invalid(f"not a zip file: {exc}") from exc
    with zf:
        infos = zf.infolist()
        if len(infos) > max_members:
            raise Invalid(f"the zip holds {len(infos)} entries, more than {max_members}")
        total = 0
        files: set[Path] = set()
        folders: set[Path] = set()
        for info in infos:
            name = info.filename
            if _unsafe(name):
                raise Invalid(f"unsafe path in zip: {name!r}")
            if stat.S_ISLNK(info.external_attr >> 16):
                raise Invalid(f"symlink in zip: {name!r}")
            if info.flag_bits & 0x1:
                raise Invalid(f"encrypted member in zip: {name!r}")
            target = (dest / name).resolve()
            if not target.is_relative_to(dest) or target == dest and not info.is_dir():
                raise Invalid(f"unsafe path in zip: {name!r}")
            if info.is_dir():
                folders.add(target)
            elif target in files:
                raise Invalid(f"the zip holds {name!r} twice")
            else:
                files.add(target)
            folders.update(p for p in target.parents if p.is_relative_to(dest) and p != dest)
            total += info.file_size
            if total > max_bytes:
                raise TooLarge(f"zip expands to more than {max_bytes} bytes")
        clash = files & folders
        if clash:
            raise Invalid(f"the zip uses {sorted(str(p.relative_to(dest)) for p in clash)[0]!r} both as a file and a folder")
        for info in infos:
            target = (dest / info.filename).resolve()
            if info.is_dir():
                target.mkdir(parents=True, exist_ok=True)
                continue
            target.parent.mkdir(parents=True, exist_ok=True)
            try:
                with zf.open(info) as src, target.open("wb") as out:
                    shutil.copyfileobj(src, out, 1 << 20)
            except (zipfile.BadZipFile, zlib.error, EOFError, NotImplementedError, RuntimeError) as exc:
                raise Invalid(f"cannot unpack {info.filename!r} from the zip: {exc}") from exc


def upload_zip(db: DB, settings: Settings, stream: BinaryIO, filename: str, name: str | None) -> dbm.SessionRecord:
    """Store an uploaded zipped session under ``<data>/sessions/`` and register it.

    The zip holds ``session.json`` at its top or inside one top-level folder. The HTTP
    body was already cut off at ``settings.max_upload_bytes`` (plus multipart overhead)
    while it streamed in (``create_app``); the copy here counts again.

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
        rec = register_folder(db, str(root), name=clean, source="uploaded", settings=settings)
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
    from core.io import read_session

    s = read_session(rec.path)
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
