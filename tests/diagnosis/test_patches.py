"""Residual fields on any surface: patches of a dome's visible surface, the signed
residual against the deformed mesh and its derivative."""

import numpy as np
import pytest
import trimesh

from core.diagnosis.fields import NOISE_GROUPS, frame_bins, residual_field, residual_field_tangent
from core.diagnosis.patches import PatchLayout, sampler_of
from core.lab.shapes import dome_surface
from core.simulation.meshing import tetrahedralise
from tests._shapes import DOME_CENTRE, DOME_SPHERE_RADIUS, cap_directions


@pytest.fixture(scope="module")
def dome(tmp_path_factory):
    V, F = dome_surface()
    path = tmp_path_factory.mktemp("dome") / "dome.stl"
    trimesh.Trimesh(V, F).export(str(path))
    return tetrahedralise(path, 0.008)


def _sphere_points(n, offset, seed):
    """Points ``offset`` (m) outside the dome's cap along the sphere's normal, up the cap."""
    return DOME_CENTRE + (DOME_SPHERE_RADIUS + offset) * cap_directions(n, seed)


def test_patches_cover_the_visible_surface_in_similar_areas(dome):
    layout = PatchLayout(dome, 16)
    assert layout.n_bins == layout.top_bins == 16 and layout.faces() == ("surface",)
    assert np.all(layout.face_of_bin() == NOISE_GROUPS.index("surface"))
    rest = sampler_of(dome).rest
    idx = layout.index(rest)
    seen = rest[:, 2] > 0.003
    assert np.all(idx[seen] >= 0) and np.all(idx[~seen] == -1)  # the base is never seen
    # measured points near the cap are binned, a point under the base is not
    assert np.all(layout.index(_sphere_points(200, 0.002, 9)) >= 0)
    assert np.all(layout.index(np.array([[0.035, 0.035, -0.001], [0.02, 0.05, -0.002]])) == -1)
    share = np.bincount(idx[seen], minlength=16) / seen.sum()
    assert share.min() > 0.25 / 16 and share.max() < 4.0 / 16, share
    # centres lie on the surface; normals point out of it (up the cap, out at the rim)
    d, _ = sampler_of(dome).nearest(layout.centres3())
    assert d.max() < 0.004
    assert np.all(np.einsum("ij,ij->i", layout.normals3(), layout.centres3() - [0.035, 0.035, 0.0]) > 0)
    assert np.all(layout.index(np.array([[0.035, 0.035, 0.06], [0.2, 0.2, 0.02]])) == -1)  # far away


def test_the_field_reads_a_known_offset_and_its_tangent_matches_differences(dome):
    layout = PatchLayout(dome, 16)
    F = 3
    clouds = [_sphere_points(600, off, f) for f, off in enumerate((0.0, 0.001, -0.0015))]
    pts, bins, counts = frame_bins(clouds, layout)
    positions = np.repeat(dome.nodes[None], F, axis=0)
    field, ss, dof = residual_field(positions, dome, layout, pts, bins, counts)
    for f, off in enumerate((0.0, 0.001, -0.0015)):
        used = counts[f] > 0
        # chords of 8 mm elements on a 37 mm sphere sit ~0.1-0.2 mm inside it
        assert np.median(field[f, used]) == pytest.approx(off + 0.15e-3, abs=0.15e-3)
    # every deviation is the surface group's, and small: the points lie on spheres, the
    # within-patch spread is the chords' sag (~0.1-0.2 mm), not noise
    g = NOISE_GROUPS.index("surface")
    assert dof[g] > 0 and ss.sum() == ss[g] > 0 and ss[g] / dof[g] < (0.3e-3) ** 2
    # moving the whole phantom up by 1 mm lowers each residual by 1 mm times its normal's z
    up = positions + [0.0, 0.0, 0.001]
    moved, _, _ = residual_field(up, dome, layout, pts, bins, counts)
    has = counts > 0
    assert np.allclose(moved[has] - field[has], -0.001 * layout.normals3()[np.nonzero(has)[1], 2], atol=0.25e-3)
    # the tangent along two directions against central differences, on the frame whose
    # points lie on the surface: the tangent leaves out (p - x) . dn, a residual times
    # the normal's turn (second order where the model fits; 6 % of the change on the
    # frames whose points sit 1-1.5 mm off under these 1 mm random node moves)
    rng = np.random.default_rng(3)
    directions = rng.normal(scale=1e-3, size=(2, F, dome.n_nodes, 3))
    tangent = residual_field_tangent(positions, directions, dome, layout, pts, bins, counts)
    for t in range(2):
        eps = 1e-3
        plus, _, _ = residual_field(positions + eps * directions[t], dome, layout, pts, bins, counts)
        minus, _, _ = residual_field(positions - eps * directions[t], dome, layout, pts, bins, counts)
        fd = (plus - minus) / (2 * eps)
        on = has[0]
        scale = np.abs(fd[0, on]).max()
        assert np.abs(tangent[t][0, on] - fd[0, on]).max() < 0.05 * scale
        assert np.abs(tangent[t][has] - fd[has]).max() < 0.10 * np.abs(fd[has]).max()


def test_the_field_in_chunks_of_frames_equals_the_field_in_one_pass(dome, monkeypatch):
    """A paper-size sequence is measured a chunk of whole frames at a time (memory): the
    bin means, the noise groups' sums of squares and degrees of freedom, and the tangent
    must not depend on the chunk size."""
    import core.diagnosis.fields as fields

    layout = PatchLayout(dome, 16)
    F = 7
    clouds = [_sphere_points(300 + 50 * f, 1e-4 * f, f) for f in range(F)]
    pts, bins, counts = frame_bins(clouds, layout)
    rng = np.random.default_rng(5)
    positions = np.repeat(dome.nodes[None], F, axis=0) + rng.normal(scale=2e-4, size=(F, dome.n_nodes, 3))
    positions[4] = np.nan  # a diverged frame stays empty either way
    directions = rng.normal(scale=1e-3, size=(3, F, dome.n_nodes, 3))
    one = residual_field(positions, dome, layout, pts, bins, counts)
    tan_one = residual_field_tangent(positions, directions, dome, layout, pts, bins, counts)
    monkeypatch.setattr(fields, "CHUNK_POINTS", 400)  # about a frame per chunk
    chunked = residual_field(positions, dome, layout, pts, bins, counts)
    tan_chunked = residual_field_tangent(positions, directions, dome, layout, pts, bins, counts)
    np.testing.assert_array_equal(chunked[0], one[0])
    np.testing.assert_allclose(chunked[1], one[1], rtol=1e-12)
    np.testing.assert_array_equal(chunked[2], one[2])
    np.testing.assert_array_equal(tan_chunked, tan_one)
    assert np.all(one[0][4] == 0) and np.any(one[0] != 0)


def test_normals_of_many_frames_and_remembered_samples_equal_the_direct_ones(dome):
    """The deformed normals at the samples (one sparse product for blocks of frames) equal
    the per-frame sums of the triangles' cross products, and the remembered nearest samples
    equal a fresh KD-tree query (the same points asked twice get the same array)."""
    sampler = sampler_of(dome)
    rng = np.random.default_rng(4)
    F = sampler.NORMAL_FRAMES + 7  # more than one block
    pos = dome.nodes[None] + 1e-3 * rng.standard_normal((F,) + dome.nodes.shape)
    pts = _sphere_points(3000, 5e-4, 9)
    frames = rng.integers(0, F, pts.shape[0])
    s = sampler.samples_of(pts)
    assert np.array_equal(s, sampler.nearest(pts)[1]) and sampler.samples_of(pts.copy()) is s
    got = sampler._point_normals(pos, frames, s)
    t = sampler.triangles
    want = np.zeros_like(got)
    for f in np.unique(frames):
        p = pos[f]
        face = np.cross(p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]])
        vn = np.zeros_like(p)
        for k in range(3):
            np.add.at(vn, t[:, k], face)
        m = frames == f
        nn = np.einsum("mk,mkj->mj", sampler.weights[s[m]], vn[sampler.nodes[s[m]]])
        want[m] = nn / np.linalg.norm(nn, axis=1, keepdims=True)
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-12)
    assert np.all(np.abs(np.linalg.norm(got, axis=1) - 1) < 1e-12) and np.unique(frames).size > sampler.NORMAL_FRAMES
