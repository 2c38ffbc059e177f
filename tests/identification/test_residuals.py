"""The identification's signed residuals on any mesh (the box's top face, any STL's
upward surface)."""

import numpy as np
import pytest
import trimesh

from core.identification.residuals import signed_residuals, surface_residuals, top_residuals
from core.lab.shapes import dome_surface
from core.simulation import box_mesh
from core.simulation.meshing import tetrahedralise
from tests._shapes import DOME_BASE_RADIUS, DOME_CENTRE, DOME_SPHERE_RADIUS, cap_directions


@pytest.fixture(autouse=True)
def _own_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("TISSUETWIN_CACHE_DIR", str(tmp_path / "cache"))


def test_points_off_a_dome_give_their_signed_distance(tmp_path):
    """Points 1 mm outside and 1 mm inside the dome's cap (of radius 37 mm) along the
    sphere's normal read +1 and -1 mm, within the chord error of 5 mm elements; the
    flat base and points 2 cm away are not used."""
    V, F = dome_surface()
    stl = tmp_path / "dome.stl"
    trimesh.Trimesh(V, F).export(str(stl))
    mesh = tetrahedralise(stl, 0.005)
    R, centre = DOME_SPHERE_RADIUS, DOME_CENTRE
    d = cap_directions(400, 0, lift=2.0)  # directions well up the cap
    for offset in (+0.001, -0.001):
        res = surface_residuals(centre + (R + offset) * d, mesh.nodes, mesh)
        assert res.size >= 390  # a few near the rim face the side (n_z < 0.5)
        assert np.median(res) == pytest.approx(offset, abs=0.25e-3)
    assert surface_residuals(centre + (R + 0.02) * d, mesh.nodes, mesh).size == 0
    a = DOME_BASE_RADIUS
    below = np.array([[a, a, -0.001], [a + 0.01, a, -0.002]])
    assert surface_residuals(below, mesh.nodes, mesh).size == 0


def test_on_the_box_grid_they_are_the_top_residuals():
    size = np.array([0.0687, 0.0393, 0.0358])
    mesh = box_mesh(size)
    rng = np.random.default_rng(1)
    pts = np.column_stack([rng.uniform(0.01, 0.06, 50), rng.uniform(0.01, 0.03, 50), size[2] + rng.normal(0, 1e-3, 50)])
    np.testing.assert_array_equal(signed_residuals(pts, mesh.nodes, mesh, size), top_residuals(pts, mesh.nodes, mesh.grid, size))
