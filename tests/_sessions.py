"""Virtual-lab sessions shared by the test workers (pytest-xdist) of one run."""

from __future__ import annotations

import os
from pathlib import Path


def shared_session(tmp_path_factory, name: str, **kwargs) -> Path:
    """A virtual-lab session (``kwargs`` go to :func:`core.lab.generate_session`) made once
    per test run and shared by the test workers: in the base folder of the run (beside the
    workers' own), the first worker to ask makes it under a file lock, the other waits and
    reads it (made once per worker, the small session took 25 s of a worker's setup in a suite run).
    Read-only for tests: copy it to change it."""
    from filelock import FileLock

    from core.lab import generate_session

    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent  # the run's folder, shared by its workers
    path = root / "shared-sessions" / name
    path.parent.mkdir(parents=True, exist_ok=True)
    with FileLock(str(path) + ".lock"):
        if not (path / "session.json").exists():  # (a folder without it: a run that died making it)
            generate_session(path, overwrite=path.exists(), **kwargs)
    return path
