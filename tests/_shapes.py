"""Phantom shapes shared by the tests: the box as a triangle surface, and the virtual
lab's default dome (:func:`core.lab.shapes.dome_surface`) with its sphere in closed form."""

import numpy as np

DOME_BASE_RADIUS = 0.035
"""The lab dome's base radius, m (its footprint is centred at (a, a))."""
DOME_HEIGHT = 0.025
"""Its height, m."""
DOME_SPHERE_RADIUS = (DOME_BASE_RADIUS**2 + DOME_HEIGHT**2) / (2 * DOME_HEIGHT)
"""The radius of the sphere its cap is cut from, m (about 37 mm)."""
DOME_CENTRE = np.array([DOME_BASE_RADIUS, DOME_BASE_RADIUS, DOME_HEIGHT - DOME_SPHERE_RADIUS])
"""That sphere's centre, m, phantom frame (below the support plane)."""


def box_surface(size):
    """The box ``[0, size]`` (m) as a watertight ``trimesh.Trimesh`` resting on z = 0."""
    import trimesh

    box = trimesh.creation.box(extents=np.asarray(size, dtype=np.float64))
    box.apply_translation(np.asarray(size, dtype=np.float64) / 2)
    return box


def cap_directions(n: int, seed: int, lift: float = 1.5) -> np.ndarray:
    """(n, 3) random unit directions from :data:`DOME_CENTRE` up the dome's cap (a normal
    draw with ``lift`` added to |z|: the larger, the nearer the apex)."""
    d = np.random.default_rng(seed).normal(size=(n, 3))
    d[:, 2] = np.abs(d[:, 2]) + lift
    return d / np.linalg.norm(d, axis=1, keepdims=True)
