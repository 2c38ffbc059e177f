"""The in-loop hook of core.simulation.solver.simulate (used for the paper's in-loop correction)."""

import numpy as np
import pytest

from core.errors import SimulationError
from core.simulation import Material, ProbePath, box_mesh, build_model, simulate

SIZE = np.array([0.0687, 0.0393, 0.0358])
GRID = (7, 3, 3)


def _setup():
    mesh = box_mesh(SIZE, GRID)
    model = build_model(mesh, 0.104, Material(5000.0))
    t = np.linspace(0.0, 0.6, 7)
    depth = np.array([0.0, 0.001, 0.003, 0.005, 0.005, 0.003, 0.0])
    centre = np.array([SIZE[0] / 2, SIZE[1] / 2, SIZE[2] + 0.005])
    path = ProbePath(t, centre[None] - depth[:, None] * np.array([0, 0, 1.0]))
    return mesh, model, path, np.linspace(0.05, 0.6, 12)


def test_hook_returning_none_changes_nothing():
    mesh, model, path, times = _setup()
    plain = simulate(model, path, 0.005, times)
    seen = []
    hooked = simulate(model, path, 0.005, times, frame_hook=lambda j, t, x: seen.append((j, t)))
    np.testing.assert_array_equal(plain.positions, hooked.positions)
    assert [j for j, _ in seen] == list(range(times.size))
    np.testing.assert_allclose([t for _, t in seen], times)


def test_hook_correction_is_recorded_and_carried_on():
    mesh, model, path, times = _setup()
    top = mesh.top_nodes()
    bottom = mesh.bottom_nodes()
    lift = 0.001

    def hook(j, t, x):
        x[top, 2] += lift
        x[bottom, 2] += lift  # fixed nodes: must be ignored
        return x

    plain = simulate(model, path, 0.005, times)
    hooked = simulate(model, path, 0.005, times, frame_hook=hook)
    assert hooked.ok
    # frame 0 is the plain frame plus the lift, exactly
    np.testing.assert_allclose(hooked.positions[0][top, 2], plain.positions[0][top, 2] + lift, atol=1e-12)
    # fixed nodes never move
    np.testing.assert_array_equal(hooked.positions[:, bottom], plain.positions[:, bottom])
    # the simulation continued from the corrected state: later frames differ from plain + lift
    later = hooked.positions[-1][top, 2] - plain.positions[-1][top, 2]
    assert np.all(later > lift * 1.05)  # corrections accumulate faster than the damped recoil


def test_hook_with_a_wrong_shape_raises():
    mesh, model, path, times = _setup()
    with pytest.raises(SimulationError, match="frame_hook must return"):
        simulate(model, path, 0.005, times, frame_hook=lambda j, t, x: x[:5])
