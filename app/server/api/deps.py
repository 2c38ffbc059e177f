"""Dependencies of the routes as ``Annotated`` aliases (full-stack-fastapi-template style)."""

from __future__ import annotations

from typing import Annotated, Any, Iterator

from fastapi import Depends, Request
from sqlalchemy.orm import Session as DBSession

from app.server.jobs.registry import Registry
from app.server.jobs.runner import JobRunner
from app.server.settings import Settings


def get_db(request: Request) -> Iterator[DBSession]:
    with request.app.state.sessionmaker() as db:
        yield db


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_runner(request: Request) -> JobRunner:
    return request.app.state.runner


def get_registry(request: Request) -> Registry:
    return request.app.state.registry


def get_viewer(request: Request) -> Any:
    return request.app.state.viewer


DB = Annotated[DBSession, Depends(get_db)]
SettingsDep = Annotated[Settings, Depends(get_settings)]
RunnerDep = Annotated[JobRunner, Depends(get_runner)]
RegistryDep = Annotated[Registry, Depends(get_registry)]
ViewerDep = Annotated[Any, Depends(get_viewer)]
