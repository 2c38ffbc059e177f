"""Effect kinds that act on the probe input (its radius, clock and position)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from core.simulation.effects.base import _AXES, Effect, FitSpace, _a, _positive, _unit, _vec3

__all__ = ["ProbeRadius", "TimeOffset", "KinematicOffset"]


@dataclass(frozen=True)
class ProbeRadius(Effect):
    """The probe's true radius (m) differs from session.json's.

    A wrong radius also moved the robot calibration: SESSION_FORMAT.md places each
    corner touch's sphere centre at the corner plus (0, 0, radius) with the nominal
    radius, while the touching sphere's centre really was ``radius`` above the corner.
    Every touch target is then off by the same vertical shift, so the Kabsch fit's
    robot -> phantom transform is off by exactly that translation, and the calibrated
    centres sit ``radius - nominal`` below the true ones. The replay therefore moves the
    path up by ``radius - nominal`` along the phantom's z (the sphere's lowest point
    stays where the calibration put it) and uses the true radius: what a bigger probe
    changes is the width of the dent, not its depth. Without this shift a fit of the
    radius runs the wrong way (measured: 7.5 mm hidden, 4.8 mm fitted).
    """

    kind: ClassVar[str] = "probe_radius"
    acts_on: ClassVar[str] = "input"
    moves_contact: ClassVar[bool] = True
    size_unit: ClassVar[str] = "m"
    reference_size: ClassVar[float] = 0.002
    max_size: ClassVar[float] = 0.005
    radius: float = 0.006

    def __post_init__(self):
        object.__setattr__(self, "radius", _positive("probe radius", self.radius))

    def transform_probe(self, path, radius):
        return path.translated(np.array([0.0, 0.0, self.radius - float(radius)])), self.radius

    def size(self, ctx):
        return abs(float(self.radius) - float(ctx.probe_radius))

    @classmethod
    def assumptions(cls, ctx):
        return ({"sign": 1.0},)  # larger than recorded

    @classmethod
    def sized(cls, size, ctx, sign=1.0):
        return cls(radius=max(float(ctx.probe_radius) + math.copysign(float(size), sign), 1e-4))

    @classmethod
    def fit_space(cls, ctx):
        r0 = float(ctx.probe_radius)
        return FitSpace("probe_radius", ("radius",), ("m",), _a(0.0005), _a(0.2 * r0), _a(3.0 * r0), (_a(r0),),
                        lambda x: {"kind": "probe_radius", "radius": float(x[0])}, lambda x: {"radius": float(x[0])},
                        absent=(("radius", float(r0)),))

    @classmethod
    def example(cls, ctx, rng):
        return cls(radius=1.5 * float(ctx.probe_radius))


TIME_OFFSET_STARTS = (-0.2, -0.1, 0.0, 0.1, 0.2)
"""Starting clock offsets (s) of the time-offset fit."""

TIME_OFFSET_SEARCHES = 1
"""Look-elsewhere factor of the time-offset fit (its starts lie farther apart than the
~50 ms on which its misfit decorrelates; the best of them is refined)."""


@dataclass(frozen=True)
class TimeOffset(Effect):
    """Clock offset: the probe's true position at camera time t is the kinematics'
    position at ``t + offset`` (s)."""

    kind: ClassVar[str] = "time_offset"
    acts_on: ClassVar[str] = "input"
    size_unit: ClassVar[str] = "s"
    reference_size: ClassVar[float] = 0.1
    max_size: ClassVar[float] = 0.5
    offset: float = 0.1

    def __post_init__(self):
        object.__setattr__(self, "offset", float(self.offset))

    def transform_probe(self, path, radius):
        return path.shifted(-self.offset), radius

    moves_clock: ClassVar[bool] = True

    def clock_shift(self):
        return -self.offset

    def size(self, ctx):
        return abs(float(self.offset))

    @classmethod
    def assumptions(cls, ctx):
        return ({"sign": 1.0},)  # the robot's clock ahead of the camera's

    @classmethod
    def sized(cls, size, ctx, sign=1.0):
        return cls(offset=math.copysign(float(size), sign))

    @classmethod
    def fit_space(cls, ctx):
        # starts on a 0.1 s grid: Levenberg-Marquardt from 0 stuck at 0.007 s for a 0.15 s
        # offset. On a field session (other law and damping) the train misfit against the
        # offset is rough on a 25-50 ms scale (field seed 4, 0.15 s offset: chi2 drop beside
        # the nuisances 111 at 10 ms, 264 at 25 ms, 468 at 50 ms, 77 at 75 ms), so LM from
        # the best start can end short of a real offset (seed 4: at -0.4 ms, a miss). A 25 ms
        # grid reached it, but claimed clock offsets of about 24 ms that are not there, with
        # a look-elsewhere factor of 1 (fresh seed 6: -22 and -24 ms) and of 8 (no-effect
        # seed 908: -24 ms; seed 32 with a hidden inclusion: +24 ms); this grid claims
        # nothing on all four sessions (measured). A false claim costs more than that miss.
        # The roughness had two causes in the replay, both gone (2026-11-27): the step grid
        # stood still while the offset moved the probe along it, and the force was read at
        # the camera's times, so its samples slid along the model-form gap with the offset
        # (the robot's clock stamps the force as it does the kinematics: no offset moves it
        # now, :func:`core.simulation.timeloop.step_grid`). On field seed 64 (12 s, force,
        # a 0.15 s offset) the train drop then rises smoothly to a plateau at 0.10-0.15 s
        # (2064 at 50 ms, 3385 at 100 ms, 3466 at 150 ms, 2062 at 200 ms).
        return FitSpace("time_offset", ("offset",), ("s",), _a(0.03), _a(-1.0), _a(1.0),
                        tuple(_a(v) for v in TIME_OFFSET_STARTS),
                        lambda x: {"kind": "time_offset", "offset": float(x[0])}, lambda x: {"offset": float(x[0])},
                        searches=TIME_OFFSET_SEARCHES, absent=(("offset", 0.0),))

    @classmethod
    def example(cls, ctx, rng):
        return cls(offset=0.15)  # a few camera frames


@dataclass(frozen=True)
class KinematicOffset(Effect):
    """The probe really is at the calibrated position plus ``offset`` (m, phantom frame)."""

    kind: ClassVar[str] = "kinematic_offset"
    acts_on: ClassVar[str] = "input"
    moves_contact: ClassVar[bool] = True
    size_unit: ClassVar[str] = "m"
    reference_size: ClassVar[float] = 0.0015
    # the fit's own bound: a dVRK arm's calibration can be several mm off, and the lab's
    # 5 mm offset (field seed 11, no force) was claimed at 5.35 mm where, capped at 5 mm,
    # its vertical min_size (5.5 mm) read "none up to the largest plausible" and the
    # claim was withdrawn
    max_size: ClassVar[float] = 0.01
    offset: tuple[float, float, float] = (0.0, 0.0, -0.002)

    def __post_init__(self):
        object.__setattr__(self, "offset", _vec3("kinematic offset", self.offset))

    def transform_probe(self, path, radius):
        return path.translated(np.asarray(self.offset)), radius

    def size(self, ctx):
        return float(np.linalg.norm(self.offset))

    @classmethod
    def assumptions(cls, ctx):
        return _AXES

    @classmethod
    def sized(cls, size, ctx, direction=(0.0, 0.0, 1.0)):
        return cls(offset=tuple(float(size) * _unit(direction)))

    @classmethod
    def fit_space(cls, ctx):
        return FitSpace(
            "kinematic_offset", ("offset_x", "offset_y", "offset_z"), ("m", "m", "m"), _a(0.0005, 0.0005, 0.0005),
            _a(-0.01, -0.01, -0.01), _a(0.01, 0.01, 0.01), (_a(0.0, 0.0, 0.0),),
            lambda x: {"kind": "kinematic_offset", "offset": [float(v) for v in x]},
            lambda x: {"offset": [float(v) for v in x]},
            absent=(("offset_x", 0.0), ("offset_y", 0.0), ("offset_z", 0.0)),
        )

    @classmethod
    def example(cls, ctx, rng):
        return cls(offset=(0.0015, -0.001, -0.0015))


