"""Residual fields, phases and candidate parameterisations of the diagnosis."""

import dataclasses

import numpy as np
import pytest

from core.diagnosis import KINDS, PHASES, FieldLayout, candidates, phase_labels
from core.diagnosis.fields import frame_bins, residual_field
from core.simulation import box_mesh, effect_from_dict

SIZE = (0.0687, 0.0393, 0.0358)
GRID = (13, 5, 5)


def test_bins_cover_the_top_interior_in_x_major_order():
    lay = FieldLayout(SIZE, (16, 8))
    c = lay.centres()
    pts = np.column_stack([c, np.full(len(c), SIZE[2])])
    assert np.array_equal(lay.index(pts), np.arange(lay.n_bins))
    outside = np.array([[0.001, 0.02, SIZE[2]], [0.03, 0.02, SIZE[2] - 0.02], [0.03, 0.0385, SIZE[2]]])
    assert np.all(lay.index(outside) == -1)


def test_flat_surface_field_is_the_offset_and_the_scatter_is_the_noise():
    rng = np.random.default_rng(0)
    lay = FieldLayout(SIZE, (8, 4))
    rest = box_mesh(SIZE, GRID).nodes
    sigma, offset = 1e-3, 3e-4
    clouds = []
    for _ in range(5):
        xy = rng.uniform([0.005, 0.005], [SIZE[0] - 0.005, SIZE[1] - 0.005], (4000, 2))
        z = SIZE[2] + offset + sigma * rng.standard_normal(4000)
        clouds.append(np.column_stack([xy, z]))
    pts, bins, counts = frame_bins(clouds, lay)
    field, ss, dof = residual_field(np.repeat(rest[None], 5, axis=0), GRID, lay, pts, bins, counts)
    assert counts.sum() == sum(len(p) for p in pts) > 15000
    assert abs(np.average(field, weights=counts) - offset) < 3 * sigma / np.sqrt(counts.sum())
    assert np.sqrt(ss / dof) == pytest.approx(sigma, rel=0.03)


def test_phases_of_a_scripted_poke():
    r, top = 0.005, SIZE[2]
    t = np.arange(0, 7.0, 1 / 30)
    x = np.full_like(t, 0.03)
    z = np.full_like(t, top + r + 0.005)  # rest: 5 mm above
    down = (t >= 1) & (t < 2)
    z[down] = top + r + 0.005 - 0.008 * (t[down] - 1)  # loading: 8 mm/s, to 3 mm deep
    z[t >= 2] = top + r - 0.003
    slide = (t >= 3) & (t < 4)
    x[slide] = 0.03 + 0.006 * (t[slide] - 3)
    x[t >= 4] = 0.036
    up = (t >= 5) & (t < 6)
    z[up] = top + r - 0.003 + 0.008 * (t[up] - 5)
    z[t >= 6] = top + r + 0.005
    centres = np.column_stack([x, np.full_like(t, 0.02), z])
    lab = phase_labels(t, centres, SIZE, r)
    name = np.array(PHASES)[lab]

    def at(a, b):
        m = (t > a + 0.1) & (t < b - 0.1)
        return set(name[m])

    assert at(0, 1.3) == {"rest"}
    assert at(1.5, 2) == {"loading"}
    assert at(2, 3) == {"holding"}
    assert at(3, 4) == {"sliding"}
    assert at(5, 5.4) == {"unloading"}  # clear of the surface 0.375 s later
    assert at(6.2, 7) == {"rest"}


def test_every_candidate_start_is_a_valid_effect_with_the_format_parameters():
    cands = candidates(SIZE, 0.005)
    assert tuple(cands) == KINDS
    for kind, c in cands.items():
        for x in c.starts:
            e = effect_from_dict(c.to_effect(x))
            fields = {f.name for f in dataclasses.fields(e)}
            assert e.kind == kind and set(c.to_parameters(x)) == fields
            assert np.all(c.clip(x) == x)
        assert len(c.names) == len(c.steps) == len(c.lower) == len(c.upper)
