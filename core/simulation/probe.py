"""The probe's path in the phantom frame."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.errors import SimulationError

__all__ = ["ProbePath"]


@dataclass(frozen=True)
class ProbePath:
    """Sphere-centre positions of the probe over time, phantom frame.

    Between samples the path is interpolated linearly, as in the paper's replay
    (Wu et al. 2020, Sec. 3.2); outside the sampled span it is held constant.

    Attributes:
        t: (K,) float64 strictly increasing times, s.
        centres: (K, 3) float64 sphere centres, m, phantom frame.
    """

    t: np.ndarray
    centres: np.ndarray

    def __post_init__(self):
        t = np.asarray(self.t, dtype=np.float64).reshape(-1)
        c = np.asarray(self.centres, dtype=np.float64)
        if c.shape != (t.shape[0], 3):
            raise SimulationError(f"probe centres must be ({t.shape[0]}, 3), got {c.shape}")
        if t.size == 0 or not np.all(np.isfinite(t)) or not np.all(np.isfinite(c)):
            raise SimulationError("probe path must be non-empty and finite")
        if t.size > 1 and np.any(np.diff(t) <= 0):
            raise SimulationError("probe path times must be strictly increasing")
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "centres", c)

    def at(self, times) -> np.ndarray:
        """(M, 3) centres at ``times`` (M,) by linear interpolation."""
        times = np.asarray(times, dtype=np.float64).reshape(-1)
        return np.stack([np.interp(times, self.t, self.centres[:, i]) for i in range(3)], axis=1)

    def shifted(self, dt: float) -> "ProbePath":
        """The path delayed by ``dt`` seconds: new(t) = old(t - dt)."""
        return ProbePath(self.t + dt, self.centres)

    def translated(self, offset: np.ndarray) -> "ProbePath":
        """The path moved by ``offset`` (3,), m."""
        return ProbePath(self.t, self.centres + np.asarray(offset, dtype=np.float64)[None, :])
