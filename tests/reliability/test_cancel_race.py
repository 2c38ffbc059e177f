"""A cancel that reaches the scheduler between the monitor's look at a job's status and
its result (measured under load in the fifty-submissions test: the job had reported
"started", the server had not stored it yet, so it cancelled the task as a queued one,
and the job was stored as failed with ``FutureCancelledError``). It must end cancelled."""

from __future__ import annotations

from distributed.client import FutureCancelledError

from app.server import db as dbm
from app.server.jobs.registry import Registry
from app.server.jobs.runner import JobRunner
from app.server.settings import Settings


class _RacedFuture:
    """Reports ``finished``, then finds itself cancelled when asked for its result."""

    status = "finished"

    def result(self):
        raise FutureCancelledError("tt-1-job", reason="unknown")

    def traceback(self):
        return None


class _Failed(_RacedFuture):
    status = "error"

    def exception(self):
        return ValueError("a real failure")


def _runner(tmp_path):
    factory = dbm.make_sessionmaker(dbm.make_engine(f"sqlite:///{tmp_path / 'jobs.db'}"))
    with factory.begin() as db:
        db.add(dbm.JobRecord(id=1, type="replay", params={}, status=dbm.QUEUED))
        db.add(dbm.JobRecord(id=2, type="replay", params={}, status=dbm.RUNNING))
    return JobRunner(Settings(), factory, Registry()), factory


def test_a_cancel_racing_the_result_ends_cancelled_and_a_failure_stays_failed(tmp_path):
    runner, factory = _runner(tmp_path)
    runner._finish(1, _RacedFuture())
    runner._finish(2, _Failed())
    with factory() as db:
        raced, failed = db.get(dbm.JobRecord, 1), db.get(dbm.JobRecord, 2)
        assert raced.status == dbm.CANCELLED and "cancelled" in raced.error and raced.finished_at is not None
        assert failed.status == dbm.FAILED and failed.error == "ValueError: a real failure"
