"""The candidate causes: each effect kind of SESSION_FORMAT.md as a fittable parameter vector.

The fit spaces are declared by the kinds themselves (:meth:`core.simulation.effects.Effect.fit_space`);
this module gives them for a session's phantom, and finds where the probe pressed into it
(the box's top face, or any part of another shape's surface): an inclusion's fits start
below those points.
"""

from __future__ import annotations

import numpy as np

from core.preparation.shape import RestShape
from core.simulation.effects import EFFECT_KINDS, FitSpace, PhantomContext

__all__ = ["Candidate", "candidates", "top_presses", "surface_presses", "phantom_context", "press_spans", "KINDS"]

KINDS = tuple(EFFECT_KINDS)
"""Every effect kind of SESSION_FORMAT.md, in the order of the effect table."""

Candidate = FitSpace
"""A candidate cause: the fit space of its kind (:class:`core.simulation.effects.FitSpace`)."""


def candidates(size, probe_radius: float, presses: np.ndarray | None = None) -> dict[str, FitSpace]:
    """All candidate causes for a phantom of ``size`` (3,) m and a probe of ``probe_radius`` m.

    Args:
        presses: (K, 2) float64, m, phantom frame: (x, y) where the probe pressed into the
            top face in the train sequences (:func:`top_presses`); an inclusion's fits start
            below these points (without any, from a 3 x 2 grid over the top).
    """
    ctx = PhantomContext(np.asarray(size, dtype=np.float64), float(probe_radius),
                         np.zeros((0, 2)) if presses is None else np.asarray(presses, dtype=np.float64).reshape(-1, 2))
    return {kind: cls.fit_space(ctx) for kind, cls in EFFECT_KINDS.items()}


def top_presses(centres: np.ndarray, size, probe_radius: float, *, min_depth: float = 0.001, merge: float = 0.005) -> np.ndarray:
    """(K, 2) float64, m: (x, y) of the deepest point of each press into the top face.

    Args:
        centres: (T, 3) probe sphere centres, m, phantom frame (a sequence's path at its
            frame times).
        size: (3,) box size, m. probe_radius: m.
        min_depth: a press reaches at least this far below the rest top, m.
        merge: presses closer than this (m) to an earlier one are dropped.
    """
    c = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    sx, sy, sz = (float(v) for v in size)
    depth = sz - (c[:, 2] - probe_radius)
    over = (c[:, 0] > 0) & (c[:, 0] < sx) & (c[:, 1] > 0) & (c[:, 1] < sy)
    pressed = over & (depth > min_depth)
    pts = c[[a + int(np.argmax(depth[a:b])) for a, b in press_spans(pressed)], :2].reshape(-1, 2)
    return pts[_spread(pts, merge)]


def surface_presses(centres: np.ndarray, shape: RestShape, probe_radius: float, *, min_depth: float = 0.001,
                    merge: float = 0.005) -> tuple[np.ndarray, np.ndarray]:
    """Where the probe pressed into the rest phantom ``shape``: the rest-surface point
    under the deepest point of each press and the outward normal there.

    On the box (:class:`core.preparation.shape.BoxShape`) these are the presses into the
    top face (:func:`top_presses`, at z = the box's height, normal +z), as before the
    phantom could take any shape; on any other shape, every press whose sphere reaches
    ``min_depth`` into the rest surface, its point the surface's nearest to the sphere's
    centre at its deepest.

    Args:
        centres: (T, 3) probe sphere centres, m, phantom frame.
        shape: the rest phantom. probe_radius: m.
        min_depth: a press reaches at least this far into the rest surface, m.
        merge: presses closer than this (m) to an earlier one are dropped.

    Returns:
        (points (K, 3), normals (K, 3)) float64, m and unit vectors, phantom frame.
    """
    c = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    if shape.is_box:
        xy = top_presses(c, shape.size, probe_radius, min_depth=min_depth, merge=merge)
        return np.column_stack([xy, np.full(len(xy), shape.size[2])]), np.tile([0.0, 0.0, 1.0], (len(xy), 1))
    depth = shape.penetration_depth(c, probe_radius) if c.size else np.zeros(0)
    deepest = [a + int(np.argmax(depth[a:b])) for a, b in press_spans(depth > min_depth)]
    if not deepest:
        return np.zeros((0, 3)), np.zeros((0, 3))
    pts, nrm = shape.project(c[deepest])
    keep = _spread(pts, merge)
    return pts[keep], nrm[keep]


def press_spans(pressed: np.ndarray) -> list[tuple[int, int]]:
    """The presses of a contact mask: ``[(start, stop), ...]`` frame index ranges (stop
    exclusive) of each run of True in ``pressed`` (T,) bool, in time order."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], np.asarray(pressed).astype(np.int8), [0]])))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2])]


def _spread(points: np.ndarray, merge: float) -> np.ndarray:
    """Indices of ``points`` (K, D) kept by a greedy pass in order: a point closer than
    ``merge`` (m) to one already kept is dropped."""
    keep: list[int] = []
    for i, p in enumerate(points):
        if all(np.linalg.norm(p - points[j]) >= merge for j in keep):
            keep.append(i)
    return np.array(keep, dtype=np.int64)


def phantom_context(prepared, names, *, merge: float = 0.005) -> PhantomContext:
    """The :class:`core.simulation.effects.PhantomContext` of a prepared session for the
    sequences ``names``: its size, nominal probe radius, rest shape, and the presses of
    those sequences (:func:`surface_presses`, merged across sequences closer than
    ``merge`` m).

    Args:
        prepared: a :class:`core.preparation.PreparedSession`. names: sequence names.

    Raises:
        KeyError: an unknown sequence. ValueError: the session's STL is not watertight.
    """
    shape = prepared.shape
    found = [surface_presses(prepared.sequences[n].probe.at(prepared.sequences[n].frame_times), shape,
                             prepared.probe_radius) for n in names]
    pts = np.concatenate([p for p, _ in found] + [np.zeros((0, 3))])
    nrm = np.concatenate([q for _, q in found] + [np.zeros((0, 3))])
    keep = _spread(pts, merge)
    return PhantomContext(prepared.size, prepared.probe_radius, pts[keep], nrm[keep], shape)
