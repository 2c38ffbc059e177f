"""Shared fixtures: generated sessions (made once per test run) and the shared sample session."""

import os
from pathlib import Path

import pytest

# The two test workers share the two cores: one BLAS / OpenMP thread each, as the Dask
# workers of core.identification.execution have. Set before numpy is first imported (the
# test modules import it after this file); OpenBLAS threads spin while they wait, which
# cost 25 % more CPU for the same wall time (a hidden-kind diagnosis test: 55.7 s of CPU
# instead of 44.6 s, 42 s either way), CPU the other worker needed.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

# The preparation cache (core.preparation) of the test run lives in one temporary folder,
# shared by both test workers and the processes they start, and never in the user's home.
if "TISSUETWIN_CACHE_DIR" not in os.environ:
    import tempfile

    os.environ["TISSUETWIN_CACHE_DIR"] = tempfile.mkdtemp(prefix="tissuetwin-test-cache-")

from tests._sessions import shared_session  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT.parent / "shared" / "sample-session"


def pytest_collection_modifyitems(config, items):
    """Run the files that hold ``slow`` tests first (a stable sort, order kept otherwise).

    With ``--dist loadfile`` a file is one unit of work; a 2-3 minute file collected
    last kept one worker busy while the other sat idle (16.7 min for 29.5 CPU-minutes).
    Longest units first, the many short files then even out the two workers' ends."""
    slow = {item.path for item in items if item.get_closest_marker("slow")}
    items.sort(key=lambda item: item.path not in slow)


@pytest.fixture(scope="session")
def sample_session() -> Path:
    if not (SAMPLE / "session.json").exists():
        pytest.skip("../shared/sample-session is not beside the repository")
    return SAMPLE


@pytest.fixture(scope="session")
def small_session(tmp_path_factory) -> Path:
    """A `small` virtual-lab session with no effects (seed 3), generated once per test run."""
    return shared_session(tmp_path_factory, "small-s3", preset="small", seed=3)


@pytest.fixture(scope="session")
def small_dome_force_session(tmp_path_factory) -> Path:
    """A `small` virtual-lab dome session with no effects (6 s sequences, seed 3, force
    columns), generated once per test run (E's model form on a dome and the diagnosis's
    finer meshes both replay it)."""
    from core.lab.generate import PRESETS

    return shared_session(tmp_path_factory, "small-dome-force-s3", preset=PRESETS["small"].with_duration(6.0), seed=3,
                          shape="dome", with_force=True)
