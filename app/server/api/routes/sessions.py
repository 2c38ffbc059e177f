"""/api/sessions: register, upload, inspect, calibrate (picked ICP)."""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter, File, Form, Request, UploadFile

from app.server.api.deps import DB, SettingsDep
from app.server.api.schemas import PickedPairs, SessionDetail, SessionOut, SessionRegister
from app.server.errors import TooLarge
from app.server.services import calibration as cal
from app.server.services import sessions as svc

router = APIRouter(prefix="/api/sessions", tags=["sessions"])


@router.get("", response_model=list[SessionOut])
def list_sessions(db: DB):
    return svc.list_sessions(db)


@router.post("", response_model=SessionOut, status_code=201)
def register_session(body: SessionRegister, db: DB):
    """Register a session folder that exists on the server (validated)."""
    return svc.register_folder(db, body.path, body.name)


@router.post("/upload", response_model=SessionOut, status_code=201)
def upload_session(request: Request, db: DB, settings: SettingsDep, file: UploadFile = File(...), name: str | None = Form(None)):
    """Upload a zipped session folder (size-limited; zip-slip and symlinks refused)."""
    length = request.headers.get("content-length")
    if length and length.isdigit() and int(length) > settings.max_upload_bytes + 1_000_000:
        raise TooLarge(f"upload larger than {settings.max_upload_bytes} bytes")
    return svc.upload_zip(db, settings, file.file, file.filename or "upload.zip", name)


@router.get("/{session_id}", response_model=SessionDetail)
def get_session(session_id: int, db: DB):
    rec = svc.get_session(db, session_id)
    return SessionDetail.model_validate({**SessionOut.model_validate(rec).model_dump(), "info": svc.describe(rec)})


@router.delete("/{session_id}", status_code=204)
def delete_session(session_id: int, db: DB, settings: SettingsDep):
    """Forget a session (an uploaded one's files are deleted; a registered folder is left)."""
    svc.unregister(db, settings, session_id)


@router.get("/{session_id}/calibration")
def get_calibration(session_id: int, db: DB):
    """The accepted picked calibration (``calibration/picked.json``), or ``{"picked": null}``."""
    rec = svc.get_session(db, session_id)
    return {"picked": cal.load_calibration(Path(rec.path))}


@router.post("/{session_id}/calibration/icp")
def preview_calibration(session_id: int, body: PickedPairs, db: DB):
    """Kabsch on the picked pairs, then ICP: transforms and residuals, nothing saved."""
    rec = svc.get_session(db, session_id)
    return cal.preview(rec.path, body.points_camera, body.points_phantom)


@router.put("/{session_id}/calibration")
def accept_calibration(session_id: int, body: PickedPairs, db: DB):
    """Accept the picks: ICP again, then save ``calibration/picked.json`` in the session."""
    rec = svc.get_session(db, session_id)
    return {"picked": cal.accept(rec.path, body.points_camera, body.points_phantom)}


@router.delete("/{session_id}/calibration")
def clear_calibration(session_id: int, db: DB):
    """Back to automatic ICP initialisation."""
    rec = svc.get_session(db, session_id)
    return {"removed": cal.clear(rec.path)}
