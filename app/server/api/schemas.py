"""Request and response models of the API (pydantic, the web boundary only)."""

from __future__ import annotations

import datetime as dt
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

Point = list[float]


class SessionRegister(BaseModel):
    path: str = Field(description="a session folder on the server's file system")
    name: str | None = None


class SessionOut(BaseModel):
    model_config = ConfigDict(from_attributes=True)

    id: int
    name: str
    path: str
    source: str
    created_at: dt.datetime


class SessionDetail(SessionOut):
    info: dict[str, Any]


class PickedPairs(BaseModel):
    points_camera: list[Point] = Field(min_length=3, description="K >= 3 points on the reference cloud, m, camera frame")
    points_phantom: list[Point] = Field(min_length=3, description="the matching K points on the rest surface, m, phantom frame")


class JobCreate(BaseModel):
    type: str = Field(description="a job type name, see GET /api/job-types")
    params: dict[str, Any] = Field(default_factory=dict)


class JobOut(BaseModel):
    model_config = ConfigDict(from_attributes=True)

    id: int
    type: str
    params: dict[str, Any]
    session_id: int | None
    status: str
    progress: float
    message: str
    result: dict[str, Any] | None
    error: str | None
    cancel_requested: bool
    created_at: dt.datetime
    started_at: dt.datetime | None
    finished_at: dt.datetime | None


class JobDetail(JobOut):
    log: str
    traceback: str | None


class Artifact(BaseModel):
    path: str
    size: int


class JobTypeOut(BaseModel):
    name: str
    title: str
    needs_session: bool
    params_schema: dict[str, Any]


class ViewerShow(BaseModel):
    job_id: int
    sequence: str | None = None


class ViewerFrame(BaseModel):
    frame: int = Field(ge=0)


class ViewerIcp(BaseModel):
    session_id: int
