"""Shared fixtures: generated sessions (made once per test run) and the shared sample session."""

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT.parent / "shared" / "sample-session"


@pytest.fixture(scope="session")
def sample_session() -> Path:
    if not (SAMPLE / "session.json").exists():
        pytest.skip("../shared/sample-session is not beside the repository")
    return SAMPLE


@pytest.fixture(scope="session")
def small_session(tmp_path_factory) -> Path:
    """A `small` virtual-lab session with no effects (seed 3), generated once."""
    from core.lab import generate_session

    return generate_session(tmp_path_factory.mktemp("lab") / "small-s3", preset="small", seed=3)
