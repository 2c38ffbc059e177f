"""The candidate causes: each effect kind of SESSION_FORMAT.md as a fittable parameter vector.

The fit spaces are declared by the kinds themselves (:meth:`core.simulation.effects.Effect.fit_space`);
this module gives them for a session's phantom, and finds where the probe pressed into the
top face (an inclusion's fits start below those points).
"""

from __future__ import annotations

import numpy as np

from core.simulation.effects import EFFECT_KINDS, FitSpace, PhantomContext

__all__ = ["Candidate", "candidates", "top_presses", "KINDS"]

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
    out: list[np.ndarray] = []
    edges = np.flatnonzero(np.diff(np.concatenate([[0], pressed.astype(np.int8), [0]])))
    for a, b in zip(edges[::2], edges[1::2]):
        k = a + int(np.argmax(depth[a:b]))
        p = c[k, :2]
        if all(np.linalg.norm(p - q) >= merge for q in out):
            out.append(p)
    return np.array(out).reshape(-1, 2)
