"""Persistence of sessions and jobs with SQLAlchemy 2.x (SQLite by default, PostgreSQL by URL)."""

from __future__ import annotations

import datetime as dt
from typing import Any

from sqlalchemy import JSON, DateTime, Float, ForeignKey, Integer, String, Text, create_engine, event, update
from sqlalchemy.engine import Engine
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, sessionmaker

__all__ = ["Base", "SessionRecord", "JobRecord", "ACTIVE", "FINAL", "MAX_ID", "valid_id", "make_engine", "make_sessionmaker", "mark_interrupted", "utcnow"]

#: Job statuses. ``interrupted``: the server stopped while the job was queued or running.
QUEUED, RUNNING, DONE, FAILED, CANCELLED, INTERRUPTED = "queued", "running", "done", "failed", "cancelled", "interrupted"
ACTIVE = (QUEUED, RUNNING)
FINAL = (DONE, FAILED, CANCELLED, INTERRUPTED)


MAX_ID = 2**63 - 1
"""Largest id a row can have (SQLite and PostgreSQL 64-bit integers)."""


def valid_id(value: int) -> bool:
    """True if ``value`` can be a row id; a larger int would make the driver raise."""
    return 1 <= value <= MAX_ID


def utcnow() -> dt.datetime:
    return dt.datetime.now(dt.timezone.utc)


class Base(DeclarativeBase):
    type_annotation_map = {dict[str, Any]: JSON}


class SessionRecord(Base):
    """A session folder known to the workbench (registered, uploaded or generated)."""

    __tablename__ = "sessions"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    name: Mapped[str] = mapped_column(String(200))
    path: Mapped[str] = mapped_column(String(2000), unique=True)
    source: Mapped[str] = mapped_column(String(20))  # registered | uploaded | generated
    created_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True), default=utcnow)


class JobRecord(Base):
    """One job: type, validated parameters, status, progress, log, result or failure."""

    __tablename__ = "jobs"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    type: Mapped[str] = mapped_column(String(50))
    params: Mapped[dict[str, Any]] = mapped_column(JSON)
    session_id: Mapped[int | None] = mapped_column(ForeignKey("sessions.id", ondelete="SET NULL"), nullable=True)
    status: Mapped[str] = mapped_column(String(20), default=QUEUED, index=True)
    progress: Mapped[float] = mapped_column(Float, default=0.0)
    message: Mapped[str] = mapped_column(Text, default="")
    log: Mapped[str] = mapped_column(Text, default="")
    result: Mapped[dict[str, Any] | None] = mapped_column(JSON, nullable=True)
    error: Mapped[str | None] = mapped_column(Text, nullable=True)
    traceback: Mapped[str | None] = mapped_column(Text, nullable=True)
    artifact_dir: Mapped[str] = mapped_column(String(2000), default="")
    cancel_requested: Mapped[bool] = mapped_column(default=False)
    created_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    started_at: Mapped[dt.datetime | None] = mapped_column(DateTime(timezone=True), nullable=True)
    finished_at: Mapped[dt.datetime | None] = mapped_column(DateTime(timezone=True), nullable=True)


def make_engine(url: str) -> Engine:
    """An engine for ``url``; SQLite gets WAL and a busy timeout (threads write progress)."""
    if url.startswith("sqlite"):
        engine = create_engine(url, connect_args={"check_same_thread": False, "timeout": 30})

        @event.listens_for(engine, "connect")
        def _pragmas(dbapi_conn, _record):  # pragma: no cover - exercised by every test
            cur = dbapi_conn.cursor()
            cur.execute("PRAGMA journal_mode=WAL")
            cur.execute("PRAGMA foreign_keys=ON")
            cur.close()

        return engine
    return create_engine(url, pool_pre_ping=True)


def make_sessionmaker(engine: Engine) -> sessionmaker:
    """Create the tables if missing and return a session factory (``expire_on_commit=False``)."""
    Base.metadata.create_all(engine)
    return sessionmaker(engine, expire_on_commit=False)


def mark_interrupted(factory: sessionmaker) -> int:
    """Mark the jobs a previous server left queued or running as ``interrupted``.

    Returns the number of jobs changed. Finished jobs and their artifacts are untouched.
    """
    with factory.begin() as db:
        res = db.execute(
            update(JobRecord)
            .where(JobRecord.status.in_(ACTIVE))
            .values(status=INTERRUPTED, finished_at=utcnow(), error="the server stopped while this job was queued or running")
        )
        return int(res.rowcount or 0)
