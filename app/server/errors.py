"""Domain errors of the job service, and their mapping to HTTP, in one place."""

from __future__ import annotations

from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse
from pydantic import ValidationError

from core.errors import TissueTwinError

__all__ = ["AppError", "NotFound", "Conflict", "Invalid", "TooLarge", "install_error_handlers"]


class AppError(Exception):
    """Base of the service's own errors; ``status`` is the HTTP status it maps to."""

    status = 400

    def __init__(self, detail: str):
        self.detail = detail
        super().__init__(detail)


class NotFound(AppError):
    """No such session, job, artifact or run."""

    status = 404


class Conflict(AppError):
    """The request contradicts the current state (a final job cannot be cancelled, ...)."""

    status = 409


class Invalid(AppError):
    """Semantically bad input the schema could not catch (a folder that is not a session, ...)."""

    status = 422


class TooLarge(AppError):
    """An upload over the size limit."""

    status = 413


def install_error_handlers(app: FastAPI) -> None:
    """Map :class:`AppError` to its status, every ``core`` :class:`TissueTwinError`
    (bad session, failed registration, bad model parameters) and pydantic
    ``ValidationError`` (job parameters) to 422 with the message."""

    @app.exception_handler(AppError)
    async def _app_error(_request: Request, exc: AppError):
        return JSONResponse(status_code=exc.status, content={"detail": exc.detail})

    @app.exception_handler(TissueTwinError)
    async def _domain_error(_request: Request, exc: TissueTwinError):
        return JSONResponse(status_code=422, content={"detail": str(exc), "type": type(exc).__name__})

    @app.exception_handler(ValidationError)
    async def _validation(_request: Request, exc: ValidationError):
        # job parameters are validated against the job type's model inside the service
        return JSONResponse(status_code=422, content={"detail": exc.errors(include_url=False, include_context=False)})
