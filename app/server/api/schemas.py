"""Request and response models of the API (pydantic, the web boundary only)."""

from __future__ import annotations

import datetime as dt
import math
from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, field_validator

Point = Annotated[list[Annotated[float, Field(allow_inf_nan=False)]], Field(min_length=3, max_length=3)]
"""[x, y, z], m, finite."""

MAX_PICKS = 1000
"""Most picked point pairs in one request."""


def _storable(value: Any, where: str) -> None:
    """Raise ValueError unless ``value`` (nested dicts and lists, as ``Any`` fields hold
    them unchecked) can be stored and sent back as JSON: finite numbers, and text without
    lone surrogates (a JSON ``"\\ud800"`` escape decodes to one; UTF-8 cannot hold it)."""
    if isinstance(value, float) and not math.isfinite(value):
        raise ValueError(f"{where} is {value}: numbers must be finite")
    if isinstance(value, str):
        try:
            value.encode("utf-8")
        except UnicodeEncodeError:
            raise ValueError(f"{where} holds a lone surrogate (not valid Unicode text)") from None
    elif isinstance(value, dict):
        for k, v in value.items():
            _storable(str(k), f"{where} key")
            _storable(v, f"{where}.{k}")
    elif isinstance(value, list):
        for i, v in enumerate(value):
            _storable(v, f"{where}[{i}]")


class ErrorOut(BaseModel):
    """Every error response: a message naming the file and the problem, or pydantic's
    list of field errors (422); ``type`` is the domain error's class when there is one."""

    detail: str | list[dict[str, Any]]
    type: str | None = None


_DESCRIPTIONS = {
    400: "a request body that cannot be parsed (not UTF-8, not JSON, broken multipart)",
    403: "a path outside the folders the server may read",
    404: "no such session, job, job type, artifact or run",
    409: "contradicts the current state (registered already, job final already, viewer off)",
    413: "request body or unpacked zip over the size limit",
    422: "invalid input: the message names the file and the problem, or the fields",
}


def errors(*codes: int) -> dict[int | str, dict[str, Any]]:
    """``responses=`` for a route: the error statuses it may answer, documented in the
    OpenAPI spec with :class:`ErrorOut` (400 and 422 always: every route parses and
    validates its input)."""
    return {c: {"model": ErrorOut, "description": _DESCRIPTIONS[c]} for c in sorted({*codes, 400, 422})}


class _Request(BaseModel):
    """A request body: strict types, as the OpenAPI spec states them (JSON ``false`` is not
    an integer, ``"1"`` is not a number), and no unknown fields."""

    model_config = ConfigDict(strict=True, extra="forbid")


class SessionRegister(_Request):
    path: str = Field(min_length=1, max_length=4096, description="a session folder on the server's file system")
    name: str | None = Field(None, max_length=200)


class SessionOut(BaseModel):
    model_config = ConfigDict(from_attributes=True)

    id: int
    name: str
    path: str
    source: str
    created_at: dt.datetime


class SessionDetail(SessionOut):
    info: dict[str, Any]


class PickedPairs(_Request):
    points_camera: list[Point] = Field(min_length=3, max_length=MAX_PICKS,
                                       description="K >= 3 points on the reference cloud, m, camera frame")
    points_phantom: list[Point] = Field(min_length=3, max_length=MAX_PICKS,
                                        description="the matching K points on the rest surface, m, phantom frame")


class JobCreate(_Request):
    type: str = Field(max_length=50, description="a job type name, see GET /api/job-types")
    params: dict[str, Any] = Field(default_factory=dict, description="validated against the type's params_schema")

    @field_validator("params")
    @classmethod
    def _no_nan(cls, v: dict[str, Any]) -> dict[str, Any]:
        # JSON has no NaN, but Python's parser accepts it; a stored NaN would break every listing
        _storable(v, "params")
        return v


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


ViewerTab = Annotated[str | None, Field(
    pattern=r"^[A-Za-z0-9_-]{1,64}$",
    description="the dashboard tab's viewer token (its iframe's websocket path /tab/<token>): act on that "
                "viewer tab only; omitted: every open viewer tab")]


class ViewerShow(_Request):
    job_id: int
    sequence: str | None = Field(None, max_length=200)
    tab: ViewerTab = None


class ViewerFrame(_Request):
    frame: int = Field(ge=0, le=10**9)
    tab: ViewerTab = None


class ViewerPlan(_Request):
    job_id: int
    tab: ViewerTab = None


class ViewerIcp(_Request):
    session_id: int
    tab: ViewerTab = None
