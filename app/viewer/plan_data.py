"""What the viewer shows of a palpation plan (issue 19, item 4), written by the plan job
beside the planner's ``plan.json``, ``plan.md`` and ``kinematics.csv``.

``plan_view.json`` (phantom frame, SI): the phantom's rest ``size`` (3,) m and the
probe ``radius`` m; the probe path ``t`` (K,) s and ``centres`` (K, 3) m (the sphere's
centre, as ``plan.json``'s ``path_phantom``); ``contact`` (K,) whether the sphere touches
or presses the rest phantom there (``core.preparation.shape.RestShape.penetration_depth`` > 0); the
``moves`` with the index where each first touches (``start``), their names and
descriptions; the plan's ``description`` lines, ``targets``, ``predicted`` and
``current`` sizes with their units, and ``record_force``. A phantom given by
``phantom.stl`` adds its rest ``surface`` (``vertices`` (V, 3) m, ``faces`` (T, 3)), which
the viewer draws instead of the box ``[0, size]``, and its contact flags are measured
against that surface.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

__all__ = ["PLAN_VIEW", "plan_view", "write_plan_view", "load_plan_view"]

PLAN_VIEW = "plan_view.json"


def plan_view(plan, size, radius: float, stl=None) -> dict:
    """The viewer's description of ``plan`` (module docstring).

    Args:
        plan: a ``core.diagnosis.planner.Plan``. size: (3,) the phantom's rest size, m.
        radius: the probe sphere's radius, m.
        stl: the session's ``phantom.stl`` (the rest surface), or None for a box.

    Returns:
        the ``plan_view.json`` dict.

    Raises:
        MeshingError: ``stl`` is not a usable phantom surface
            (:func:`core.simulation.meshing.check_stl`).
    """
    from core.preparation.shape import BoxShape, SurfaceShape
    from core.simulation.effects import EFFECT_KINDS

    centres = np.asarray(plan.path_phantom, float).reshape(-1, 3)
    surface = None
    if stl is None:
        shape = BoxShape(size)
    else:
        from core.simulation.meshing import check_stl

        surface = check_stl(stl)
        shape = SurfaceShape(surface.vertices, surface.faces)
    contact = (shape.penetration_depth(centres, float(radius)) > 0.0) if len(centres) else np.zeros(0, dtype=bool)
    # each move's first touch, in path order: moves are pressed one after the other
    touches = np.flatnonzero(contact & ~np.concatenate([[False], contact[:-1]]))
    moves = []
    for i, m in enumerate(plan.moves):
        moves.append({"name": m.name, "description": m.description, "face": m.face,
                      "start": int(touches[i]) if i < touches.size else None})
    units = {k: EFFECT_KINDS[k].size_unit for k in set(plan.predicted) | set(plan.current) if k in EFFECT_KINDS}
    return {
        "size": [float(v) for v in size],
        "radius": float(radius),
        "t": np.asarray(plan.path_t, float).tolist(),
        "centres": centres.tolist(),
        "contact": contact.tolist(),
        "moves": moves,
        "description": list(plan.description),
        "targets": dict(plan.targets),
        "predicted": dict(plan.predicted),
        "current": dict(plan.current),
        "units": units,
        "record_force": bool(plan.record_force),
        **({} if surface is None else {"surface": {"vertices": np.asarray(surface.vertices, float).tolist(),
                                                   "faces": np.asarray(surface.faces, int).tolist()}}),
    }


def write_plan_view(plan, size, radius: float, out, stl=None) -> Path:
    """Write ``plan_view.json`` (:func:`plan_view`; ``stl``: the session's ``phantom.stl``
    or None) into the folder ``out``; returns its path."""
    path = Path(out) / PLAN_VIEW
    path.write_text(json.dumps(plan_view(plan, size, radius, stl), indent=1))
    return path


def load_plan_view(folder) -> dict:
    """Read a plan job's ``plan_view.json``.

    Raises:
        FileNotFoundError: the folder holds no plan view (not a finished plan job).
    """
    path = Path(folder) / PLAN_VIEW
    if not path.exists():
        raise FileNotFoundError(f"{folder}: no {PLAN_VIEW} (not a finished plan job)")
    return json.loads(path.read_text())
