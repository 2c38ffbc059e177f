"""What a running job sees: progress reporting, cancellation, its folders, where trials run.

A job function runs on a Dask worker (or in-process). It reports through a
:class:`Channel`: on Dask, :class:`DaskChannel` puts ``(kind, payload)`` items on a
``distributed.Queue`` that the server drains into the database, and reads the
cancellation flag from a ``distributed.Event`` that the server sets. Progress calls
are throttled; every call that passes the throttle also checks the flag and raises
:class:`JobCancelled`, so a job stops at its next progress report.
"""

from __future__ import annotations

import re
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

__all__ = ["JobCancelled", "WorkerCrashed", "Channel", "LocalChannel", "DaskChannel", "JobContext"]


def _shape(message: str) -> str:
    return re.sub(r"\d+", "#", message)


class JobCancelled(Exception):
    """Raised inside a job (from its progress callback) when the user cancelled it."""


class WorkerCrashed(Exception):
    """The worker that ran this job died; the job is not retried (it may crash again)."""


class Channel:
    """Transport of a job's reports to the server."""

    def send(self, kind: str, payload: Any) -> None:
        raise NotImplementedError

    def cancelled(self) -> bool:
        raise NotImplementedError


@dataclass
class LocalChannel(Channel):
    """In-process channel: calls ``on_report(kind, payload)``; ``cancel_flag()`` says stop."""

    on_report: Callable[[str, Any], None] = lambda kind, payload: None
    cancel_flag: Callable[[], bool] = lambda: False

    def send(self, kind, payload):
        self.on_report(kind, payload)

    def cancelled(self):
        return self.cancel_flag()


class DaskChannel(Channel):
    """Channel over the scheduler: a ``distributed.Queue`` for reports, an ``Event`` for cancel.

    Args:
        token: unique name prefix of this job run (``tt-<job id>-<uuid>``).
    """

    def __init__(self, token: str, client=None):
        from distributed import Event, Queue

        self.queue = Queue(f"{token}-reports", client=client)
        self.cancel_event = Event(f"{token}-cancel", client=client)
        self.started_event = Event(f"{token}-started", client=client)

    def send(self, kind, payload):
        self.queue.put((kind, payload))

    def cancelled(self):
        return self.cancel_event.is_set()


@dataclass
class JobContext:
    """Handed to a job function.

    Attributes:
        job_id: database id of the job.
        artifact_dir: the job's own folder; everything it writes goes here (downloadable).
        session_path: the session folder for session jobs, else None.
        picked: accepted picked point pairs of the session's camera calibration,
            ``(points_camera (K, 3), points_phantom (K, 3))`` m, or None (automatic).
        channel: where reports go.
        interval: least time between two progress reports, s.
    """

    job_id: int
    artifact_dir: Path
    channel: Channel
    session_path: Path | None = None
    picked: tuple[np.ndarray, np.ndarray] | None = None
    interval: float = 0.25
    _last: float = field(default=-1e9, repr=False)
    _last_message: str = field(default="", repr=False)

    def check_cancelled(self) -> None:
        """Raise :class:`JobCancelled` if the user asked to cancel."""
        if self.channel.cancelled():
            raise JobCancelled("cancelled by the user")

    def progress(self, fraction: float, message: str = "") -> None:
        """Report ``fraction`` in [0, 1] done with ``message``; throttled to one report per
        ``interval`` (a new message always goes through). Raises :class:`JobCancelled`."""
        now = time.monotonic()
        if now - self._last < self.interval and message == self._last_message:
            return
        self._last = now
        self.check_cancelled()
        fraction = float(min(max(fraction, 0.0), 1.0))
        self.channel.send("progress", (fraction, str(message)))
        if message and _shape(message) != _shape(self._last_message):  # "step 5/90" -> one log line per stage
            self.channel.send("log", str(message))
        self._last_message = message

    def log(self, message: str) -> None:
        """Append a line to the job's log."""
        self.channel.send("log", str(message))

    def scaled(self, lo: float, hi: float) -> Callable[[float, str], None]:
        """A ``callback(fraction, message)`` mapping [0, 1] onto [lo, hi] of this job."""
        return lambda f, msg="": self.progress(lo + (hi - lo) * float(f), msg)

    @contextmanager
    def executor(self) -> Iterator[Any]:
        """Where the job's trials run: on the job's own Dask cluster when the job runs on a
        worker (``worker_client``: the job's thread secedes while its trials run), else
        in this process. Yields a ``core.identification.Executor``."""
        from core.identification import DaskExecutor, SerialExecutor

        try:
            from distributed import get_worker, worker_client

            get_worker()
        except (ImportError, ValueError):
            yield SerialExecutor()
            return
        with worker_client() as client:
            yield DaskExecutor(client)
