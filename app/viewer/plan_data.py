"""What the viewer shows of a palpation plan (issue 19, item 4), written by the plan job
beside the planner's ``plan.json``, ``plan.md`` and ``kinematics.csv``.

``plan_view.json`` (phantom frame, SI): the phantom's rest ``size`` (3,) m and the
probe ``radius`` m; the probe path ``t`` (K,) s and ``centres`` (K, 3) m (the sphere's
centre, as ``plan.json``'s ``path_phantom``); ``contact`` (K,) whether the sphere touches
or presses the rest phantom there (``core.lab.probing.penetration_depth`` > 0); the
``moves`` with the index where each first touches (``start``), their names and
descriptions; the plan's ``description`` lines, ``targets``, ``predicted`` and
``current`` sizes with their units, and ``record_force``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

__all__ = ["PLAN_VIEW", "plan_view", "write_plan_view", "load_plan_view"]

PLAN_VIEW = "plan_view.json"


def plan_view(plan, size, radius: float) -> dict:
    """The viewer's description of ``plan`` (module docstring).

    Args:
        plan: a ``core.diagnosis.planner.Plan``. size: (3,) the phantom's rest size, m.
        radius: the probe sphere's radius, m.

    Returns:
        the ``plan_view.json`` dict.
    """
    from core.lab.probing import penetration_depth
    from core.simulation.effects import EFFECT_KINDS

    centres = np.asarray(plan.path_phantom, float)
    contact = penetration_depth(centres, size, radius) > 0.0
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
    }


def write_plan_view(plan, size, radius: float, out) -> Path:
    """Write ``plan_view.json`` into the folder ``out``; returns its path."""
    path = Path(out) / PLAN_VIEW
    path.write_text(json.dumps(plan_view(plan, size, radius), indent=1))
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
