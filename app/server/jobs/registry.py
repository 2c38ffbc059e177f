"""The registry of job types: one small entry per type (a pydantic model + a function)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

from pydantic import BaseModel

from app.server.jobs.context import JobContext

__all__ = ["JobType", "Registry"]


@dataclass(frozen=True)
class JobType:
    """A kind of job.

    Attributes:
        name: the type's name in the API (``"sweep"``).
        params: pydantic model of its parameters (validated at the web boundary; its JSON
            schema drives the dashboard's form). A ``session_id`` field makes it a session job.
        run: ``run(params, ctx) -> dict``: calls ``core`` with ``ctx.progress`` as callback,
            writes its files into ``ctx.artifact_dir`` and returns a JSON-able summary. A
            summary key ``"register_session"`` (``{"path", "name"}``) registers a new session.
            Must be a module-level function (it is pickled to a Dask worker).
        title: one line for the dashboard.
        imports: ``core`` packages the job needs beyond
            :data:`app.server.jobs.runner.WARM_IMPORTS` (``("core.learning",)``), imported
            one thread at a time before it runs (see there why).
    """

    name: str
    params: type[BaseModel]
    run: Callable[[Any, JobContext], dict]
    title: str = ""
    imports: tuple[str, ...] = ()

    @property
    def needs_session(self) -> bool:
        return "session_id" in self.params.model_fields


class Registry:
    """Job types by name."""

    def __init__(self, types: list[JobType] | None = None):
        self._types: dict[str, JobType] = {}
        for t in types or []:
            self.add(t)

    def add(self, job_type: JobType) -> None:
        if job_type.name in self._types:
            raise ValueError(f"job type {job_type.name!r} registered twice")
        self._types[job_type.name] = job_type

    def get(self, name: str) -> JobType | None:
        return self._types.get(name)

    def __iter__(self):
        return iter(self._types.values())

    def names(self) -> list[str]:
        return list(self._types)
