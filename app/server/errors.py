"""Domain errors of the job service, and their mapping to HTTP, in one place."""

from __future__ import annotations

import json
import math
from typing import Any

from fastapi import FastAPI, Request
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import ValidationError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.middleware.body_limit import MAX_BODY_SIZE_SCOPE_KEY

from core.errors import TissueTwinError

__all__ = ["AppError", "NotFound", "Forbidden", "Conflict", "Invalid", "TooLarge", "install_error_handlers"]


class AppError(Exception):
    """Base of the service's own errors; ``status`` is the HTTP status it maps to."""

    status = 400

    def __init__(self, detail: str):
        self.detail = detail
        super().__init__(detail)


class NotFound(AppError):
    """No such session, job, artifact or run."""

    status = 404


class Forbidden(AppError):
    """A path outside what the server may read (a session folder outside the allowed roots)."""

    status = 403


class Conflict(AppError):
    """The request contradicts the current state (a final job cannot be cancelled, ...)."""

    status = 409


class Invalid(AppError):
    """Semantically bad input the schema could not catch (a folder that is not a session, ...)."""

    status = 422


class TooLarge(AppError):
    """An upload over the size limit."""

    status = 413


def _json_safe(obj: Any) -> Any:
    """``obj`` made JSON-encodable for an error body: non-finite floats (a ``NaN`` the
    client sent, echoed as the bad ``input``) become strings, lone surrogates escapes,
    anything else exotic its str."""
    if isinstance(obj, float) and not math.isfinite(obj):
        return str(obj)
    if isinstance(obj, str):  # a lone surrogate the client sent as "\\ud800": UTF-8 cannot hold it
        return obj.encode("utf-8", "backslashreplace").decode("utf-8")
    if isinstance(obj, dict):
        return {str(k): _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    if obj is None or isinstance(obj, (str, int, float, bool)):
        return obj
    try:
        return _json_safe(jsonable_encoder(obj))
    except Exception:  # noqa: BLE001 - an error body must always render
        return str(obj)


def _errors(exc: ValidationError | RequestValidationError) -> list:
    if isinstance(exc, ValidationError):
        return _json_safe(exc.errors(include_url=False, include_context=False))
    return _json_safe([{k: v for k, v in e.items() if k not in ("ctx", "url")} for e in exc.errors()])


def _too_large(limit: int | None) -> str:
    """The 413 error detail for a body over ``limit`` bytes."""
    return f"request body larger than {limit} bytes" if limit else "request body too large"


def install_error_handlers(app: FastAPI) -> None:
    """Map :class:`AppError` to its status, every ``core`` :class:`TissueTwinError`
    (bad session, failed registration, bad model parameters) and pydantic
    ``ValidationError`` (job parameters) to 422 with the message, request validation
    errors to 422 (even when the client sent ``NaN``), and a body over its limit to 413
    saying the limit. Every error body is ``{"detail": str | list, ...}`` (``api.schemas.ErrorOut``)."""

    @app.exception_handler(AppError)
    async def _app_error(_request: Request, exc: AppError):
        return JSONResponse(status_code=exc.status, content={"detail": _json_safe(exc.detail)})

    @app.exception_handler(TissueTwinError)
    async def _domain_error(_request: Request, exc: TissueTwinError):
        return JSONResponse(status_code=422, content={"detail": _json_safe(str(exc)), "type": type(exc).__name__})

    @app.exception_handler(ValidationError)
    async def _validation(_request: Request, exc: ValidationError):
        # job parameters are validated against the job type's model inside the service
        return JSONResponse(status_code=422, content={"detail": _errors(exc)})

    @app.exception_handler(RequestValidationError)
    async def _request_validation(_request: Request, exc: RequestValidationError):
        return JSONResponse(status_code=422, content={"detail": _errors(exc)})

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException):
        detail = exc.detail
        if exc.status_code == 413 and MAX_BODY_SIZE_SCOPE_KEY in request.scope:
            detail = _too_large(request.scope[MAX_BODY_SIZE_SCOPE_KEY])
        return JSONResponse(status_code=exc.status_code, content={"detail": detail}, headers=exc.headers)


class JSONTooLarge:
    """ASGI wrapper: Starlette's body-limit middleware answers a body whose announced
    Content-Length is over the limit itself, before any handler, in plain text
    ("Content Too Large"). This rewrites that one response into the documented error
    body, ``{"detail": "request body larger than N bytes"}`` (``api.schemas.ErrorOut``).
    Every other response passes through untouched."""

    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        rewriting = False

        async def send_json(message):
            nonlocal rewriting
            if message["type"] == "http.response.start" and message["status"] == 413:
                ctype = dict(message.get("headers") or []).get(b"content-type", b"")
                if ctype.startswith(b"text/plain"):
                    rewriting = True
                    return
            if rewriting and message["type"] == "http.response.body":
                body = json.dumps({"detail": _too_large(scope.get(MAX_BODY_SIZE_SCOPE_KEY))}).encode()
                await send({"type": "http.response.start", "status": 413,
                            "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]})
                await send({"type": "http.response.body", "body": body})
                return
            await send(message)

        await self.app(scope, receive, send_json)
