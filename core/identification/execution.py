"""Where trials run: in this process, or on Dask (a local cluster or an existing one).

Every trial is a pure function of (prepared data, trial parameters), and builds its
own model, so the same trials give the same numbers wherever they run. The prepared
session (calibration and cleaned clouds) is shipped to the workers once.
"""

from __future__ import annotations

import os
from contextlib import contextmanager
from typing import Any, Callable, Iterator, Sequence

__all__ = ["Executor", "SerialExecutor", "DaskExecutor", "executor", "LOCAL_CLUSTER_CONFIG"]

LOCAL_CLUSTER_CONFIG = {"distributed.scheduler.active-memory-manager.start": False}
"""Dask settings of the local clusters this project starts (:func:`executor`, the
workbench's job runner): no Active Memory Manager. Its default policy (ReduceReplicas,
every 2 s) drops all but one copy of a key, including the prepared session that
:class:`DaskExecutor` broadcasts to every worker; the scheduler then puts a map's trials on
the worker that still holds it rather than pay the transfer, and the other worker idles.
Measured (2026-11-29, 2 workers): two 0.5 s trials over a 96 MB broadcast object, 2.5 s
apart, ran on one worker 19 times in 20 (1.1 s instead of 0.54 s); in a 4 x 12 s diagnosis
two 10.7 s fine-grid trials ran one after the other (21.6 s; its joint refit with E took
43.9 s, 34.8 s with this setting). A scheduler given by address keeps its own settings: start it
with ``DASK_DISTRIBUTED__SCHEDULER__ACTIVE_MEMORY_MANAGER__START=False``."""

Progress = Callable[[int, int], None]


class Executor:
    """Runs ``fn(shared, item)`` for every item, in order of the items."""

    concurrent: bool = False
    """Whether ``map`` may be called from several threads at once and then runs their
    items side by side (Dask's client is thread-safe; the serial executor gains nothing)."""

    def map(self, fn: Callable[[Any, Any], Any], shared: Any, items: Sequence[Any], progress: Progress | None = None) -> list:
        raise NotImplementedError

    def run_everywhere(self, fn: Callable[[], Any]) -> None:
        """Call ``fn()`` once in every process that runs items (this one for a serial
        executor, each worker for Dask): how a caller empties the per-process caches of
        the trials it is done with. Exceptions propagate."""
        fn()


class SerialExecutor(Executor):
    """Runs the trials one after the other in this process."""

    def map(self, fn, shared, items, progress=None):
        out = []
        for i, item in enumerate(items):
            out.append(fn(shared, item))
            if progress:
                progress(i + 1, len(items))
        return out


def _single_threaded() -> None:
    # One BLAS/numba thread per worker process: the workers are the parallelism, and
    # thread-count-dependent reductions would make results differ from a serial run.
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
        os.environ[var] = "1"


class DaskExecutor(Executor):
    """Runs trials on a ``distributed.Client``.

    The shared object is scattered to every worker once (broadcast); trials are
    submitted in order and gathered in order, so the result list is independent of
    scheduling. ``map`` may be called from several threads at once (``concurrent``): the
    client is thread-safe and the workers interleave the calls' trials.
    """

    concurrent = True

    def __init__(self, client):
        self.client = client
        self._shared: tuple | None = None  # (shared object, its future on the workers)

    def _scatter(self, shared):
        """The workers' copy of ``shared``, sent once per object: a diagnosis maps hundreds
        of small batches over the same prepared session (~20 MB of clouds), and sending it
        with every batch cost more than the replays and defeated the workers' caches."""
        if self._shared is None or self._shared[0] is not shared:
            self._shared = (shared, self.client.scatter(shared, broadcast=True, hash=False))
        return self._shared[1]

    def map(self, fn, shared, items, progress=None):
        from distributed import as_completed

        ref = self._scatter(shared)
        futures = [self.client.submit(fn, ref, item, pure=False) for item in items]
        done = 0
        for _ in as_completed(futures):
            done += 1
            if progress:
                progress(done, len(items))
        return self.client.gather(futures)

    def run_everywhere(self, fn):
        self.client.run(fn)


@contextmanager
def executor(scheduler: str | None = None, *, workers: int | None = 2, serial: bool = False) -> Iterator[Executor]:
    """The execution back end for sweeps, fits and diagnoses.

    Args:
        scheduler: address of an existing Dask scheduler (``tcp://host:8786``); also read
            from the ``TISSUETWIN_SCHEDULER`` environment variable. None starts a local
            cluster in this process (worker processes, one thread each).
        workers: worker processes of the local cluster (default 2, this machine's cores).
        serial: run in this process without Dask (tests, debugging, reference runs).
    """
    if serial or workers == 0:
        yield SerialExecutor()
        return
    scheduler = scheduler or os.environ.get("TISSUETWIN_SCHEDULER") or None
    from distributed import Client, LocalCluster

    if scheduler:
        with Client(scheduler) as client:
            yield DaskExecutor(client)
        return
    _single_threaded()
    import dask

    with dask.config.set(LOCAL_CLUSTER_CONFIG), LocalCluster(
        n_workers=workers or 2,
        threads_per_worker=1,
        processes=True,
        dashboard_address=None,
        silence_logs=40,
    ) as cluster, Client(cluster) as client:
        yield DaskExecutor(client)
