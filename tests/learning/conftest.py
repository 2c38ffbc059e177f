"""Fixtures of the learned-correction tests: a `small` session whose truth has gravity,
replayed (with gravity) at a 5x too soft E, so the replay's error is far above the
noise floor (measured: ~4.2 mm against ~1.4 mm at the true E of 5 kPa).

Why gravity: the base sessions are displacement-controlled, so without a body force the
replayed shape barely depends on E (every E from 10 Pa to 1e5 Pa gives 1.41-1.46 mm on
seed 3, within 4 % of the 1.41 mm noise floor) and a wrong E leaves nothing to correct.
"""

from __future__ import annotations

import pytest

WRONG_E = 1000.0
"""Pa: the truth is 5 kPa; 10x too soft (500 Pa) collapses under gravity, 1 kPa does not."""

SMALL_NET = dict(widths=(8, 16, 32))
"""Narrow UNets for tests (the paper's 64/128/256 are the default and go to the benchmark)."""


@pytest.fixture(scope="session")
def gravity_session(tmp_path_factory):
    from tests._sessions import shared_session

    return shared_session(tmp_path_factory, "small-gravity-s3", preset="small", seed=3, effects=[{"kind": "gravity"}])


@pytest.fixture(scope="session")
def gravity_prepared(gravity_session):
    from core.preparation import prepare_session
    from core.simulation.replay import ReplayConfig
    return prepare_session(gravity_session, ReplayConfig())


@pytest.fixture(scope="session")
def wrong_e_config():
    from core.simulation import Gravity
    from core.simulation.replay import ReplayConfig
    return ReplayConfig(youngs_modulus=WRONG_E, effects=(Gravity(),))


@pytest.fixture(scope="session")
def wrong_e_frames(gravity_prepared, wrong_e_config):
    from core.learning import build_frames

    return build_frames(gravity_prepared, wrong_e_config)
