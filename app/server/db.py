"""Persistence of sessions and jobs with SQLAlchemy 2.x (SQLite by default, PostgreSQL by URL).

Both back-ends behave the same: datetimes come back timezone-aware in UTC, JSON columns
store non-finite floats as null (PostgreSQL's ``json`` rejects ``NaN``), string limits
are checked before the database sees them (SQLite ignores ``VARCHAR(n)``, PostgreSQL
refuses), and ``postgresql://`` / ``postgres://`` URLs use the psycopg 3 driver.
"""

from __future__ import annotations

import datetime as dt
import json
import math
from typing import Any

from sqlalchemy import (JSON, DateTime, Float, ForeignKey, Integer, String, Text, create_engine, event, inspect, select, text,
                        update)
from sqlalchemy.engine import Engine, make_url
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, sessionmaker, validates
from sqlalchemy.types import TypeDecorator

from app.server.errors import Invalid

__all__ = ["Base", "SessionRecord", "JobRecord", "ACTIVE", "FINAL", "UTCDateTime", "json_dumps", "normalize_url",
           "MAX_ID", "valid_id", "make_engine", "make_sessionmaker", "mark_interrupted", "active_tokens", "utcnow"]

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
    """Now, timezone-aware in UTC."""
    return dt.datetime.now(dt.timezone.utc)


class UTCDateTime(TypeDecorator):
    """A ``DateTime(timezone=True)`` column that reads back timezone-aware UTC on every
    back-end (SQLite returns naive values; PostgreSQL returns the session's time zone).

    Raises:
        ValueError: on writing a naive datetime (its time zone would be a guess).
    """

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: dt.datetime | None, dialect) -> dt.datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            raise ValueError(f"naive datetime {value.isoformat()} for a UTC column; use app.server.db.utcnow()")
        return value.astimezone(dt.timezone.utc)

    def process_result_value(self, value: dt.datetime | None, dialect) -> dt.datetime | None:
        if value is None:
            return None
        return value.replace(tzinfo=dt.timezone.utc) if value.tzinfo is None else value.astimezone(dt.timezone.utc)


def _finite(value: Any) -> Any:
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    return value


def json_dumps(value: Any) -> str:
    """The JSON columns' serializer: standard JSON with NaN and +-inf (anywhere in nested
    dicts and lists) written as null, as the API shows them.

    Raises:
        TypeError: a value JSON cannot hold (e.g. a numpy array).
    """
    return json.dumps(_finite(value), allow_nan=False)


class Base(DeclarativeBase):
    type_annotation_map = {dict[str, Any]: JSON}


def _check_length(record, key: str, value: str | None) -> str | None:
    limit = record.__table__.c[key].type.length
    if value is not None and limit is not None and len(value) > limit:
        raise Invalid(f"{record.__tablename__[:-1]} {key} is {len(value)} characters long; at most {limit} are stored")
    return value


class SessionRecord(Base):
    """A session folder known to the workbench (registered, uploaded or generated)."""

    __tablename__ = "sessions"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    name: Mapped[str] = mapped_column(String(200))
    path: Mapped[str] = mapped_column(String(2000), unique=True)
    source: Mapped[str] = mapped_column(String(20))  # registered | uploaded | generated
    created_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utcnow)

    @validates("name", "path")
    def _fits(self, key: str, value: str) -> str:
        """Raises :class:`~app.server.errors.Invalid` (422) for a name or path over its column's length."""
        return _check_length(self, key, value)


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
    dask_token: Mapped[str | None] = mapped_column(String(64), nullable=True)
    """Name prefix of the job's Dask task and events (``<token>-job``, ``<token>-cancel``):
    a restarted server cancels the task of a job its predecessor left running."""
    created_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utcnow)
    started_at: Mapped[dt.datetime | None] = mapped_column(UTCDateTime, nullable=True)
    finished_at: Mapped[dt.datetime | None] = mapped_column(UTCDateTime, nullable=True)


def normalize_url(url: str) -> str:
    """``url`` with the psycopg 3 driver for ``postgresql://`` and ``postgres://`` (SQLAlchemy
    would look for psycopg2, which is not installed); other URLs unchanged.

    Raises:
        sqlalchemy.exc.ArgumentError: not a database URL.
    """
    parsed = make_url(url)
    if parsed.drivername in ("postgresql", "postgres"):
        return parsed.set(drivername="postgresql+psycopg").render_as_string(hide_password=False)
    return url


def make_engine(url: str) -> Engine:
    """An engine for ``url``; SQLite gets WAL and a busy timeout (threads write progress).
    JSON columns are written with :func:`json_dumps` on every back-end."""
    url = normalize_url(url)
    if url.startswith("sqlite"):
        engine = create_engine(url, json_serializer=json_dumps, connect_args={"check_same_thread": False, "timeout": 30})

        @event.listens_for(engine, "connect")
        def _pragmas(dbapi_conn, _record):  # pragma: no cover - exercised by every test
            cur = dbapi_conn.cursor()
            cur.execute("PRAGMA journal_mode=WAL")
            cur.execute("PRAGMA foreign_keys=ON")
            cur.close()

        return engine
    return create_engine(url, json_serializer=json_dumps, pool_pre_ping=True)


_SCHEMA_LOCK = 0x74697373  # PostgreSQL advisory lock key of the table creation ("tiss")


def make_sessionmaker(engine: Engine) -> sessionmaker:
    """Create the tables if missing and return a session factory (``expire_on_commit=False``).

    On PostgreSQL, servers starting at once against one database take turns (an
    advisory lock): concurrent ``CREATE TABLE`` of the same table fails there.
    """
    with engine.begin() as conn:
        if conn.dialect.name == "postgresql":
            conn.execute(text("SELECT pg_advisory_xact_lock(:key)"), {"key": _SCHEMA_LOCK})
        Base.metadata.create_all(conn)
        _add_missing_columns(conn)
    return sessionmaker(engine, expire_on_commit=False)


_ADDED_COLUMNS = {"jobs": {"dask_token": "VARCHAR(64)"}}
"""Nullable columns added after the first release: ``create_all`` does not add a column
to an existing table, so a database made by an earlier version gets them here."""


def _add_missing_columns(conn) -> None:
    insp = inspect(conn)
    for table, columns in _ADDED_COLUMNS.items():
        have = {c["name"] for c in insp.get_columns(table)}
        for name, sql_type in columns.items():
            if name not in have:
                conn.execute(text(f"ALTER TABLE {table} ADD COLUMN {name} {sql_type}"))


def active_tokens(factory: sessionmaker) -> list[str]:
    """Dask tokens of the jobs a previous server left queued or running (to cancel them)."""
    with factory() as db:
        rows = db.execute(select(JobRecord.dask_token).where(JobRecord.status.in_(ACTIVE))).scalars()
        return [t for t in rows if t]


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
