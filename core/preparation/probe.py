"""The probe's path in the phantom frame (the calibrated kinematics a replay follows)."""

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

    def smoothed(self, sigma: float) -> "ProbePath":
        """The path low-passed by a Gaussian kernel of ``sigma`` seconds (zero phase).

        Robot kinematics carry encoder noise (~20 um at every sample of a dVRK), which a
        stiff probe contact and the stiffness damping turn into ~15-25 mN of force jitter
        in a replay (measured on a 6 s session, 200 Hz kinematics: 14 mN per frame along
        z during holds); a probe pressing at 3-15 mm/s moves smoothly below ~5 Hz. At
        sigma = 10 ms the jitter drops to 6 mN and a replay of the lab's own model matches
        the measured force to its 10 mN noise. Uniformly sampled paths are filtered with
        ``scipy.ndimage.gaussian_filter1d`` (ends held), others with a windowed average.

        Args:
            sigma: standard deviation of the kernel, s (0: unchanged).

        Raises:
            SimulationError: a negative or non-finite sigma.
        """
        if not (np.isfinite(sigma) and sigma >= 0):
            raise SimulationError(f"smoothing sigma must be >= 0 s, got {sigma}")
        if sigma == 0 or self.t.size < 3:
            return self
        dt = np.diff(self.t)
        if np.all(np.abs(dt - dt.mean()) <= 0.01 * dt.mean()):
            from scipy.ndimage import gaussian_filter1d

            c = gaussian_filter1d(self.centres, sigma / float(dt.mean()), axis=0, mode="nearest")
            return ProbePath(self.t, c)
        out = np.empty_like(self.centres)
        lo = np.searchsorted(self.t, self.t - 4 * sigma)
        hi = np.searchsorted(self.t, self.t + 4 * sigma, side="right")
        for i in range(self.t.size):
            w = np.exp(-0.5 * ((self.t[lo[i]:hi[i]] - self.t[i]) / sigma) ** 2)
            out[i] = w @ self.centres[lo[i]:hi[i]] / w.sum()
        return ProbePath(self.t, out)

