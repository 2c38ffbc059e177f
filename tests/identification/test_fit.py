"""Fits of Young's modulus: honest "cannot tell", and recovery when force data pin E down."""

import json
from dataclasses import replace

import pytest

from core.identification import Trial, executor, fit_youngs_modulus
from core.preparation import prepare_session
from tests._presets import SHORT_SMALL  # 6 s sequences: the fits below pass as at 10 s, in half the time


def test_displacement_only_without_gravity_is_not_identifiable(small_session):
    """The quasi-static shape of a homogeneous linear-elastic body under a displacement-
    controlled probe does not depend on E: the fit must say so, not report a value."""
    prepared = prepare_session(small_session)
    with executor(serial=True) as ex:
        fit = fit_youngs_modulus(prepared, executor=ex, n_boot=200)
    assert fit.identifiable is False
    assert fit.youngs_modulus is None and fit.interval is None
    assert fit.reason.startswith("flat profile")
    assert "force" in fit.reason  # says what would help
    data = fit.to_json()
    assert data["youngs_modulus"]["identifiable"] is False and data["youngs_modulus"]["value"] is None
    assert set(data["errors"]) == {"train", "validation", "test"}
    json.dumps(data)  # serialisable as written to fit.json


@pytest.fixture(scope="module")
def force_session(tmp_path_factory):
    from core.lab import generate_session

    return generate_session(tmp_path_factory.mktemp("lab") / "force-s4", preset=SHORT_SMALL, seed=4, with_force=True)


@pytest.mark.slow
def test_force_columns_pin_down_youngs_modulus(force_session):
    """With measured probe force, E is identifiable. The fit uses the truth's material law
    (stable neo-Hookean): with the paper's corotational law the same data give ~5.9 kPa,
    a model-form bias of the linear law at 3-10 mm indentations, not an identification
    error. The replay grid alone (13x5x5) is stiffened by volumetric locking (~3.1 kPa);
    the refit on the refined grid corrects it (measured 5.20 kPa). The reported interval
    holds the model form too (E refitted under other laws, Poisson's ratios and grids,
    core.identification.model_form): measured 2.23-7.24 kPa, a 3.2x span, against a
    statistical (bootstrap) interval of 4.98-5.39 kPa. It must hold the truth and stay
    informative (well under the 10x that reads "not identifiable")."""
    truth = json.loads((force_session / "truth.json").read_text())["youngs_modulus"]
    prepared = prepare_session(force_session)
    with executor(serial=True) as ex:
        fit = fit_youngs_modulus(prepared, base=Trial(sequence="", youngs_modulus=1.0, law="stable_neo_hookean"), executor=ex, n_boot=200)
    assert fit.uses_force and fit.identifiable, fit.reason
    assert fit.youngs_modulus == pytest.approx(truth, rel=0.10)
    lo, hi = fit.interval
    assert lo <= truth <= hi and lo <= fit.youngs_modulus <= hi and hi / lo < 5.0
    blo, bhi = fit.bootstrap_interval
    assert lo <= blo <= fit.youngs_modulus <= bhi <= hi and bhi / blo < 1.5  # the data alone: tight
    mf = fit.model_form
    assert mf is not None and mf["low"] < fit.youngs_modulus < mf["high"] and mf["high"] / mf["low"] > 1.5
    assert 0 < fit.probe_sigma < 3e-4 and fit.calibration_shift > 0  # robot calibration widened it
    assert fit.coarse_value < 0.8 * truth  # locking on the coarse grid, corrected above


@pytest.mark.slow
def test_gravity_in_truth_and_model_pins_down_youngs_modulus(tmp_path):
    """With gravity the sag (~rho g H^2 / E, ~1 mm here) carries E. The fit uses the
    truth's law (measured 5014 Pa, interval 4828-5370 Pa with the calibration term);
    the corotational law gives ~5.3 kPa. The interval must contain the truth."""
    from core.lab import generate_session

    g = {"kind": "gravity", "g": [0.0, 0.0, -9.81]}
    path = generate_session(tmp_path / "gravity-s5", preset=SHORT_SMALL, seed=5, effects=[g])
    truth = json.loads((path / "truth.json").read_text())["youngs_modulus"]
    prepared = prepare_session(path)
    base = Trial(sequence="", youngs_modulus=1.0, law="stable_neo_hookean", effects=(g,))
    with executor(serial=True) as ex:
        fit = fit_youngs_modulus(prepared, base=base, executor=ex, n_boot=200)
    assert fit.identifiable, fit.reason
    assert fit.youngs_modulus == pytest.approx(truth, rel=0.10)
    lo, hi = fit.interval
    assert lo <= truth <= hi and lo <= fit.youngs_modulus <= hi and hi / lo < 1.5
    blo, bhi = fit.bootstrap_interval
    assert lo <= blo and bhi <= hi  # the calibration term and the model form only widen
    # without force the sag sets E, and the sag depends on the law and nu: the interval
    # holds E refitted to the surface under both laws at either end of nu (on the fine grid's scale)
    mf, scale = fit.model_form, fit.refined_value / fit.coarse_value
    assert mf["channel"] == "surface" and len(mf["variants"]) == 4
    assert lo <= mf["low"] * scale * (1 + 1e-9) and mf["high"] * scale <= hi * (1 + 1e-9)
    assert mf["high"] / mf["low"] > 1.05  # the variants do move it


def test_only_force_gravity_or_a_fixed_foundation_set_a_scale_for_E():
    """Structural identifiability: scaling E scales every quasi-static stress, so only a
    measured force, a body force or a foundation of fixed stiffness can pin E."""
    from core.identification.objective import structurally_identifiable

    def trial(*effects):
        return Trial(sequence="", youngs_modulus=1.0, effects=effects)

    assert not structurally_identifiable(trial(), use_force=False)
    assert structurally_identifiable(trial(), use_force=True)
    assert structurally_identifiable(trial({"kind": "gravity", "g": [0, 0, -9.81]}), use_force=False)
    assert not structurally_identifiable(trial({"kind": "gravity", "g": [0, 0, 0]}), use_force=False)
    assert structurally_identifiable(trial({"kind": "base_compliance", "stiffness": 1e5}), use_force=False)
    for kind in ("friction", "viscoelasticity", "inclusion", "probe_radius", "time_offset", "kinematic_offset"):
        assert not structurally_identifiable(trial({"kind": kind}), use_force=False)
    # a foundation fitted to the surface is known over E only (Trial.effects_youngs): no scale
    fitted = Trial(sequence="", youngs_modulus=1.0, effects=({"kind": "base_compliance", "stiffness": 1e5},),
                   effects_youngs=5e3)
    assert not structurally_identifiable(fitted, use_force=False)
    assert structurally_identifiable(replace(fitted, effects=fitted.effects + ({"kind": "gravity", "g": [0, 0, -9.81]},)),
                                     use_force=False)


def test_a_foundation_fitted_to_the_surface_moves_with_E(small_session):
    """With ``effects_youngs`` the base's stiffness scales with E (stiffness x E /
    effects_youngs), so the replayed surface is the same at any E (up to the dynamics, the
    only term that does not scale): E cannot be read off a stiffness the surface measured
    over E. Held at its Pa/m, the same base makes the surface depend on E. Measured (small
    lab session, 3x E): the mean squared top residual moves 0.67 % moving, 21.4 % held."""
    from core.identification import run_trial

    prepared = prepare_session(small_session)
    name = next(n for n, s in prepared.sequences.items() if s.role == "train")
    base = {"kind": "base_compliance", "stiffness": 3e4}
    moving = Trial(sequence=name, youngs_modulus=5e3, effects=(base,), effects_youngs=5e3, paper_error=False)
    assert moving.model_effects()[0].stiffness == pytest.approx(3e4)
    assert replace(moving, youngs_modulus=1.5e4).model_effects()[0].stiffness == pytest.approx(9e4)

    def top(trial):
        r = run_trial(prepared, trial)
        assert r.ok, r.message
        return r.frame_top_sq.sum() / r.frame_top_counts.sum()

    ref = top(moving)
    moved = abs(top(replace(moving, youngs_modulus=1.5e4)) - ref) / ref
    held = abs(top(replace(moving, youngs_modulus=1.5e4, effects_youngs=None)) - ref) / ref
    assert moved < 0.02 and held > 5 * moved, (moved, held)
