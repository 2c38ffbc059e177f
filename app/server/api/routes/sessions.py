"""/api/sessions: register, upload, inspect, calibrate (picked ICP).

``upload_router`` holds the zip upload alone: ``create_app`` includes it with the upload
size limit, every other route gets the small JSON body limit.
"""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter, File, Form, UploadFile

from app.server.api.deps import DB, SettingsDep
from app.server.api.schemas import PickedPairs, SessionDetail, SessionOut, SessionRegister, errors
from app.server.services import calibration as cal
from app.server.services import sessions as svc

router = APIRouter(prefix="/api/sessions", tags=["sessions"])
upload_router = APIRouter(prefix="/api/sessions", tags=["sessions"])


@router.get("", response_model=list[SessionOut], responses=errors())
def list_sessions(db: DB):
    return svc.list_sessions(db)


@router.post("", response_model=SessionOut, status_code=201, responses=errors(403, 409))
def register_session(body: SessionRegister, db: DB, settings: SettingsDep):
    """Register a session folder that exists on the server (validated: 422 names the file
    and the problem; 403 outside the allowed roots; nothing is stored on error)."""
    return svc.register_folder(db, body.path, body.name, settings=settings)


@upload_router.post("/upload", response_model=SessionOut, status_code=201, responses=errors(409, 413))
def upload_session(db: DB, settings: SettingsDep, file: UploadFile = File(...),
                   name: str | None = Form(None, max_length=200)):
    """Upload a zipped session folder (size-limited while it streams in; zip-slip,
    symlinks and zip bombs refused; validated like a registered folder)."""
    return svc.upload_zip(db, settings, file.file, file.filename or "upload.zip", name)


@router.get("/{session_id}", response_model=SessionDetail, responses=errors(404))
def get_session(session_id: int, db: DB):
    rec = svc.get_session(db, session_id)
    return SessionDetail.model_validate({**SessionOut.model_validate(rec).model_dump(), "info": svc.describe(rec)})


@router.delete("/{session_id}", status_code=204, responses=errors(404))
def delete_session(session_id: int, db: DB, settings: SettingsDep):
    """Forget a session (an uploaded one's files are deleted; a registered folder is left)."""
    svc.unregister(db, settings, session_id)


@router.get("/{session_id}/calibration", responses=errors(404))
def get_calibration(session_id: int, db: DB):
    """The accepted picked calibration (``calibration/picked.json``), or ``{"picked": null}``."""
    rec = svc.get_session(db, session_id)
    return {"picked": cal.load_calibration(Path(rec.path))}


@router.post("/{session_id}/calibration/icp", responses=errors(404))
def preview_calibration(session_id: int, body: PickedPairs, db: DB):
    """Kabsch on the picked pairs, then ICP: transforms and residuals, nothing saved."""
    rec = svc.get_session(db, session_id)
    return cal.preview(rec.path, body.points_camera, body.points_phantom)


@router.put("/{session_id}/calibration", responses=errors(404))
def accept_calibration(session_id: int, body: PickedPairs, db: DB):
    """Accept the picks: ICP again, then save ``calibration/picked.json`` in the session."""
    rec = svc.get_session(db, session_id)
    return {"picked": cal.accept(rec.path, body.points_camera, body.points_phantom)}


@router.delete("/{session_id}/calibration", responses=errors(404))
def clear_calibration(session_id: int, db: DB):
    """Back to automatic ICP initialisation."""
    rec = svc.get_session(db, session_id)
    return {"removed": cal.clear(rec.path)}
