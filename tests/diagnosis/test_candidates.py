"""The candidate causes' parameter spaces (core.diagnosis.candidates)."""

import numpy as np
import pytest

from core.diagnosis.candidates import KINDS, candidates

SIZE = (0.0687, 0.0393, 0.0358)


def test_every_kind_has_a_candidate_whose_starts_are_feasible():
    cands = candidates(SIZE, 0.005)
    assert tuple(cands) == KINDS
    for c in cands.values():
        for s in c.starts:
            np.testing.assert_array_equal(c.clip(s), s, err_msg=c.kind)
            assert c.to_effect(s)["kind"] == c.kind


@pytest.mark.parametrize("x", [
    (0.0, 0.0, 0.0, 0.008, 0.5),  # centre on the corner: pushed a radius inside
    (0.0687, 0.0393, 0.0358, 0.02, 0.5),  # radius above its bound, centre on the far corner
    (0.05, -1.0, 0.03, 0.001, 0.5),  # radius below its bound, centre outside the box
])
def test_an_inclusion_stays_inside_the_phantom(x):
    c = candidates(SIZE, 0.005)["inclusion"]
    y = c.clip(np.array(x))
    r = y[3]
    assert c.lower[3] <= r <= c.upper[3]
    assert np.all(y[:3] - r >= -1e-15) and np.all(np.asarray(SIZE) - y[:3] - r >= -1e-15)
    inner = np.array([0.03, 0.02, 0.02, 0.008, 0.5])
    np.testing.assert_array_equal(c.clip(inner), inner)  # a feasible point is left alone


def test_top_presses_finds_the_deepest_point_of_each_press_on_the_top():
    from core.diagnosis.candidates import top_presses

    size, r = (0.0687, 0.0393, 0.0358), 0.005
    t = np.linspace(0.0, 1.0, 101)
    depth = np.where(t < 0.5, np.sin(2 * np.pi * t), 0.0) * 0.006 + np.where(t >= 0.5, np.sin(2 * np.pi * (t - 0.5)), 0.0) * 0.004
    x = np.where(t < 0.5, 0.020, 0.045) + 0.002 * t  # two presses, the first drifting slightly
    centres = np.stack([x, np.full_like(t, 0.02), size[2] + r - depth], axis=1)
    centres = np.concatenate([centres, [[0.08, 0.02, size[2]]]])  # beside the box: not a top press
    got = top_presses(centres, size, r)
    np.testing.assert_allclose(got, [[0.020 + 0.002 * 0.25, 0.02], [0.045 + 0.002 * 0.75, 0.02]], atol=1e-9)
    starts = candidates(size, r, got)["inclusion"].starts
    assert [tuple(np.round(s[:2], 6)) for s in starts] == [tuple(np.round(p, 6)) for p in got]
