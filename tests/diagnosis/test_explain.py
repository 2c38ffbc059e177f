"""Explaining a learned correction: its field projected onto the causes' field changes."""

import numpy as np
import pytest

from core.diagnosis.explain import explain_correction
from core.errors import TissueTwinError
from core.simulation import effect_from_dict
from core.preparation import prepare_session
from core.simulation.replay import ReplayConfig, build_replay_model
from core.simulation.solver import simulate

GRAVITY = {"kind": "gravity", "g": [0.0, 0.0, -9.81]}
LATERAL = {"kind": "kinematic_offset", "offset": [0.002, 0.0, 0.0]}
RADIUS = {"kind": "probe_radius", "radius": 0.0065}


def _top(prepared, name, config, effects=()):
    seq = prepared.sequences[name]
    model = build_replay_model(prepared, ReplayConfig(grid=config.grid, effects=tuple(effect_from_dict(e) for e in effects)))
    pos = simulate(model, seq.probe, prepared.probe_radius, seq.frame_times).positions
    nx, ny, nz = config.grid
    return pos[:, np.arange(nx * ny * nz).reshape(nx, ny, nz)[:, :, -1].ravel()]


@pytest.fixture(scope="module")
def prepared(small_session):
    return prepare_session(small_session, ReplayConfig(grid=(7, 5, 5), sequences=("seq01",)))


def test_a_correction_that_is_a_scaled_cause_is_attributed_to_it(prepared):
    """The synthetic 'network' corrects 60 % of the sag gravity causes, plus 10 % noise:
    gravity must account for nearly all of it at scale 0.6, the other causes for little."""
    config = ReplayConfig(grid=(7, 5, 5))
    sag = _top(prepared, "seq01", config, [GRAVITY]) - _top(prepared, "seq01", config)
    rng = np.random.default_rng(0)
    rms = np.sqrt(np.mean(sag**2))
    correction = 0.6 * sag + rng.normal(0.0, 0.1 * 0.6 * rms, sag.shape)
    ex = explain_correction(prepared, {"seq01": correction}, config, [GRAVITY, LATERAL, RADIUS], claimed=[GRAVITY])
    by_kind = {c.kind: c for c in ex.causes}
    assert ex.causes[0].kind == "gravity"
    # noise of 10 % RMS leaves a share of 1 / (1 + 0.01): anything above 0.95 is the sag
    assert by_kind["gravity"].share > 0.95 and by_kind["gravity"].scale == pytest.approx(0.6, rel=0.05)
    assert by_kind["kinematic_offset"].share < 0.5 and by_kind["probe_radius"].share < 0.5
    assert ex.claimed_share == pytest.approx(by_kind["gravity"].share, abs=1e-9)
    assert ex.unexplained_share == pytest.approx(1 - ex.claimed_share)
    assert ex.frames == sag.shape[0] and ex.correction_rms == pytest.approx(np.sqrt(np.mean(correction**2)))


def test_a_correction_of_the_wrong_shape_is_refused(prepared):
    with pytest.raises(TissueTwinError, match="shape"):
        explain_correction(prepared, {"seq01": np.zeros((3, 35, 3))}, ReplayConfig(grid=(7, 5, 5)), [GRAVITY])
    with pytest.raises(TissueTwinError, match="no sequence"):
        explain_correction(prepared, {"seq09": np.zeros((3, 35, 3))}, ReplayConfig(grid=(7, 5, 5)), [GRAVITY])
