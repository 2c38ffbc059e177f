"""Effect kinds of ``SESSION_FORMAT.md``: each one class that declares everything about it.

A kind's class is

- **a model option**: it changes the model only through the
  :class:`~core.simulation.model.ModelBuilder` hooks (per-element stiffness, supports,
  body forces, extra stress terms, contact friction) or the probe input (radius, clock,
  position); the solver has no effect-specific branches;
- **a fit problem**: :meth:`Effect.fit_space` gives its fit variables, units, steps,
  bounds and starts on a given phantom (:class:`FitSpace`);
- **a size**: :meth:`Effect.size` is the kind's size measure of ``SESSION_FORMAT.md``
  (the ``detectability`` table), :meth:`Effect.sized` an effect of a given size with the
  parameters a detectability statement assumes (:meth:`Effect.assumptions`);
- **a role**: ``acts_on`` ("body": the truth FEM carries it; "input": it changes the
  probe input and the recorded kinematics), ``scales_with_youngs`` (whether the
  model's displacements stay unchanged and its forces scale with E when E scales) and
  :meth:`Effect.sets_youngs_scale` (whether an instance sets a scale for E without force
  data, which the E fit's structural identifiability asks);
- **an example**: :meth:`Effect.example`, a detectable instance for the virtual lab.

The diagnosis, the planner and the lab read these declarations; a ninth kind is one new
class here (and its tests). Names and parameters match the effect table of
``SESSION_FORMAT.md``; positions are in the phantom frame, SI units throughout.
"""

from __future__ import annotations

import dataclasses

from core.errors import SimulationError
from core.simulation.effects.base import Effect, FitSpace, PhantomContext
from core.simulation.effects.body import BaseCompliance, Friction, Gravity, Inclusion, Viscoelasticity
from core.simulation.effects.inputs import KinematicOffset, ProbeRadius, TimeOffset

__all__ = [
    "PhantomContext",
    "FitSpace",
    "Effect",
    "Gravity",
    "Inclusion",
    "Viscoelasticity",
    "Friction",
    "BaseCompliance",
    "ProbeRadius",
    "TimeOffset",
    "KinematicOffset",
    "EFFECT_KINDS",
    "effect_class",
    "effect_from_dict",
]


EFFECT_KINDS: dict[str, type[Effect]] = {
    cls.kind: cls
    for cls in (Gravity, Inclusion, Viscoelasticity, Friction, BaseCompliance, ProbeRadius, TimeOffset, KinematicOffset)
}


def effect_class(kind: str) -> type[Effect]:
    """The class of effect ``kind``.

    Raises:
        SimulationError: an unknown kind (the message lists the known ones).
    """
    if kind not in EFFECT_KINDS:
        raise SimulationError(f"unknown effect kind {kind!r}; expected one of {sorted(EFFECT_KINDS)}")
    return EFFECT_KINDS[kind]


def effect_from_dict(d: dict) -> Effect:
    """Build an effect from ``{"kind": ..., **parameters}``; missing parameters take defaults.

    Raises:
        SimulationError: unknown kind, unknown parameter, or invalid value.
    """
    if not isinstance(d, dict) or "kind" not in d:
        raise SimulationError(f"an effect must be a dict with a 'kind', got {d!r}")
    kind = d["kind"]
    cls = effect_class(kind)
    params = {k: v for k, v in d.items() if k != "kind"}
    allowed = {f.name for f in dataclasses.fields(cls)}
    unknown = set(params) - allowed
    if unknown:
        raise SimulationError(f"effect {kind!r} has no parameter(s) {sorted(unknown)}; it takes {sorted(allowed)}")
    return cls(**params)
