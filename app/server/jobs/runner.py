"""Run jobs on Dask and keep the database in step with them.

* Submission: one Dask task per job (:func:`execute_job`), on a local cluster of worker
  processes (default) or an existing scheduler. Jobs that run trials (sweep, fit) submit
  them to the same cluster from inside the task (``worker_client``).
* Progress: the task puts ``(kind, payload)`` on a ``distributed.Queue``; one monitor
  thread per job drains it into the job's row (progress, message, log).
* Cancel: the server sets a ``distributed.Event``; the job's next progress report raises
  :class:`JobCancelled`. A job that has not started is cancelled on the scheduler.
* Worker crash: the scheduler would re-run a task whose worker died. The task sets a
  ``started`` event first; a re-run that finds it set fails at once with
  :class:`WorkerCrashed`, so a crashing job fails alone while trial tasks of other jobs
  that were on the dead worker are retried by Dask as usual. On the local cluster each
  worker runs one job task at a time (:data:`JOB_SLOT`), seceded or not, so no other job
  shares the dead worker's fate; on an existing scheduler, whose workers do not offer
  the slot, two jobs can share a worker and a crash fails both.
* Restart: a stopping server leaves its jobs ``interrupted`` (also done at start-up for
  jobs a killed server left behind, :func:`app.server.db.mark_interrupted`). On an
  external cluster, where a killed server's tasks outlive it, the new server cancels
  them through the tokens stored in their rows (:meth:`JobRunner.cancel_orphans`).
"""

from __future__ import annotations

import logging
import math
import signal
import sys
import threading
import time
import traceback as tb_module
import uuid
from concurrent.futures import CancelledError
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from sqlalchemy.orm import sessionmaker

from app.server import db as dbm
from app.server.jobs.context import DaskChannel, JobCancelled, JobContext, WorkerCrashed
from app.server.jobs.registry import Registry
from app.server.settings import Settings

__all__ = ["execute_job", "JobRunner", "quiet_client_gc", "warm_imports", "WARM_IMPORTS", "JOB_SLOT"]

log = logging.getLogger(__name__)

WARM_IMPORTS = ("core.io", "core.registration", "core.preparation", "core.simulation", "core.identification",
                "core.lab", "core.diagnosis")
"""The ``core`` packages every process running jobs imports once, in this order, at start.

Why: the job functions and the trial tasks import ``core`` lazily, and a worker runs
several of them on threads at once (a sweep secedes while its trials and the next job
run). CPython's import locks take a submodule's lock before its package's, so two
threads importing different submodules of a package that is not loaded yet can
deadlock; the import system breaks that by handing one of them the partially run
module (CI saw ``cannot import name 'Clouds' from partially initialized module
'core.preparation.prepared'`` in a sweep submitted together with eleven others).
Importing the packages in one thread before any job runs leaves nothing to race.
``core.learning`` (torch, about 90 MB) is not here: the job types that need it name it
(:attr:`app.server.jobs.registry.JobType.imports`)."""

_import_lock = threading.Lock()

JOB_SLOT = "tissuetwin_job"
"""The Dask worker resource a job task holds while it runs, one per local worker.

Why: a job that runs trials (sweep, fit, diagnose) secedes from its worker thread while
they run (``worker_client``), and a seceded task no longer counts against
``threads_per_worker``, so before 2026-12-01 a second job could start in the same worker
process. When one of them killed it (a crash, out of memory), the scheduler re-ran both,
and the innocent one failed with :class:`WorkerCrashed` by design: CI saw
``test_a_worker_crash_fails_only_its_job`` fail that way once (2026-11-30). A
resource is held until the task ends, seceded or not (``distributed``'s worker state
machine releases it on completion only), so with one slot per worker each worker process
runs at most one job task; trial tasks ask for no resource and run anywhere. The price:
at most ``Settings.workers`` jobs run at once and the rest wait ``queued`` (on two cores
a third CPU-bound job would only slow the other two)."""


def warm_imports(extra: tuple[str, ...] = ()) -> None:
    """Import :data:`WARM_IMPORTS` and ``extra`` (module names), one thread at a time.

    Idempotent and cheap once done (about 0.5 s the first time). Raises ImportError as
    ``import`` does."""
    import importlib

    with _import_lock:
        for name in WARM_IMPORTS + tuple(extra):
            importlib.import_module(name)


def quiet_client_gc() -> None:
    """Drop one known piece of shutdown noise from this process's stderr.

    A Dask worker makes its own ``Client`` when a job first talks to the scheduler
    (the job's report queue, ``worker_client`` for trials). When the cluster closes just
    as a job starts (Ctrl-C right after a submission), that client is garbage-collected
    after its event loop is gone and Python prints ``Exception ignored in: Client.__del__
    ... RuntimeError: IOLoop is closed`` (seen once in CI, in the README smoke test).
    The client was being thrown away anyway; nothing is lost. Every other unraisable
    exception still reaches the previous hook. Idempotent."""
    previous = sys.unraisablehook
    if getattr(previous, "_tissuetwin_quiet", False):
        return

    def hook(unraisable) -> None:
        if (isinstance(unraisable.exc_value, RuntimeError) and str(unraisable.exc_value) == "IOLoop is closed"
                and getattr(unraisable.object, "__qualname__", "") == "Client.__del__"):
            return
        previous(unraisable)

    hook._tissuetwin_quiet = True
    sys.unraisablehook = hook


def _quiet_worker_plugin():
    """A WorkerPlugin that runs :func:`quiet_client_gc` in each worker (also restarted ones)."""
    from distributed.diagnostics.plugin import WorkerPlugin

    class QuietShutdown(WorkerPlugin):
        name = "tissuetwin-quiet-shutdown"

        def setup(self, worker):
            quiet_client_gc()

    return QuietShutdown()


def _warm_imports_plugin():
    """A WorkerPlugin that runs :func:`warm_imports` in each worker before it runs a task
    (workers present at registration and any that join or restart later)."""
    from distributed.diagnostics.plugin import WorkerPlugin

    class WarmImports(WorkerPlugin):
        name = "tissuetwin-warm-imports"

        def setup(self, worker):
            warm_imports()

    return WarmImports()


def execute_job(token: str, job_id: int, run, params_cls, params: dict, artifact_dir: str,
                session_path: str | None, picked, interval: float, imports: tuple[str, ...] = ()) -> dict:
    """The Dask task of one job: import what it needs, validate the parameters, run,
    return the summary. ``imports``: ``core`` packages beyond :data:`WARM_IMPORTS` that the
    job type needs, imported under :func:`warm_imports`'s lock before the job runs.

    Raises:
        WorkerCrashed: this is a re-run after the worker running it died.
        JobCancelled: the user cancelled it.
        Exception: whatever the job raised (domain errors carry the reason).
    """
    import numpy as np

    channel = DaskChannel(token)
    if channel.started_event.is_set():
        raise WorkerCrashed("the worker running this job died (process crash or out of memory); not retried")
    channel.started_event.set()
    channel.send("started", time.time())
    warm_imports(imports)  # a no-op where the worker plugin already ran, bar ``imports``
    ctx = JobContext(
        job_id=job_id, artifact_dir=Path(artifact_dir), channel=channel,
        session_path=Path(session_path) if session_path else None,
        picked=None if picked is None else (np.asarray(picked[0], float), np.asarray(picked[1], float)),
        interval=interval,
    )
    ctx.artifact_dir.mkdir(parents=True, exist_ok=True)
    ctx.check_cancelled()
    return run(params_cls.model_validate(params), ctx)


@contextmanager
def _sigint_ignored():
    """Ignore SIGINT while local workers are spawned (main thread only; elsewhere a no-op).

    Ctrl-C in a terminal signals the whole foreground process group, the Dask worker
    processes included, which then print KeyboardInterrupt tracebacks while the server
    shuts them down. A process started while SIGINT is ignored inherits that, and Python
    installs its KeyboardInterrupt handler only over the default disposition.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


QUEUED_POLL = 1.0
"""Seconds between two looks at a job that has not started yet."""


def _append(text: str, line: str) -> str:
    stamp = time.strftime("%H:%M:%S")
    return f"{text}{stamp} {line}\n"


class JobRunner:
    """Owns the Dask client and one monitor thread per active job.

    Args:
        settings: scheduler address / local workers, progress interval.
        factory: SQLAlchemy session factory.
        registry: the job types.
    """

    def __init__(self, settings: Settings, factory: sessionmaker, registry: Registry):
        self.settings = settings
        self.factory = factory
        self.registry = registry
        self.client = None
        self.cluster = None
        self._futures: dict[int, Any] = {}
        self._tokens: dict[int, str] = {}
        self._threads: dict[int, threading.Thread] = {}
        self._closing = threading.Event()
        self._lock = threading.Lock()

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        """Connect to the scheduler, or start a local cluster of worker processes."""
        import dask
        from distributed import Client, LocalCluster

        from core.identification.execution import LOCAL_CLUSTER_CONFIG

        address = self.settings.scheduler
        if address:
            self.client = Client(address)
            self.client.register_plugin(_warm_imports_plugin())
            return
        # non-daemonic workers: jobs may start processes (the virtual lab's simulation pool);
        # workers that ignore Ctrl-C: the server alone handles it and closes the cluster
        # no Active Memory Manager (LOCAL_CLUSTER_CONFIG): a job's broadcast session stays on every worker
        with dask.config.set({"distributed.worker.daemon": False, **LOCAL_CLUSTER_CONFIG}), _sigint_ignored():
            self.cluster = LocalCluster(
                n_workers=self.settings.workers, threads_per_worker=1, processes=True,
                # CRITICAL: under load a worker's last heartbeat can race the scheduler's
                # shutdown on Ctrl-C and log a CommClosedError traceback at ERROR (seen in CI);
                # job errors reach the job rows through their futures, not these logs
                dashboard_address=None, silence_logs=logging.CRITICAL,
                env={"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1"},
                resources={JOB_SLOT: 1},  # one job task per worker process, seceded or not
            )
        self.client = Client(self.cluster)
        quiet_client_gc()
        self.client.register_plugin(_quiet_worker_plugin())
        self.client.register_plugin(_warm_imports_plugin())

    def close(self) -> None:
        """Stop monitoring, mark unfinished jobs interrupted, close the client and cluster."""
        self._closing.set()
        scheduler_log = logging.getLogger("distributed.scheduler")
        level = scheduler_log.level
        if self.cluster is not None:
            # the local cluster's scheduler runs in this process: while it shuts down, a job's
            # own client (a sweep's executor on a worker) can be gone when the scheduler
            # reports a finished key to it, which it logs at CRITICAL with a traceback
            # (CommClosedError, seen in CI on Ctrl-C); the jobs are marked interrupted below
            # and their errors reach the job rows through their futures, not these logs.
            # Silenced until the cluster is closed, so a later cluster in this process logs.
            scheduler_log.setLevel(logging.CRITICAL + 1)
        try:
            for t in list(self._threads.values()):
                t.join(timeout=5)
            dbm.mark_interrupted(self.factory)
            if self.client is not None:
                self.client.close()
            if self.cluster is not None:
                self.cluster.close()
        finally:
            scheduler_log.setLevel(level)

    # ------------------------------------------------------------------ jobs
    def submit(self, job: dbm.JobRecord, session_path: str | None, picked) -> None:
        """Send a queued job (already in the database) to the cluster and monitor it."""
        job_type = self.registry.get(job.type)
        assert job_type is not None, job.type
        token = f"tt-{job.id}-{uuid.uuid4().hex[:12]}"
        with self.factory.begin() as db:  # a restarted server finds it there (cancel_orphans)
            rec = db.get(dbm.JobRecord, job.id)
            if rec is not None:
                rec.dask_token = token
        future = self.client.submit(
            execute_job, token, job.id, job_type.run, job_type.params, job.params, job.artifact_dir,
            session_path, picked, self.settings.progress_interval, job_type.imports, key=f"{token}-job", pure=False,
            retries=0, resources={JOB_SLOT: 1} if self.cluster is not None else None,
        )
        with self._lock:
            self._futures[job.id] = future
            self._tokens[job.id] = token
            thread = threading.Thread(target=self._monitor, args=(job.id, token, future), name=f"job-{job.id}", daemon=True)
            self._threads[job.id] = thread
        thread.start()

    def cancel(self, job_id: int) -> None:
        """Ask a job to stop: set its cancel event; cancel it on the scheduler if not started."""
        from distributed import Event

        with self._lock:
            token, future = self._tokens.get(job_id), self._futures.get(job_id)
        if token is None:
            return
        Event(f"{token}-cancel", client=self.client).set()
        with self.factory() as db:
            job = db.get(dbm.JobRecord, job_id)
            started = job is not None and job.status == dbm.RUNNING
        if not started and future is not None:
            future.cancel()

    def cancel_orphans(self, tokens: list[str]) -> int:
        """Stop the tasks a previous server of this database left on an external cluster.

        Its jobs' cancel events lived in the dead server's memory only as references:
        the events themselves are on the scheduler, so setting them (and cancelling the
        task by its key) ends a running job at its next progress report and drops a
        queued one. A local cluster died with the server: nothing to do. Returns the
        number of tokens signalled."""
        if not tokens or self.cluster is not None or self.client is None:
            return 0
        from distributed import Event, Future

        for token in tokens:
            Event(f"{token}-cancel", client=self.client).set()
            Future(f"{token}-job", client=self.client).cancel()
        return len(tokens)

    def active(self) -> list[int]:
        with self._lock:
            return [k for k, t in self._threads.items() if t.is_alive()]

    # ------------------------------------------------------------------ monitoring
    def _apply(self, job_id: int, items: list) -> None:
        if not items:
            return
        with self.factory.begin() as db:
            job = db.get(dbm.JobRecord, job_id)
            if job is None:
                return
            for kind, payload in items:
                if kind == "started":
                    if job.status == dbm.QUEUED:
                        job.status = dbm.RUNNING
                        job.started_at = dbm.utcnow()
                        job.log = _append(job.log, "started")
                elif kind == "progress":
                    fraction = float(payload[0])
                    if math.isfinite(fraction):
                        job.progress = min(max(fraction, 0.0), 1.0)
                    job.message = str(payload[1])
                elif kind == "log":
                    job.log = _append(job.log, str(payload))

    def _finish(self, job_id: int, future) -> None:
        status = future.status
        result, error, trace = None, None, None
        if status == "finished":
            try:
                result = future.result()
                final = dbm.DONE
            except CancelledError:
                # the user's cancel reached the scheduler between the status and the result
                # (measured under load: a cancel sent while the job's "started" report was
                # still on its way, so the task was cancelled as a queued one)
                final, error = dbm.CANCELLED, "cancelled by the user"
            except Exception as exc:  # a result that cannot be unpickled
                final, error, trace = dbm.FAILED, f"{type(exc).__name__}: {exc}", tb_module.format_exc()
        elif status == "cancelled":
            final, error = dbm.CANCELLED, "cancelled by the user before it started"
        else:
            try:
                exc = future.exception()
                tb = future.traceback()
            except CancelledError:  # the same race after an "error" status
                exc, tb = JobCancelled("cancelled by the user"), None
            trace = "".join(tb_module.format_list(tb_module.extract_tb(tb))) if tb else None
            name = type(exc).__name__
            if isinstance(exc, JobCancelled) or name == "JobCancelled":
                final, error = dbm.CANCELLED, str(exc) or "cancelled by the user"
            elif isinstance(exc, WorkerCrashed) or name in ("KilledWorker", "WorkerCrashed"):
                final, error = dbm.FAILED, f"worker crashed: {exc}"
            else:
                final, error = dbm.FAILED, f"{name}: {exc}"
            if trace:
                trace = f"{trace}{name}: {exc}\n"
        register = (result or {}).pop("register_session", None) if isinstance(result, dict) else None
        with self.factory.begin() as db:
            job = db.get(dbm.JobRecord, job_id)
            if job is None:
                return
            job.status, job.result, job.error, job.traceback = final, result, error, trace
            job.finished_at = dbm.utcnow()
            if final == dbm.DONE:
                job.progress, job.message = 1.0, "done"
            job.log = _append(job.log, final + (f": {error}" if error else ""))
            if register:
                path = str(Path(register["path"]).resolve())
                rec = dbm.SessionRecord(name=register["name"], path=path, source="generated")
                db.add(rec)
                db.flush()
                job.result = {**(result or {}), "session_id": rec.id}

    def _monitor(self, job_id: int, token: str, future) -> None:
        from distributed import Queue

        queue = Queue(f"{token}-reports", client=self.client)
        started = False
        try:
            while not self._closing.is_set():
                done = future.done()
                items = queue.get(batch=True)
                started = started or any(kind == "started" for kind, _ in items)
                self._apply(job_id, items)
                if done:
                    self._finish(job_id, future)
                    break
                # a queued job reports nothing: ask the scheduler seldom (fifty queued
                # jobs at the progress interval would be 200 requests a second)
                interval = self.settings.progress_interval
                self._closing.wait(interval if started else max(interval, QUEUED_POLL))
        except Exception:  # noqa: BLE001 - a monitor must never take the server down
            log.exception("monitor of job %s failed", job_id)
            if not self._closing.is_set():
                with self.factory.begin() as db:
                    job = db.get(dbm.JobRecord, job_id)
                    if job is not None and job.status in dbm.ACTIVE:
                        job.status, job.error, job.traceback = dbm.FAILED, "lost track of the job", tb_module.format_exc()
                        job.finished_at = dbm.utcnow()
        finally:
            with self._lock:
                self._futures.pop(job_id, None)
                self._tokens.pop(job_id, None)
