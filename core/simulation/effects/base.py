"""Base declarations of the effect kinds: :class:`Effect`, :class:`FitSpace`,
:class:`PhantomContext` (see :mod:`core.simulation.effects`)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Callable, ClassVar

import numpy as np

from core.errors import SimulationError
from core.preparation.shape import BoxShape, RestShape

if TYPE_CHECKING:  # pragma: no cover
    from core.simulation.model import ModelBuilder
    from core.preparation.probe import ProbePath

__all__ = ["PhantomContext", "FitSpace", "Effect"]


@dataclass(frozen=True)
class PhantomContext:
    """What a kind's fit space, sizes and examples need to know of a session.

    Attributes:
        size: (3,) float64 box size, m (x length, y width, z height), phantom frame; for a
            phantom of another shape, the upper corner of its bounds.
        probe_radius: the nominal probe radius of session.json, m.
        presses: (K, 3) float64, m, phantom frame: the rest-surface point under the
            deepest point of each press (may be empty). An inclusion changes the data only
            near where the probe pressed. (K, 2) (x, y) is read as presses into the top of
            the box (z = ``size[2]``).
        press_normals: (K, 3) float64 outward unit normals of the rest surface at
            ``presses``; None: +z (presses into the box's top).
        shape: the rest phantom (:class:`core.preparation.shape.RestShape`); None: the box
            ``[0, size]``.

    Raises:
        SimulationError: a size that is not 3 positive lengths, or presses and normals
            of different counts.
    """

    size: np.ndarray
    probe_radius: float = 0.005
    presses: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    press_normals: np.ndarray | None = None
    shape: RestShape | None = None

    def __post_init__(self):
        size = np.asarray(self.size, dtype=np.float64).reshape(-1)
        if size.shape != (3,) or not np.all(size > 0):
            raise SimulationError(f"phantom size must be 3 positive lengths in m, got {self.size!r}")
        object.__setattr__(self, "size", size)
        object.__setattr__(self, "probe_radius", _positive("probe radius", self.probe_radius))
        pr = np.asarray(self.presses, dtype=np.float64)
        pr = pr.reshape(-1, pr.shape[-1] if pr.ndim == 2 else 3) if pr.size else np.zeros((0, 3))
        if pr.shape[1] == 2:
            pr = np.column_stack([pr, np.full(len(pr), size[2])])
        if pr.shape[1] != 3:
            raise SimulationError(f"presses must be (K, 2) or (K, 3) points, got shape {pr.shape}")
        nrm = (np.tile([0.0, 0.0, 1.0], (len(pr), 1)) if self.press_normals is None
               else np.asarray(self.press_normals, dtype=np.float64).reshape(-1, 3))
        if nrm.shape != pr.shape:
            raise SimulationError(f"{len(pr)} presses but {len(nrm)} press normals")
        object.__setattr__(self, "presses", pr)
        object.__setattr__(self, "press_normals", nrm)
        object.__setattr__(self, "shape", self.shape if self.shape is not None else BoxShape(size))

    def under(self, depth: float) -> np.ndarray:
        """(K, 3) float64, m: the points ``depth`` (m) under each press, along the inward
        normal (for the box's top presses: ``size[2] - depth`` below each (x, y))."""
        return self.presses - float(depth) * self.press_normals

    def default_press(self) -> tuple[np.ndarray, np.ndarray]:
        """The rest-surface point (3,) and outward normal (3,) used when nothing was
        pressed: the middle of the box's top, or the highest point of another shape
        (:meth:`core.preparation.shape.RestShape.summit`)."""
        return self.shape.summit()


@dataclass(frozen=True)
class FitSpace:
    """One effect kind as a fit problem.

    Fit variables are in units where the data are close to linear in them (log10 for
    scale parameters, metres and seconds otherwise).

    Attributes:
        kind: effect kind (SESSION_FORMAT.md).
        names: names of the fit variables. units: their units, for reports.
        steps: (n,) finite-difference step of each variable.
        lower, upper: (n,) bounds of each variable.
        starts: starting vectors (the best of them by train misfit is refined). Kinds
            whose signature vanishes at the base model (an inclusion of ratio 1 has no
            centre to differentiate) or is strongly nonlinear start from a small grid.
        to_effect: vector -> effect dict ``{"kind": ..., **parameters}`` (SI, phantom frame).
        to_parameters: vector -> the SESSION_FORMAT parameters of the kind.
        project: optional map of a bounded vector onto the feasible set, for
            constraints that couple variables (an inclusion's sphere inside the box).
        searches: how many effectively separate places the fit searches (an inclusion's
            starting locations): a claim's look-elsewhere factor.
        absent: ``((name, value), ...)``: the variables' values without the effect (an
            inclusion's ``log10_stiffness_ratio`` 0, a clock offset 0); ``inf`` or ``-inf``
            where the effect vanishes beyond that variable's bound (a base's
            ``log10_stiffness``). A claim whose 95 % interval over the model-form worlds
            holds every one of them cannot be told from no effect
            (:func:`core.diagnosis.worlds.absence_within`).
        open_ends: the bounds that are not the kind's plausible range but the phantom's
            geometry or the fit's resolution: ``"name"`` (both of that variable's bounds),
            ``"name:lower"`` or ``"name:upper"`` (an inclusion's centre stays inside the
            phantom, its radius at least 3 mm). A fit at any other bound (:meth:`at_bound`)
            asked for more of the kind than a phantom plausibly holds.
    """

    kind: str
    names: tuple[str, ...]
    units: tuple[str, ...]
    steps: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    starts: tuple[np.ndarray, ...]
    to_effect: Callable[[np.ndarray], dict]
    to_parameters: Callable[[np.ndarray], dict]
    project: Callable[[np.ndarray], np.ndarray] | None = None
    searches: int = 1
    absent: tuple[tuple[str, float], ...] = ()
    open_ends: tuple[str, ...] = ()

    def at_bound(self, x: np.ndarray) -> list[str]:
        """The variables of ``x`` (n,) that sit within one step (:attr:`steps`) of a bound
        that is the kind's plausible range (not one of :attr:`open_ends`), as
        ``"name at its lower bound -1"`` strings for a report; [] when none does."""
        x = np.asarray(x, dtype=np.float64).reshape(-1)[: len(self.names)]
        out = []
        for j, name in enumerate(self.names):
            for side, bound, near in (("lower", self.lower[j], x[j] <= self.lower[j] + self.steps[j]),
                                      ("upper", self.upper[j], x[j] >= self.upper[j] - self.steps[j])):
                if near and name not in self.open_ends and f"{name}:{side}" not in self.open_ends:
                    out.append(f"{name} at its {side} bound {bound:.4g}")
        return out

    def clip(self, x: np.ndarray) -> np.ndarray:
        """``x`` clipped to the bounds, then projected onto the feasible set, (n,) float64."""
        x = np.clip(np.asarray(x, dtype=np.float64), self.lower, self.upper)
        return x if self.project is None else self.project(x)


def _a(*v) -> np.ndarray:
    return np.array(v, dtype=np.float64)


@dataclass(frozen=True)
class Effect:
    """Base class of the effect kinds (see the module docstring). Subclasses set the
    class attributes and override the hooks they need.

    Class attributes:
        kind: the SESSION_FORMAT.md name.
        acts_on: "body" (the truth FEM carries it) or "input" (the probe input).
        scales_with_youngs: scaling E leaves the model's displacements unchanged and
            scales its forces (its stiffnesses are ratios of E, or it acts on the input);
            gravity (a fixed body force) and a foundation (a fixed stiffness in Pa/m) set
            a scale for E of their own.
        size_unit: unit of :meth:`size`.
        reference_size: a size that our lab's data show clearly: signatures for
            detectability are simulated at it and scaled.
        max_size: the largest size a phantom experiment plausibly has; a kind that
            would not be claimed even at this size "cannot be told" from the data.
    """

    kind: ClassVar[str] = ""
    acts_on: ClassVar[str] = "body"
    scales_with_youngs: ClassVar[bool] = True
    size_unit: ClassVar[str] = ""
    reference_size: ClassVar[float] = 1.0
    max_size: ClassVar[float] = math.inf

    def configure(self, builder: "ModelBuilder") -> None:
        """Change the model under construction (default: nothing)."""

    def transform_probe(self, path: "ProbePath", radius: float) -> tuple["ProbePath", float]:
        """Map the calibrated probe input to the true one (default: unchanged)."""
        return path, radius

    moves_clock: ClassVar[bool] = False
    """Whether the effect moves the probe input along time (:meth:`clock_shift`)."""

    moves_contact: ClassVar[bool] = False
    """Whether the effect moves where and how deep the probe presses (the probe's position
    or size): a replay's mesh error, which grows with the press, then differs from the
    model's without it, so a fine-minus-coarse discrepancy measured on that model does
    not carry over (the diagnosis measures it again at the fit,
    :meth:`core.diagnosis.evidence.Evidence.discrepancy_at`)."""

    def clock_shift(self) -> float:
        """How far (s) the effect moves the probe input along time: the replay's step
        grid moves with it (:func:`core.simulation.timeloop.step_grid`), default 0."""
        return 0.0

    def at_youngs(self, ratio: float) -> "Effect":
        """This effect when E is scaled by ``ratio`` and only its parameters' ratios to E are
        known (they were fitted to surface data, which measure a stiffness over E): the
        same effect for a kind that scales with E or acts on the input; a fixed stiffness
        (a foundation, Pa/m) scales with it. Gravity, a body force of known size, stays.

        Args:
            ratio: E_new / E at which the effect was fitted (> 0).
        """
        return self

    @classmethod
    def sets_youngs_scale(cls, effect: dict, *, fitted_over_youngs: bool = False) -> bool:
        """Whether the effect, as given in a session's or trial's effect dict, sets a scale
        for E (Pa) without force data: a nonzero body force (gravity) or a foundation of
        fixed stiffness in Pa/m (base compliance). Every other kind leaves the quasi-static
        model invariant to scaling E (:attr:`scales_with_youngs`) and sets none: the default
        is ``not scales_with_youngs``, which the two kinds that set one refine per instance.

        Args:
            effect: ``{"kind": cls.kind, **parameters}``, parameters as in SESSION_FORMAT.md
                (missing ones take the kind's defaults); read as given, not validated.
            fitted_over_youngs: the effect's parameters were fitted to surface data at some E
                and move with E (``Trial.effects_youngs``, :meth:`at_youngs`): a stiffness so
                fitted is known only over E and sets no scale; a body force stays.

        Raises:
            ValueError, TypeError: a parameter the kind reads is not numeric (gravity's ``g``).
        """
        return not cls.scales_with_youngs

    def to_dict(self) -> dict:
        """``{"kind": ..., **parameters}`` as in truth.json / diagnosis.json (lists, not arrays)."""
        out = {"kind": self.kind}
        for k, v in asdict(self).items():
            out[k] = np.asarray(v).tolist() if isinstance(v, (tuple, list, np.ndarray)) else float(v)
        return out

    # ---- declarations read by the diagnosis, the planner and the lab ---------------
    def size(self, ctx: PhantomContext) -> float:
        """The kind's size measure (SESSION_FORMAT.md ``detectability`` table), >= 0."""
        raise NotImplementedError

    @classmethod
    def strength(cls, size: float) -> float:
        """The coordinate in which the data change about linearly with the size, zero
        without the effect (the size itself, except for a stiffness ratio)."""
        return float(size)

    @classmethod
    def size_at(cls, strength: float) -> float:
        """Inverse of :meth:`strength`."""
        return float(strength)

    @classmethod
    def assumptions(cls, ctx: PhantomContext) -> tuple[dict, ...]:
        """The parameters a detectability statement assumes besides the size: one dict per
        placement or direction considered (see ``assume``)."""
        return ({},)

    assumed_over: ClassVar[str] = "directions"
    """What the several :meth:`assumptions` range over, in words for reports."""

    assume: ClassVar[str] = "least_detectable"
    """Of several :meth:`assumptions`, the detectability statement takes the
    "least_detectable" (a direction: the size that shows in every direction) or the
    "most_detectable" (a placement: "best-placed under the palpated region")."""

    beside_distance: ClassVar[float | None] = None
    """For a placed kind ("most_detectable"), how far (m) to the side of its best placement
    the detectability statement also says how large it would have to be
    (:meth:`beside`); None: the kind has no placement."""

    @classmethod
    def beside(cls, ctx: PhantomContext, assumed: dict) -> tuple[dict, ...]:
        """Placements :attr:`beside_distance` to the side of the ``assumed`` one (the same
        parameters otherwise), for the statement's "and this far away from it"; empty for a
        kind without a placement."""
        return ()

    @classmethod
    def sized(cls, size: float, ctx: PhantomContext, **assumed) -> "Effect":
        """An effect of this kind of ``size`` with the ``assumed`` parameters."""
        raise NotImplementedError

    @classmethod
    def fit_space(cls, ctx: PhantomContext) -> FitSpace:
        """The kind as a fit problem on the phantom of ``ctx``."""
        raise NotImplementedError

    @classmethod
    def example(cls, ctx: PhantomContext, rng: np.random.Generator) -> "Effect":
        """A detectable instance of the kind, for the virtual lab's scenarios."""
        raise NotImplementedError


def _vec3(name: str, value) -> tuple[float, float, float]:
    arr = np.asarray(value, dtype=np.float64).reshape(-1)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise SimulationError(f"{name} must be 3 finite numbers, got {value!r}")
    return tuple(float(v) for v in arr)


def _positive(name: str, value) -> float:
    v = float(value)
    if not np.isfinite(v) or v <= 0:
        raise SimulationError(f"{name} must be positive, got {value!r}")
    return v


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    n = float(np.linalg.norm(v))
    if not n > 0:
        raise SimulationError(f"a direction must be non-zero, got {v!r}")
    return v / n


_AXES = ({"direction": [1.0, 0.0, 0.0]}, {"direction": [0.0, 1.0, 0.0]}, {"direction": [0.0, 0.0, 1.0]})


