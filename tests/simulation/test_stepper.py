"""The compiled time loop (core.simulation.stepper) against the Python reference step.

Both run the same algorithm; they may differ by floating-point rounding only. Each case
replays 3 s of pokes, holds and slides (contact on, off, sliding) on the 13x5x5 grid.
Tolerances: 1e-12 m on positions and 1e-9 N on forces (rounding accumulated over 360
steps of a stiff contact; measured 1e-16 m and 1e-12 N).
"""

import numpy as np
import pytest

from core.simulation import Material, ProbePath, SimulationConfig, box_mesh, build_model, effect_from_dict, simulate

SIZE = (0.0687, 0.0393, 0.0358)


def _path(duration=3.0, rate=200.0):
    keys_t = [0.0, 0.4, 1.0, 1.4, 2.0, 2.5, duration]
    top = SIZE[2] + 0.005
    keys = [[0.03, 0.02, top + 0.004], [0.03, 0.02, top - 0.006], [0.03, 0.02, top - 0.006],
            [0.037, 0.024, top - 0.005], [0.037, 0.024, top - 0.005], [0.037, 0.024, top + 0.004],
            [0.037, 0.024, top + 0.004]]
    t = np.arange(0.0, duration, 1.0 / rate)
    c = np.stack([np.interp(t, keys_t, np.asarray(keys)[:, i]) for i in range(3)], axis=1)
    return ProbePath(t, c)


CASES = {
    "plain": ("corotational", [], {}),
    "friction": ("corotational", [{"kind": "friction", "mu": 0.8}], {}),
    "gravity": ("corotational", [{"kind": "gravity"}], {}),
    "viscoelasticity": ("corotational", [{"kind": "viscoelasticity", "relaxation_time": 0.5, "stiffness_ratio": 2.0}], {}),
    "foundation+inclusion": ("corotational", [{"kind": "base_compliance", "stiffness": 5e4}, {"kind": "inclusion"}], {}),
    "inputs": ("corotational", [{"kind": "probe_radius", "radius": 0.007}, {"kind": "time_offset", "offset": 0.1},
                                {"kind": "kinematic_offset", "offset": [0.001, 0.0, -0.001]}], {}),
    "neo-hookean, two corrections": ("stable_neo_hookean", [], {"newton_iterations": 2}),
    "yeoh with friction": ("stable_yeoh", [{"kind": "friction", "mu": 0.5}], {}),
}


@pytest.mark.parametrize("case", list(CASES))
def test_compiled_loop_matches_the_reference_step(case):
    law, effects, kw = CASES[case]
    mesh = box_mesh(SIZE, (13, 5, 5))
    frames = np.arange(0.0, 3.0, 1.0 / 30.0) + 0.004
    out = {}
    for compiled in (False, True):
        model = build_model(mesh, 0.104, Material(5000.0, 0.44, law, stiffening=1.5 if law == "stable_yeoh" else 0.0),
                            SimulationConfig(compiled=compiled, **kw), [effect_from_dict(e) for e in effects])
        out[compiled] = simulate(model, _path(), 0.005, frames)
    ref, fast = out[False], out[True]
    assert ref.ok and fast.ok and ref.steps == fast.steps
    assert np.max(np.abs(ref.contact_force)) > 0.05  # the probe pressed
    np.testing.assert_allclose(fast.positions, ref.positions, rtol=0, atol=1e-12)
    np.testing.assert_allclose(fast.contact_force, ref.contact_force, rtol=0, atol=1e-9)


def test_in_loop_correction_is_applied_identically():
    """A frame hook that lifts the free nodes by 0.1 mm on every other frame: the compiled
    loop stops at each frame for it and continues from the corrected state."""
    mesh = box_mesh(SIZE, (13, 5, 5))
    frames = np.arange(0.0, 2.0, 1.0 / 30.0)

    def hook(j, t, x):
        return x + np.array([0.0, 0.0, 1e-4]) if j % 2 == 0 else None

    out = {}
    for compiled in (False, True):
        model = build_model(mesh, 0.104, Material(5000.0, 0.44), SimulationConfig(compiled=compiled))
        out[compiled] = simulate(model, _path(2.0), 0.005, frames, frame_hook=hook)
    np.testing.assert_allclose(out[True].positions, out[False].positions, rtol=0, atol=1e-12)
    free = model.free
    lifted = out[True].positions[2][free, 2] - out[True].positions[1][free, 2]
    assert np.median(lifted) > 5e-5  # the correction is in the record


def test_divergence_is_reported_at_the_same_step():
    """The probe driven 36 mm through the phantom in 0.2 s with 50 ms steps and no stiffness
    damping blows up; both loops stop at the same step with the same reason."""
    mesh = box_mesh(SIZE, (13, 5, 5))
    frames = np.arange(0.0, 1.0, 1.0 / 30.0)
    msgs = {}
    for compiled in (False, True):
        model = build_model(mesh, 0.104, Material(5000.0, 0.44), SimulationConfig(compiled=compiled, dt=0.05,
                                                                                  rayleigh_stiffness=0.0))
        path = ProbePath(np.array([0.0, 0.2, 1.0]), np.array([[0.03, 0.02, 0.05], [0.03, 0.02, 0.0], [0.03, 0.02, 0.0]]))
        res = simulate(model, path, 0.005, frames)
        msgs[compiled] = (res.status, res.message, res.steps, np.isnan(res.positions).any(axis=(1, 2)).tolist())
    assert msgs[True] == msgs[False]
    assert msgs[True][0] == "diverged" and "node moved" in msgs[True][1]


@pytest.mark.parametrize("error", [ZeroDivisionError("division by zero"), np.linalg.LinAlgError("Array must not contain infs or NaNs.")])
def test_a_numerical_error_inside_the_compiled_step_is_a_divergence(monkeypatch, error):
    """Numba raises these when a step's state has gone non-finite (field seed 807's
    model-form run, the lab's truth of a box-shaped STL): the replay, and its
    sensitivities, report "diverged" with NaN frames from there on instead of raising."""
    from core.simulation import stepper
    from core.simulation.sensitivity import simulate_sensitivities

    real = stepper.advance
    calls = []

    def failing(*args):
        calls.append(1)
        if len(calls) > 1:  # the first chunk completes, the next one fails
            raise error
        return real(*args)

    mesh = box_mesh(SIZE, (7, 4, 4))
    frames = np.arange(0.0, 1.0, 1.0 / 30.0)
    path = ProbePath(np.array([0.0, 1.0]), np.array([[0.03, 0.02, 0.05], [0.03, 0.02, 0.03]]))
    monkeypatch.setattr(stepper, "advance", failing)
    model = build_model(mesh, 0.104, Material(5000.0, 0.44), SimulationConfig())
    res = simulate(model, path, 0.005, frames, callback=lambda f, m: None)
    assert res.status == "diverged" and "non-finite" in res.message
    # the frames of the completed chunk stand, every frame from the failure on is NaN
    bad = np.isnan(res.positions).any(axis=(1, 2))
    k = int(bad.argmax())
    assert bad.any() and k > 0 and bad[k:].all() and np.isfinite(res.positions[:k]).all()
    calls.clear()
    calls.append(1)  # fail at once

    def build(theta, factorize):
        return build_model(mesh, 0.104, Material(float(theta[0]), 0.44), SimulationConfig(), factorize=factorize)

    sens = simulate_sensitivities(build, np.array([5000.0]), path, 0.005, frames)
    assert sens.result.status == "diverged" and "non-finite" in sens.result.message
    assert np.isnan(sens.result.positions[-1]).all()


def test_a_numerical_error_leaves_the_shared_factor_usable(monkeypatch):
    """A step that raises after its factor's cache of inverse rows grew into a new buffer
    (slots and count updated in place, the buffer lost with the exception) must not leave
    that cached, shared factor inconsistent: measured, a dome's diagnosis then failed on the
    next run that needed new rows ("cannot assign slice of shape (87, 1677) from input of
    shape (0, 1677)")."""
    from core.simulation import stepper
    from core.simulation.lowrank import ensure_rows

    mesh = box_mesh(SIZE, (7, 4, 4))
    frames = np.arange(0.0, 1.0, 1.0 / 30.0)

    def press(x, y):
        return ProbePath(np.array([0.0, 1.0]), np.array([[x, y, 0.05], [x, y, 0.03]]))

    model = build_model(mesh, 0.104, Material(5000.0, 0.44), SimulationConfig())
    assert simulate(model, press(0.03, 0.02), 0.005, frames).ok
    real = stepper.advance

    def failing(*args):
        pbtrs, cbT, rows, slot, used = args[1:6]
        # rows of nodes far from both presses: more than the buffer holds
        far = np.flatnonzero(mesh.nodes[:, 0] > 0.05)
        dofs = model.free_index[(3 * far[:, None] + np.arange(3)).ravel()]
        dofs = dofs[(dofs >= 0) & (slot[np.maximum(dofs, 0)] < 0)].astype(np.int64)
        grown = ensure_rows(pbtrs, cbT, rows, slot, used, dofs)
        assert grown.shape[0] > rows.shape[0]  # a new buffer, as a contact on new nodes makes
        raise ZeroDivisionError("division by zero")

    monkeypatch.setattr(stepper, "advance", failing)
    assert simulate(model, press(0.03, 0.02), 0.005, frames).status == "diverged"
    monkeypatch.setattr(stepper, "advance", real)
    # the same model (so the same cached factor) pressing elsewhere needs new rows
    again = simulate(model, press(0.012, 0.012), 0.005, frames)
    fresh = simulate(build_model(mesh, 0.104, Material(5000.0, 0.44), SimulationConfig(compiled=False)),
                     press(0.012, 0.012), 0.005, frames)  # the Python reference step
    assert again.ok and np.max(np.abs(again.contact_force)) > 0.05
    np.testing.assert_allclose(again.positions, fresh.positions, rtol=0, atol=1e-9)
    np.testing.assert_allclose(again.contact_force, fresh.contact_force, rtol=0, atol=1e-6)
