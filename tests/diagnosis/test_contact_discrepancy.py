"""The mesh error measured again at a fit that moves the contact (a robot offset, a probe
radius): the coarse replay corrected by it is the fine mesh's, and a robot offset's fit is
no longer held back by the base model's correction, which was measured on presses of
another depth."""

import json
from dataclasses import replace

import numpy as np
import pytest

from core.diagnosis.candidates import phantom_context
from core.diagnosis.config import DiagnosisConfig
from core.diagnosis.evidence import Evidence, Spec
from core.diagnosis.fitting import fit_candidate
from core.diagnosis.patches import field_layout
from core.diagnosis.rounds import Round
from core.identification.execution import SerialExecutor
from core.preparation import prepare_session
from core.simulation.effects import EFFECT_KINDS
from tests._presets import SHORT_SMALL

OFFSET_Z = 0.004
"""The hidden robot offset, m: the probe really is 4 mm above its calibrated position, so
the recorded presses are 4 mm deeper than the real ones."""


@pytest.fixture(scope="module")
def offset_session(tmp_path_factory):
    from core.lab import generate_session

    return generate_session(tmp_path_factory.mktemp("lab") / "kin-s9", preset=SHORT_SMALL, seed=9,
                            effects=[{"kind": "kinematic_offset", "offset": [0.0, 0.0, OFFSET_Z]}])


@pytest.fixture(scope="module")
def evidence(offset_session):
    """(prepared session, Evidence with the base discrepancy and the faces weighed), shared
    by the tests below (the fine runs of the base model are the slow part)."""
    prepared = prepare_session(offset_session)
    cfg = DiagnosisConfig(n_null=999)
    ev = Evidence(prepared, cfg, SerialExecutor(), field_layout(prepared, cfg))
    assert ev.discrepancy(("train", "validation")) == []
    noise = ev.runs([[]], "train", fine=True)[0] + ev.runs([[]], "validation", fine=True)[0]
    ss, dof = np.sum([r.ss for r in noise], axis=0), np.sum([r.dof for r in noise], axis=0)
    face_sigma2 = np.where(dof > 0, ss / np.maximum(dof, 1), 0.0)
    ev.weigh_faces(face_sigma2, float(face_sigma2[0]))
    return prepared, ev


def test_a_coarse_run_corrected_at_its_own_model_is_the_fine_run(evidence):
    """``discrepancy_at`` of the base model is the stored base discrepancy; of another model,
    the coarse run corrected by it is that model's fine run at the fine fits' step plus the
    base model's change from the simulator's step to it (exactly), within a small fraction
    of the model's fine run at the simulator's step, where the base model's correction
    leaves a difference that grows with the offset (measured: 0.54 % of the fine run's
    norm against 76 %)."""
    _, ev = evidence
    base = ev.discrepancy_at(Spec((), ev.cfg.youngs_modulus), ("train", "validation"))
    assert set(base) == set(ev.names["train"] + ev.names["validation"])
    for name, d in base.items():
        np.testing.assert_allclose(d, ev.delta[name], atol=1e-12)
    moved = Spec(({"kind": "kinematic_offset", "offset": [0.0, 0.0, OFFSET_Z]},), ev.cfg.youngs_modulus)
    disc = ev.discrepancy_at(moved, ("train",))
    assert set(disc) == set(ev.names["train"])
    at = (("dt", ev.cfg.fine_fit_dt),)
    coarse, fine = ev.runs([moved], "train")[0], ev.runs([moved], "train", fine=True)[0]
    fine_at = ev.runs([Spec(moved.effects, moved.youngs_modulus, simulation=at)], "train", fine=True)[0]
    base_fine = ev.runs([Spec((), ev.cfg.youngs_modulus)], "train", fine=True)[0]
    base_at = ev.runs([Spec((), ev.cfg.youngs_modulus, simulation=at)], "train", fine=True)[0]
    for c, f, b, bs in zip(coarse, fine_at, base_fine, base_at):
        np.testing.assert_allclose(ev.field(c, disc), f.field + (b.field - bs.field), atol=1e-12)
    here, fine_v = ev.vector(coarse, discrepancy=disc), ev.vector(fine, shifted=False)
    near = np.linalg.norm(here - fine_v) / np.linalg.norm(fine_v)
    off_by = np.linalg.norm(ev.vector(coarse) - fine_v) / np.linalg.norm(fine_v)
    assert off_by > 0.05, off_by  # the base model's correction is another one here
    assert near < 0.05 * off_by, (near, off_by)


def test_without_a_fine_fit_step_the_correction_is_the_fine_run_exactly(evidence):
    """With ``fine_fit_dt`` None the fine run steps as the base model's did: the coarse run
    corrected at its own model is that model's fine run exactly."""
    _, ev = evidence
    cfg = ev.cfg
    try:
        ev.cfg = replace(cfg, fine_fit_dt=None)
        moved = Spec(({"kind": "kinematic_offset", "offset": [0.0, 0.0, OFFSET_Z]},), cfg.youngs_modulus)
        disc = ev.discrepancy_at(moved, ("train",))
        coarse, fine = ev.runs([moved], "train")[0], ev.runs([moved], "train", fine=True)[0]
        here, fine_v = ev.vector(coarse, discrepancy=disc), ev.vector(fine, shifted=False)
        np.testing.assert_allclose(here, fine_v, atol=1e-9 * np.abs(fine_v).max())
    finally:
        ev.cfg = cfg


def test_a_robot_offset_is_fitted_as_the_fine_mesh_makes_it(offset_session, evidence):
    """The coarse fit of a robot offset from no offset, the mesh error measured again at the
    fit (``contact_relinearisations``), recovers the hidden 4 mm within a quarter and carries
    the discrepancy at its parameters on train and validation. Measured here: 4.40 mm, and
    3.89 mm with the base model's correction throughout (this lab's presses are shallow;
    on field seed 11's stiffening lab that fit stopped at 0.77 mm of a 5 mm offset and the
    diagnosis now claims 5.12 mm: README)."""
    truth = json.loads((offset_session / "truth.json").read_text())["effects"][0]["offset"]
    assert truth[2] == OFFSET_Z
    prepared, ev = evidence
    rnd = Round.build(ev, [], ev.cfg.youngs_modulus, ev.cfg, 0)
    cand = EFFECT_KINDS["kinematic_offset"].fit_space(phantom_context(prepared, ev.names["train"]))
    held = fit_candidate(ev, cand, [], nuisance=rnd.nuisance, relinearise=0)
    moved = fit_candidate(ev, cand, [], nuisance=rnd.nuisance)
    z_held, z_moved = float(held.x[2]), float(moved.x[2])
    assert held.discrepancy is None
    assert set(moved.discrepancy) == set(ev.names["train"] + ev.names["validation"])
    assert abs(z_moved - OFFSET_Z) < 0.25 * OFFSET_Z, (z_held, z_moved)
    assert z_moved != z_held  # the fit did go on from the new correction


def test_plain_trial_steps_give_the_fit_that_trials_with_derivatives_give(evidence, monkeypatch):
    """``SPECULATIVE_TRIALS``: a fit whose shorter trial steps are plain replays (their
    Jacobian made at the next iteration when one is taken) lands where the fit that replays
    every trial step with its derivatives lands, with fewer replays with derivatives. The
    robot offset's fit (three variables, steps tried in turn) from a start at its bounds
    in x and z (10 mm off sideways and up), where long steps overshoot: measured here 7
    replays with derivatives against 5, the same offset, the misfit equal to 1e-15."""
    import core.diagnosis.fitting as fitting

    prepared, ev = evidence
    rnd = Round.build(ev, [], ev.cfg.youngs_modulus, ev.cfg, 0)
    cand = EFFECT_KINDS["kinematic_offset"].fit_space(phantom_context(prepared, ev.names["train"]))
    start = np.array([-0.01, 0.0, 0.01])
    calls = {"n": 0}
    jacobian_runs = Evidence.jacobian_runs

    def counted(self, directions, role, **kw):
        calls["n"] += 1
        return jacobian_runs(self, directions, role, **kw)

    monkeypatch.setattr(Evidence, "jacobian_runs", counted)
    fits, n_jac = {}, {}
    for speculative in (len(fitting.LM_DAMPING) + len(fitting.LM_DAMPING_SHORT), 1):
        monkeypatch.setattr(fitting, "SPECULATIVE_TRIALS", speculative)
        ev.cache.clear()  # every replay made afresh: the two fits share no run
        calls["n"] = 0
        fits[speculative] = fit_candidate(ev, cand, [], nuisance=rnd.nuisance, start=start, relinearise=0)
        n_jac[speculative] = calls["n"]
    every, first = fits[max(fits)], fits[1]
    np.testing.assert_allclose(first.x, every.x, rtol=0, atol=1e-9)  # m: the same fit to round-off
    assert first.train_rss == pytest.approx(every.train_rss, rel=1e-9)
    assert n_jac[1] < n_jac[max(n_jac)], n_jac  # the shorter steps were tried, as plain replays


def test_a_real_robot_offset_still_explains_held_out_data_on_finer_meshes(evidence):
    """``beyond_finer_mesh``: the hidden 4 mm robot offset, as its round fits it, still
    explains more held-out data than its claim needs when the model and the model with it
    are replayed on the meshes finer than the fine reference (31x11x11 and 37x13x13 for
    25x9x9); a tenth of it (0.4 mm, straight up) does not. Measured here: the fit
    (-0.29, 0.80, 4.39) mm explains 7682 (chi2) where a claim needs 2223, and 2740 on
    37x13x13 (its least); the 0.4 mm offset 1540 on 31x11x11."""
    from core.diagnosis.model_form import beyond_finer_mesh, finer_meshes
    from core.diagnosis.rounds import assess_all, channel_masks

    prepared, ev = evidence
    assert [m.grid for m in finer_meshes(ev)] == [(31, 11, 11), (37, 13, 13)]
    assert all(m.element_size is None for m in finer_meshes(ev))
    E = ev.cfg.youngs_modulus
    rnd = Round.build(ev, [], E, ev.cfg, 0)
    cand = EFFECT_KINDS["kinematic_offset"].fit_space(phantom_context(prepared, ev.names["train"]))
    e = assess_all(ev, {"kinematic_offset": cand}, rnd, ev.cfg, len(ev.cfg.kinds),
                   channel_masks(ev, "validation"))["kinematic_offset"]
    assert e.statistic > e.critical, (e.statistic, e.critical)
    ok, label, t_w = beyond_finer_mesh(ev, [], E, rnd.nuisance, e.fit.effects, e.critical)
    assert ok and t_w >= e.critical, (label, t_w, e.critical)
    small = [{"kind": "kinematic_offset", "offset": [0.0, 0.0, 0.1 * OFFSET_Z]}]
    ok_small, label_small, t_small = beyond_finer_mesh(ev, [], E, rnd.nuisance, small, e.critical)
    assert not ok_small, (label_small, t_small, e.critical)


def test_a_robot_offset_s_min_size_holds_on_the_finer_meshes(evidence):
    """``world_min_size`` of a kind that moves the contact has the finer meshes among its
    worlds (its claim must hold there: ``beyond_finer_mesh``): the runs with and without a
    robot offset along -x of the stated size are made on 31x11x11 and 37x13x13, and the
    size stated is the largest over every world, here 37x13x13's, above the size the other
    worlds alone state; a kind that does not move the contact (gravity) gets no finer-mesh
    run. Measured on this session: -x 1.163 mm where the other worlds alone state 1.151 mm
    (the neo-Hookean law's); the finer meshes set the size along +y (2.35 mm) and -z (3.97
    mm) too, the neo-Hookean law along -y (1.35 mm); +x and +z none up to 10 mm (the Yeoh
    k = 1 world)."""
    from dataclasses import replace as dc_replace

    from core.diagnosis.model_form import finer_meshes
    from core.diagnosis.sizing import signatures, world_min_size

    prepared, ev = evidence
    E = ev.cfg.youngs_modulus
    rnd = Round.build(ev, [], E, ev.cfg, 0)
    ctx = phantom_context(prepared, ev.names["train"] + ev.names["validation"])
    cls = EFFECT_KINDS["kinematic_offset"]
    assumed = {"direction": [-1.0, 0.0, 0.0]}
    level = ev.cfg.alpha / len(ev.cfg.kinds)
    d_t, d_v = signatures(ev, rnd, [cls.sized(cls.reference_size, ctx, **assumed).to_dict()])[0]
    critical = max(rnd.test.critical(rnd.test.null(d_t[:, None], d_v[:, None]), level), 0.0)

    def finer_keys():
        grids = {m.grid for m in finer_meshes(ev)}
        return {k for k in ev.cache.keys() if isinstance(k[4], tuple) and k[4] in grids}

    before = finer_keys()
    size, label = world_min_size(ev, rnd, cls, ctx, assumed, cls.reference_size, critical, level)
    made = finer_keys() - before
    assert size is not None and size > 0, (size, label)
    # with and without the offset at the size of the last step, on train and validation,
    # on each finer mesh (the base model's runs may be the cache's already)
    effects_runs = [k for k in made if "kinematic_offset" in k[0]]
    assert len(effects_runs) == 2 * len(ev.names["train"] + ev.names["validation"]), sorted(made)
    original = ev.cfg
    try:
        ev.cfg = dc_replace(original, contact_mesh_refinements=())
        size_0, label_0 = world_min_size(ev, rnd, cls, ctx, assumed, cls.reference_size, critical, level)
    finally:
        ev.cfg = original
    assert label == finer_meshes(ev)[-1].label and size_0 is not None and size > size_0, (size, label, size_0, label_0)

    g = EFFECT_KINDS["gravity"]
    before = finer_keys()
    world_min_size(ev, rnd, g, ctx, {"direction": [0.0, 0.0, -1.0]}, g.reference_size, critical, level)
    assert finer_keys() == before
