"""Sensitivities of a replay against central finite differences, for every fitted parameter.

Each case replays 3 s of a press, a hold, a slide and a release (contact on and off,
sliding) on the 13x5x5 grid and differentiates the node trajectories and the probe force
with respect to Young's modulus, Poisson's ratio and every effect kind's fit variables,
the penalty contact (through E and the probe's input) and the clock offset included.

A central difference of a whole replay is only a reference while the step does not cross
a switch of the contact's active set or friction's slip branch: the replay is piecewise
smooth, and a step of 1e-2 of a parameter's scale crossed one for friction, an inclusion's
radius and a lateral probe offset (measured: 10-100 % off, while smaller steps agreed to
1e-8). The reference is therefore the better of two steps, 1e-4 and 1e-5 of the scale
(measured: at most 3e-6 relative to the largest derivative, from the differences'
truncation and round-off); the tolerance is 1e-5.
"""

import numpy as np
import pytest

from core.simulation import Material, ProbePath, SimulationConfig, box_mesh, build_model, effect_from_dict
from core.simulation.sensitivity import finite_difference, simulate_sensitivities

SIZE = (0.0687, 0.0393, 0.0358)
FRAMES = np.arange(0.0, 3.0, 1.0 / 30.0) + 0.004
TOL = 1e-5


def _path(duration=3.0, rate=200.0):
    keys_t = [0.0, 0.4, 1.0, 1.4, 2.0, 2.5, duration]
    top = SIZE[2] + 0.005
    keys = [[0.03, 0.02, top + 0.004], [0.03, 0.02, top - 0.006], [0.03, 0.02, top - 0.006],
            [0.037, 0.024, top - 0.005], [0.037, 0.024, top - 0.005], [0.037, 0.024, top + 0.004],
            [0.037, 0.024, top + 0.004]]
    t = np.arange(0.0, duration, 1.0 / rate)
    return ProbePath(t, np.stack([np.interp(t, keys_t, np.asarray(keys)[:, i]) for i in range(3)], axis=1))


def _inclusion(th):
    return [{"kind": "inclusion", "center": [th[0], th[1], th[2]], "radius": th[3], "stiffness_ratio": 10 ** th[4]}]


# name: (theta -> (effects, E, nu), theta, scales, law, simulation options)
CASES = {
    "youngs_poisson": (lambda th: ([], 10 ** th[0], th[1]), [np.log10(5000.0), 0.44], [0.02, 0.01], "corotational", {}),
    "gravity": (lambda th: ([{"kind": "gravity", "g": [th[0], th[1], th[2]]}], 5000.0, 0.44),
                [0.5, -0.3, -9.81], [1.0, 1.0, 1.0], "corotational", {}),
    "gravity_youngs": (lambda th: ([{"kind": "gravity", "g": [0.0, 0.0, th[0]]}], 10 ** th[1], 0.44),
                       [-9.81, np.log10(5000.0)], [1.0, 0.02], "corotational", {}),
    "inclusion": (lambda th: (_inclusion(th), 5000.0, 0.44), [0.031, 0.019, 0.024, 0.008, np.log10(4.0)],
                  [0.002, 0.002, 0.002, 0.001, 0.1], "corotational", {}),
    "viscoelasticity": (lambda th: ([{"kind": "viscoelasticity", "relaxation_time": 10 ** th[0],
                                      "stiffness_ratio": 10 ** th[1]}], 5000.0, 0.44),
                        [np.log10(0.5), 0.0], [0.1, 0.1], "corotational", {}),
    "friction": (lambda th: ([{"kind": "friction", "mu": th[0]}], 5000.0, 0.44), [0.6], [0.1], "corotational", {}),
    "base_compliance": (lambda th: ([{"kind": "base_compliance", "stiffness": 10 ** th[0]}], 5000.0, 0.44),
                        [4.7], [0.1], "corotational", {}),
    "probe_radius": (lambda th: ([{"kind": "probe_radius", "radius": th[0]}], 5000.0, 0.44), [0.006], [0.0005],
                     "corotational", {}),
    "time_offset": (lambda th: ([{"kind": "time_offset", "offset": th[0]}], 5000.0, 0.44), [0.05], [0.03],
                    "corotational", {}),
    "kinematic_offset": (lambda th: ([{"kind": "kinematic_offset", "offset": [th[0], th[1], th[2]]}], 5000.0, 0.44),
                         [0.0005, -0.0002, -0.0003], [0.0005, 0.0005, 0.0005], "corotational", {}),
    # the contact surface subdivided 3 x 3 per triangle (SimulationConfig.contact_subdivision)
    "probe_radius_subdivided_contact": (lambda th: ([{"kind": "probe_radius", "radius": th[0]}], 5000.0, 0.44),
                                        [0.006], [0.0005], "corotational", {"contact_subdivision": 3}),
    "kinematic_offset_subdivided_contact": (
        lambda th: ([{"kind": "kinematic_offset", "offset": [th[0], th[1], th[2]]}], 10 ** th[3], 0.44),
        [0.0005, -0.0002, -0.0003, np.log10(5000.0)], [0.0005, 0.0005, 0.0005, 0.02], "corotational",
        {"contact_subdivision": 3}),
    "neo_hookean_two_corrections": (lambda th: ([{"kind": "friction", "mu": 0.4}], 10 ** th[0], th[1]),
                                    [np.log10(5000.0), 0.44], [0.02, 0.01], "stable_neo_hookean",
                                    {"newton_iterations": 2}),
}


def _builder(case):
    f, _, _, law, sim = CASES[case]
    mesh = box_mesh(SIZE, (13, 5, 5))

    def build(theta, factorize):
        effects, E, nu = f(theta)
        return build_model(mesh, 0.104, Material(E, nu, law), SimulationConfig(**sim),
                           [effect_from_dict(e) for e in effects], factorize=factorize)

    return build


@pytest.mark.parametrize("case", list(CASES))
def test_sensitivities_match_central_differences(case):
    _, theta, scales, _, _ = CASES[case]
    build = _builder(case)
    s = simulate_sensitivities(build, theta, _path(), 0.005, FRAMES, scales=scales)
    assert s.result.ok
    assert s.positions.shape == (len(theta), FRAMES.size, 325, 3) and s.contact_force.shape == (len(theta), FRAMES.size, 3)
    for j, scale in enumerate(scales):
        errors = []
        for rel in (1e-4, 1e-5):
            dX, dF = finite_difference(build, theta, _path(), 0.005, FRAMES, j, rel * scale)
            assert np.abs(dX).max() > 0, (case, j)  # the parameter moves the nodes
            error = np.abs(s.positions[j] - dX).max() / np.abs(dX).max()
            if case == "time_offset":
                # the force is on the robot's clock, as the kinematics are: no offset moves it
                assert np.abs(dF).max() < 1e-9 and np.abs(s.contact_force[j]).max() < 1e-9
            else:
                assert np.abs(dF).max() > 0, (case, j)  # the parameter changes the force
                error = max(error, np.abs(s.contact_force[j] - dF).max() / np.abs(dF).max())
            errors.append(error)
        assert min(errors) < TOL, (case, j, errors)


def test_a_wrong_derivative_is_caught():
    """The check can fail: the derivative along E compared with the difference along nu."""
    build = _builder("youngs_poisson")
    theta, scales = CASES["youngs_poisson"][1], CASES["youngs_poisson"][2]
    s = simulate_sensitivities(build, theta, _path(), 0.005, FRAMES, scales=scales)
    dX, dF = finite_difference(build, theta, _path(), 0.005, FRAMES, 1, 1e-4 * scales[1])
    assert np.abs(s.contact_force[0] - dF).max() / np.abs(dF).max() > 0.1


def test_the_replay_it_carries_is_the_replay():
    from core.simulation import simulate

    build = _builder("gravity")
    theta = CASES["gravity"][1]
    s = simulate_sensitivities(build, theta, _path(), 0.005, FRAMES, scales=CASES["gravity"][2])
    r = simulate(build(np.asarray(theta), True), _path(), 0.005, FRAMES)
    np.testing.assert_allclose(s.result.positions, r.positions, rtol=0, atol=1e-12)
    np.testing.assert_allclose(s.result.contact_force, r.contact_force, rtol=0, atol=1e-9)
