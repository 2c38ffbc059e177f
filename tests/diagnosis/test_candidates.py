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


def test_a_fit_at_the_edge_of_a_kinds_plausible_range_is_told_but_not_one_at_the_phantoms_geometry():
    """``FitSpace.at_bound``: a probe radius of 3x the nominal (its upper bound), friction at
    mu 2 and a stiffness ratio at its bound are flagged; an inclusion's centre against the
    phantom's side or its smallest radius (geometry, resolution: ``open_ends``) are not, nor
    is any kind's start, or a fit one step and a bit inside."""
    cands = candidates(SIZE, 0.005)
    for c in cands.values():
        for s in c.starts:
            assert c.at_bound(s) == [], (c.kind, s)
    pr = cands["probe_radius"]
    assert pr.at_bound(np.array([0.015])) == ["radius at its upper bound 0.015"]
    assert pr.at_bound(pr.upper - 1.01 * pr.steps) == []
    assert cands["friction"].at_bound(np.array([2.0])) and cands["friction"].at_bound(np.array([0.01]))
    inc = cands["inclusion"]
    x = inc.clip(np.array([0.0, 0.02, 0.03, 0.003, 0.6]))  # against the side, smallest radius
    assert inc.at_bound(x) == []
    x[4] = inc.upper[4]
    assert inc.at_bound(x) == ["log10_stiffness_ratio at its upper bound 1.5"]
    g = cands["gravity"]
    assert g.at_bound(np.array([0.0, 0.0, -9.81])) == [] and g.at_bound(np.array([0.0, 0.0, -30.0]))
