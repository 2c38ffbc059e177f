"""/api/job-types: what can be launched, with the JSON schema of each type's parameters."""

from __future__ import annotations

from fastapi import APIRouter

from app.server.api.deps import RegistryDep
from app.server.api.schemas import JobTypeOut, errors

router = APIRouter(prefix="/api/job-types", tags=["jobs"])


@router.get("", response_model=list[JobTypeOut], responses=errors())
def list_job_types(registry: RegistryDep):
    return [JobTypeOut(name=t.name, title=t.title, needs_session=t.needs_session, params_schema=t.params.model_json_schema())
            for t in registry]
