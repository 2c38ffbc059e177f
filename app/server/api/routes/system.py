"""/api/health and /api/config."""

from __future__ import annotations

from fastapi import APIRouter, Request

from app.server.api.deps import SettingsDep, ViewerDep
from app.server.api.schemas import errors

router = APIRouter(prefix="/api", tags=["system"])


@router.get("/health", responses=errors())
def health():
    return {"status": "ok"}


@router.get("/config", responses=errors())
def config(request: Request, settings: SettingsDep, viewer: ViewerDep):
    """What the dashboard needs: the viewer's port (same host as the dashboard) and limits."""
    return {
        "viewer_port": viewer.port if viewer is not None else None,
        "max_upload_bytes": settings.max_upload_bytes,
        "scheduler": settings.scheduler or "local cluster",
        "workers": settings.workers,
    }
