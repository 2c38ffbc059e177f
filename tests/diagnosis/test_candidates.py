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
