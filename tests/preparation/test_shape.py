"""The rest shape (core/preparation/shape.py): the box in closed form, any STL through
trimesh; checked against hand-computed distances, the box as an STL, and a sphere's
analytic distance on the dome."""

import numpy as np
import pytest

from core.diagnosis.candidates import surface_presses
from core.lab.shapes import dome_surface
from core.preparation.shape import BoxShape, SurfaceShape, rest_shape
from core.simulation.effects import EFFECT_KINDS, PhantomContext
from tests._shapes import DOME_BASE_RADIUS, DOME_CENTRE, DOME_HEIGHT, DOME_SPHERE_RADIUS, box_surface

SIZE = np.array([0.08, 0.05, 0.05])
A, H = DOME_BASE_RADIUS, DOME_HEIGHT
R, CENTRE = DOME_SPHERE_RADIUS, DOME_CENTRE  # the sphere its cap is cut from


def _box_stl() -> SurfaceShape:
    m = box_surface(SIZE)
    return SurfaceShape(m.vertices, m.faces)


@pytest.fixture(scope="module")
def dome() -> SurfaceShape:
    return SurfaceShape(*dome_surface(A, H))


def test_box_distances_projections_and_fits_by_hand():
    box = BoxShape(SIZE)
    pts = np.array([[0.04, 0.025, 0.06], [0.04, 0.025, 0.045], [-0.003, -0.004, 0.02], [0.079, 0.025, 0.02]])
    np.testing.assert_allclose(box.clearance(pts), [0.01, -0.005, 0.005, -0.001], atol=1e-12)
    q, n = box.project(pts)
    np.testing.assert_allclose(q, [[0.04, 0.025, 0.05], [0.04, 0.025, 0.05], [0.0, 0.0, 0.02], [0.08, 0.025, 0.02]], atol=1e-12)
    np.testing.assert_allclose(n[[0, 1, 3]], [[0, 0, 1], [0, 0, 1], [1, 0, 0]])
    np.testing.assert_allclose(box.penetration_depth(pts, 0.005), [-0.005, 0.01, 0.0, 0.006], atol=1e-12)
    np.testing.assert_allclose(box.keep_inside([0.079, 0.001, 0.03], 0.01), [0.07, 0.01, 0.03])


def test_a_box_stl_answers_like_the_box():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-0.02, 0.1, (1500, 3))
    box, stl = BoxShape(SIZE), _box_stl()
    np.testing.assert_allclose(stl.clearance(pts), box.clearance(pts), atol=1e-6)  # trimesh: within 1 um
    # projections agree wherever the nearest face is unique (away from the box's edges)
    qb, nb = box.project(pts)
    qs, ns = stl.project(pts)
    planes = np.sort(np.abs(np.concatenate([pts, SIZE - pts], axis=1)), axis=1)
    clear = (planes[:, 1] - planes[:, 0] > 1e-3) & np.all((pts > 0) & (pts < SIZE), axis=1)
    assert clear.sum() > 100
    np.testing.assert_allclose(qs[clear], qb[clear], atol=1e-4)  # trimesh: within 0.1 mm
    np.testing.assert_allclose(ns[clear], nb[clear], atol=1e-9)


def test_dome_distances_match_the_sphere(dome):
    rng = np.random.default_rng(1)
    # points around the cap, well above the flat base, within 10 mm of the sphere
    d = rng.normal(size=(300, 3))
    d[:, 2] = np.abs(d[:, 2]) + 1.5
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    pts = CENTRE + d * (R + rng.uniform(-0.008, 0.01, (300, 1)))
    ok = pts[:, 2] > 0.012
    exact = np.linalg.norm(pts - CENTRE, axis=1) - R
    # the STL is a tessellation of the sphere (24 rings x 64 segments): chord sag < 0.3 mm
    np.testing.assert_allclose(dome.clearance(pts[ok]), exact[ok], atol=3e-4)
    q, n = dome.project(pts[ok])
    radial = (q - CENTRE) / np.linalg.norm(q - CENTRE, axis=1, keepdims=True)
    assert np.degrees(np.arccos(np.clip(np.sum(n * radial, axis=1), -1, 1))).max() < 8.0
    assert dome.size == pytest.approx([2 * A, 2 * A, H], abs=1e-9) and dome.lower == pytest.approx([0, 0, 0], abs=1e-9)


def test_keep_inside_fits_a_sphere_under_a_curved_surface(dome):
    for start in ([A, A, H], [0.05, 0.04, 0.02], [0.01, A, 0.004], [A + 0.02, A - 0.02, 0.03]):
        c = dome.keep_inside(np.array(start, float), 0.008)
        assert dome.clearance(c[None])[0] <= -0.008 * 0.99, (start, c)


def test_rest_shape_names_the_file_of_a_bad_stl(tmp_path):
    import trimesh

    m = trimesh.creation.box(extents=SIZE)
    open_mesh = trimesh.Trimesh(m.vertices, m.faces[:-2], process=False)
    path = tmp_path / "phantom.stl"
    open_mesh.export(path)
    with pytest.raises(ValueError, match="phantom.stl.*watertight"):
        rest_shape(SIZE, path)
    assert isinstance(rest_shape(SIZE), BoxShape)


def test_presses_into_a_dome_and_into_the_box_top(dome):
    # two pokes into the dome along its normals, 2 mm deep with a 5 mm sphere, with a
    # pause clear of it between them
    r = 0.005
    dirs = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]])
    path = []
    for u in dirs:
        surf = CENTRE + R * u
        for depth in (-0.01, -0.004, 0.0, 0.002, 0.001, -0.004, -0.01):
            path.append(surf + (r - depth) * u)
    pts, nrm = surface_presses(np.array(path), dome, r)
    assert len(pts) == 2
    np.testing.assert_allclose(pts, CENTRE + R * dirs, atol=4e-4)
    assert np.all(np.sum(nrm * dirs, axis=1) > np.cos(np.radians(8)))
    # the box keeps its top presses (z at the top, normal +z); a press into a side is not one
    box = BoxShape(SIZE)
    top = [[0.03, 0.02, 0.05 + r - d] for d in (-0.01, 0.003, -0.01)]
    side = [[0.08 + r - d, 0.02, 0.03] for d in (-0.01, 0.003, -0.01)]
    pts, nrm = surface_presses(np.array(top + side), box, r)
    np.testing.assert_allclose(pts, [[0.03, 0.02, 0.05]])
    np.testing.assert_allclose(nrm, [[0.0, 0.0, 1.0]])


def test_an_inclusion_on_a_dome_starts_and_stays_inside_it(dome):
    presses = np.array([CENTRE + R * np.array([0.0, 0.0, 1.0]), CENTRE + R * np.array([0.0, 0.6, 0.8])])
    ctx = PhantomContext(dome.size, 0.005, presses, (presses - CENTRE) / R, dome)
    space = EFFECT_KINDS["inclusion"].fit_space(ctx)
    assert len(space.starts) == 2
    for x, p in zip(space.starts, presses):
        # 12 mm under each press along the inward normal, clear of the surface by its radius
        assert np.linalg.norm(x[:3] - (p - 0.012 * (p - CENTRE) / R)) < 1e-3
        assert dome.clearance(x[None, :3])[0] <= -x[3] * 0.99
    rng = np.random.default_rng(2)
    for _ in range(20):
        x = space.clip(rng.uniform(space.lower, space.upper))
        assert dome.clearance(x[None, :3])[0] <= -x[3] * 0.99
    # the kind's sized effect and its detectability assumption lie inside too
    assumed = EFFECT_KINDS["inclusion"].assumptions(ctx)
    assert len(assumed) == len(presses) == 2  # one under each press
    for a in assumed:
        eff = EFFECT_KINDS["inclusion"].sized(4.0, ctx, **a)
        assert dome.clearance(np.asarray(eff.center)[None])[0] <= -eff.radius * 0.99
    ex = EFFECT_KINDS["inclusion"].example(ctx, np.random.default_rng(3))
    assert dome.clearance(np.asarray(ex.center)[None])[0] <= -ex.radius * 0.99
    # with no press, the default press point is the dome's apex (the box's: the top's middle)
    p, n = PhantomContext(dome.size, 0.005, shape=dome).default_press()
    np.testing.assert_allclose(p, CENTRE + [0.0, 0.0, R], atol=2e-4)
    assert n[2] > np.cos(np.radians(3))
    p, n = PhantomContext(SIZE, 0.005).default_press()
    np.testing.assert_allclose(p, [SIZE[0] / 2, SIZE[1] / 2, SIZE[2]])
    np.testing.assert_allclose(n, [0.0, 0.0, 1.0])


def test_placements_beside_an_inclusion_lie_one_radius_along_the_surface_at_its_depth(dome):
    """Inclusion.beside: the detectability statement's "10 mm to the side of the best
    placement": four spheres at the same depth under the surface, 10 mm away along it, inside
    the phantom. On the box's top they move in x and y at z = top - 12 mm; on the dome they
    stay 12 mm under its curved surface."""
    cls = EFFECT_KINDS["inclusion"]
    box = PhantomContext(SIZE, 0.005, np.array([[0.03, 0.02]]))
    (a,) = cls.assumptions(box)
    near = cls.beside(box, a)
    assert len(near) == 4
    moves = np.array([np.asarray(b["center"]) - np.asarray(a["center"]) for b in near])
    np.testing.assert_allclose(np.abs(moves).sum(axis=1), 0.010, atol=1e-9)  # one axis, 10 mm
    np.testing.assert_allclose(moves[:, 2], 0.0, atol=1e-12)  # same depth under the top
    assert {tuple(np.sign(np.round(m[:2] * 1e3))) for m in moves} == {(1, 0), (-1, 0), (0, 1), (0, -1)}
    press = CENTRE + R * np.array([0.0, 0.0, 1.0])  # the apex
    ctx = PhantomContext(dome.size, 0.005, press[None], ((press - CENTRE) / R)[None], dome)
    (a,) = cls.assumptions(ctx)
    for b in cls.beside(ctx, a):
        c = np.asarray(b["center"])
        assert abs(dome.clearance(c[None])[0] + 0.012) < 1e-3  # inside, 12 mm under the surface
        # 10 mm along the surface is 10 (R - 12 mm) / R at the sphere's depth
        assert np.linalg.norm(c - np.asarray(a["center"])) == pytest.approx(0.010 * (R - 0.012) / R, rel=0.1)
    # kinds without a placement have none beside
    assert EFFECT_KINDS["gravity"].beside(box, {"direction": [0, 0, -1]}) == ()
