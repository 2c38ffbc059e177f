"""Residual fields, phases and candidate parameterisations of the diagnosis."""

import dataclasses

import numpy as np
import pytest

from core.diagnosis import KINDS, PHASES, FieldLayout, candidates, phase_labels
from core.diagnosis.fields import FACES, face_residuals, frame_bins, residual_field
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
    assert np.sqrt(ss[0] / dof[0]) == pytest.approx(sigma, rel=0.03) and ss[1:].sum() == 0 == dof[1:].sum()


def test_binned_points_are_read_from_the_clouds_and_give_the_same_field():
    """frame_bins keeps indices into the clouds (4 bytes a point) and int16 bins (2), not
    copies: each frame's kept points are exactly the clouds' in-bin points, and the field
    from them equals the field from materialised copies."""
    rng = np.random.default_rng(3)
    lay = FieldLayout(SIZE, (8, 4), side_rows=2)
    rest = box_mesh(SIZE, GRID).nodes
    clouds = [np.column_stack([rng.uniform(-0.005, SIZE[0] + 0.005, 3000), rng.uniform(-0.005, SIZE[1] + 0.005, 3000),
                               SIZE[2] + 3e-4 * rng.standard_normal(3000)]).astype(np.float32) for _ in range(4)]
    clouds[2] = clouds[2][:0]  # a frame with no points
    pts, bins, counts = frame_bins(clouds, lay)
    copies = []
    for f, c in enumerate(clouds):
        inside = lay.index(c) >= 0
        assert np.array_equal(pts[f], c[inside]) and pts[f].dtype == np.float32
        assert np.array_equal(bins[f], lay.index(c)[inside]) and bins[f].dtype == np.int16
        copies.append(c[inside].copy())
    n = sum(len(b) for b in bins)
    assert n > 3000 and pts.nbytes == 4 * n and sum(b.nbytes for b in bins) == 2 * n
    moved = np.repeat(rest[None], 4, axis=0) + 2e-4 * rng.standard_normal((4,) + rest.shape)
    a = residual_field(moved, GRID, lay, pts, bins, counts)
    b = residual_field(moved, GRID, lay, copies, [x.astype(np.int32) for x in bins], counts)
    for x, y in zip(a, b):
        assert np.array_equal(x, y)
    assert np.all(a[0][2] == 0) and np.any(a[0][0] != 0)


def test_side_faces_have_their_own_bins_sign_and_noise():
    """A box whose +x face sits 0.5 mm out and whose -y face sits 0.3 mm in, each with its
    own noise: the side bins read +0.5 / -0.3 mm (outward positive), the top 0, and each
    face's scatter is its own noise."""
    rng = np.random.default_rng(1)
    lay = FieldLayout(SIZE, (8, 4), side_rows=3)
    assert lay.n_bins == 8 * 4 + 2 * 4 * 3 + 2 * 8 * 3
    c3 = lay.centres3()
    assert np.array_equal(lay.index(c3), np.arange(lay.n_bins))  # every centre lands in its own bin
    sx, sy, sz = SIZE
    n = 3000
    top = np.column_stack([rng.uniform(0.005, sx - 0.005, n), rng.uniform(0.005, sy - 0.005, n), sz + 2e-4 * rng.standard_normal(n)])
    px = np.column_stack([sx + 5e-4 + 4e-4 * rng.standard_normal(n), rng.uniform(0.005, sy - 0.005, n), rng.uniform(0.005, sz - 0.005, n)])
    my = np.column_stack([rng.uniform(0.005, sx - 0.005, n), 3e-4 + 6e-4 * rng.standard_normal(n), rng.uniform(0.005, sz - 0.005, n)])
    rest = box_mesh(SIZE, GRID).nodes
    pts, bins, counts = frame_bins([np.concatenate([top, px, my])], lay)
    field, ss, dof = residual_field(rest[None], GRID, lay, pts, bins, counts)
    face = lay.face_of_bin()
    w = counts[0]
    assert abs(np.average(field[0][face == 0], weights=w[face == 0])) < 2e-5
    assert np.average(field[0][face == 2], weights=w[face == 2]) == pytest.approx(5e-4, abs=5e-5)
    assert np.average(field[0][face == 3], weights=w[face == 3]) == pytest.approx(-3e-4, abs=3e-5)
    assert counts[0][face == 1].sum() == 0 == counts[0][face == 4].sum()
    sig = np.sqrt(ss / np.maximum(dof, 1))
    assert sig[0] == pytest.approx(2e-4, rel=0.05) and sig[2] == pytest.approx(4e-4, rel=0.05) and sig[3] == pytest.approx(6e-4, rel=0.05)


def test_face_residuals_of_the_top_are_the_top_residuals():
    from core.diagnosis.fields import face_residuals
    from core.identification.residuals import top_residuals

    rng = np.random.default_rng(2)
    rest = box_mesh(SIZE, GRID).nodes
    moved = rest + 1e-3 * rng.standard_normal(rest.shape)
    lay = FieldLayout(SIZE, (8, 4))
    p = np.column_stack([rng.uniform(0.005, SIZE[0] - 0.005, 500), rng.uniform(0.005, SIZE[1] - 0.005, 500),
                         SIZE[2] + 1e-3 * rng.standard_normal(500)])
    kept = p[lay.index(p) >= 0]
    np.testing.assert_allclose(face_residuals(kept, moved, GRID, SIZE, "top"), top_residuals(p, moved, GRID, SIZE))


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


def test_bin_normals_point_out_of_their_faces():
    lay = FieldLayout(SIZE, (8, 4), side_rows=3)
    n, c, face = lay.normals3(), lay.centres3(), lay.face_of_bin()
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0)
    # a step along the normal leaves the box through the bin's own face, and no other bin takes it
    out = c + 1e-4 * n
    assert np.all(np.any((out < 0) | (out > np.asarray(SIZE)), axis=1))
    assert np.array_equal(n[face == 0], np.tile([0.0, 0.0, 1.0], ((face == 0).sum(), 1)))
    assert np.array_equal(n[face == 1], np.tile([-1.0, 0.0, 0.0], ((face == 1).sum(), 1)))
    assert np.array_equal(lay.index(c - 1e-5 * n), np.arange(lay.n_bins))  # just inside: each bin finds itself


def test_field_derivative_is_the_central_difference_of_the_field():
    """The residual field's derivative along node motions (the diagnosis's Jacobians are
    built from it) against a central difference of the field itself, on every face; the
    residual is bilinear within a point's cells, so a 1e-9 step is exact to rounding."""
    from core.diagnosis.fields import face_residuals_tangent

    rng = np.random.default_rng(4)
    grid = (13, 5, 5)
    rest = box_mesh(SIZE, grid).nodes
    pos = rest[None] + 1e-3 * rng.standard_normal((3,) + rest.shape)
    d = rng.standard_normal((2,) + pos.shape)
    pts = rng.uniform(0.05, 0.95, (2000, 3)) * np.asarray(SIZE)
    frames = rng.integers(0, 3, 2000)
    for face in FACES:
        dr = face_residuals_tangent(pts, pos, d, grid, SIZE, face, frames)
        for t in range(2):
            h = 1e-9
            fd = (face_residuals(pts, pos + h * d[t], grid, SIZE, face, frames=frames)
                  - face_residuals(pts, pos - h * d[t], grid, SIZE, face, frames=frames)) / (2 * h)
            assert np.abs(dr[t] - fd).max() <= 1e-6 * np.abs(fd).max(), face


def test_the_compiled_field_reads_mapped_clouds_in_place_and_equals_per_point_residuals(tmp_path):
    """The box's field is one compiled pass over the points where they are stored (mapped
    clouds and kept indices): its bin means, per-face scatter and degrees of freedom, and
    its tangent, equal those assembled here from per-point residuals of each face
    (:meth:`FieldLayout.residuals`), with a diverged frame and an empty one skipped."""
    from core.diagnosis.fields import residual_field_tangent
    from core.preparation import Clouds

    rng = np.random.default_rng(5)
    lay = FieldLayout(SIZE, (8, 4), side_rows=2)
    rest = box_mesh(SIZE, GRID).nodes
    F = 6
    clouds = []
    for f in range(F):
        n = 0 if f == 4 else 2500
        p = np.column_stack([rng.uniform(-0.004, SIZE[0] + 0.004, n), rng.uniform(-0.004, SIZE[1] + 0.004, n),
                             rng.uniform(SIZE[2] - 0.012, SIZE[2] + 0.001, n)])
        clouds.append(p.astype(np.float32))
    counts_f = np.array([len(c) for c in clouds])
    np.save(tmp_path / "p.npy", np.concatenate(clouds))
    np.save(tmp_path / "o.npy", np.concatenate([[0], np.cumsum(counts_f)]))
    mapped = Clouds.open(str(tmp_path / "p.npy"), str(tmp_path / "o.npy"))
    pts, bins, counts = frame_bins(mapped, lay)
    pos = rest[None] + 3e-4 * rng.standard_normal((F,) + rest.shape)
    pos[2, 5] = np.nan  # a diverged frame
    dpos = rng.standard_normal((3,) + pos.shape)
    field, ss, dof = residual_field(pos, GRID, lay, pts, bins, counts)
    dfield = residual_field_tangent(pos, dpos, GRID, lay, pts, bins, counts)

    B = lay.n_bins
    face_of = lay.face_of_bin()
    want, dwant = np.zeros((F, B)), np.zeros((3, F, B))
    want_ss, points = np.zeros(len(ss)), np.zeros(len(ss), dtype=np.int64)
    for f in (0, 1, 3, 5):
        p = np.asarray(clouds[f], dtype=np.float64)[pts.index[f]]
        bn = np.asarray(bins[f], dtype=np.int64)
        fr = np.full(len(bn), f)
        r = lay.residuals(p, bn, fr, pos, GRID)
        dr = lay.residuals_tangent(p, bn, fr, pos, dpos, GRID)
        n = np.bincount(bn, minlength=B)
        want[f] = np.divide(np.bincount(bn, weights=r, minlength=B), n, out=np.zeros(B), where=n > 0)
        for t in range(3):
            dwant[t, f] = np.divide(np.bincount(bn, weights=dr[t], minlength=B), n, out=np.zeros(B), where=n > 0)
        want_ss += np.bincount(face_of[bn], weights=(r - want[f][bn]) ** 2, minlength=len(ss))
        points += np.bincount(face_of[bn], minlength=len(ss)) - np.bincount(face_of[n > 0], minlength=len(ss))
    assert np.all(field[2] == 0) and np.all(field[4] == 0) and np.any(field[0] != 0)
    np.testing.assert_allclose(field, want, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(dfield, dwant, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(ss, want_ss, rtol=1e-10)
    assert np.array_equal(dof, points) and dof[0] > 1000 and dof[1:5].sum() > 100
