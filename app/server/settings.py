"""Settings of the workbench, from arguments or the environment (pydantic-settings)."""

from __future__ import annotations

from pathlib import Path

from pydantic import AliasChoices, Field
from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    """Where data lives and how jobs run.

    Every field can come from the environment as ``TISSUETWIN_<FIELD>``; the database
    URL also as plain ``DATABASE_URL`` and the scheduler as ``TISSUETWIN_SCHEDULER``
    (the same variable the CLI's sweeps read).
    """

    model_config = SettingsConfigDict(env_prefix="TISSUETWIN_", extra="ignore")

    data_dir: Path = Field(default=Path("data"), validation_alias=AliasChoices("TISSUETWIN_DATA", "data_dir"))
    """Data directory: ``workbench.db`` (SQLite), ``sessions/`` (uploads), ``jobs/<id>/`` (artifacts)."""
    database_url: str | None = Field(default=None, validation_alias=AliasChoices("DATABASE_URL", "database_url"))
    """SQLAlchemy URL, e.g. ``postgresql+psycopg://user:pw@host/db``; default SQLite in ``data_dir``."""
    scheduler: str | None = None
    """Address of an existing Dask scheduler (``tcp://host:8786``); None starts a local cluster."""
    workers: int = 2
    """Worker processes of the local cluster (one thread each)."""
    viewer: bool = True
    """Start the viser viewer."""
    viewer_host: str = "127.0.0.1"
    viewer_port: int = 8081
    """Port of the viser viewer (its own server; the dashboard embeds it in an iframe)."""
    max_upload_bytes: int = Field(512 * 1024 * 1024, ge=1024)
    """Largest accepted zip upload (compressed and uncompressed), bytes. Enforced while
    the request streams in (a larger body is cut off with 413 before it is stored)."""
    max_body_bytes: int = Field(1024 * 1024, ge=1024)
    """Largest request body of every other route (JSON), bytes (413 beyond)."""
    session_roots: list[Path] = Field(default_factory=list)
    """Folders under which ``POST /api/sessions`` may register session folders (after
    resolving ``..`` and symlinks); empty: any folder the server can read. Uploaded and
    generated sessions live under ``data_dir`` and are always allowed. From the
    environment as a JSON list: ``TISSUETWIN_SESSION_ROOTS='["/lab/sessions"]'``."""
    progress_interval: float = 0.25
    """Least time between two progress reports of a job, s (the cancel flag is checked as often)."""

    @property
    def url(self) -> str:
        """The effective database URL."""
        if self.database_url:
            return self.database_url
        return f"sqlite:///{(Path(self.data_dir) / 'workbench.db').resolve()}"

    @property
    def sessions_dir(self) -> Path:
        """Uploaded sessions, one folder each."""
        return Path(self.data_dir) / "sessions"

    @property
    def jobs_dir(self) -> Path:
        """Job artifacts, ``jobs/<id>/``; generated sessions live in their job's folder."""
        return Path(self.data_dir) / "jobs"
