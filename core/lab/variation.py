"""A randomised virtual lab: a lab that is not our replay model.

The default lab's truth differs from the replay model only by its finer mesh and its
hyperelastic law; its damping, contact and noise are the replay's own assumptions. A fit
or a diagnosis validated on it can therefore lean on assumptions that a real phantom
would not honour. :class:`LabVariation` draws, per seed, the things the replay model
*assumes* but a real experiment does not guarantee (the material law and its
nonlinearity, Poisson's ratio, the modulus, the discretisation of the truth, the contact
stiffness, the damping, the sensor noise), in the spirit of domain randomisation (Tobin
et al. 2017, "Domain randomization for transferring deep neural networks from
simulation to the real world"): what survives these draws does not depend on the
replay model being exactly right.

The draws come from their own generator (``numpy.random.default_rng([seed, 7])`` in
:func:`core.lab.generate_session`), so the robot and camera poses, the probe plans and
every noise stream of a seed are the same with and without variation.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # core.lab.config imports this module
    from core.lab.generate import LabConfig

__all__ = ["VARIATION_LAWS", "LabVariation", "apply_variation"]

VARIATION_LAWS = ("stable_neo_hookean", "stable_yeoh")
"""Truth material laws a variation may draw (see :class:`core.simulation.Material`)."""


def _check_range(name: str, r, *, positive: bool = True, upper: float | None = None) -> None:
    if len(r) != 2 or not all(np.isfinite(v) for v in r) or r[0] > r[1]:
        raise ValueError(f"LabVariation.{name} must be a finite (low, high) with low <= high, got {r!r}")
    if positive and r[0] <= 0:
        raise ValueError(f"LabVariation.{name} must be positive, got {r!r}")
    if upper is not None and r[1] >= upper:
        raise ValueError(f"LabVariation.{name} must stay below {upper}, got {r!r}")


@dataclass(frozen=True)
class LabVariation:
    """Ranges the lab draws its truth and sensors from, per seed. Ranges are
    ``(low, high)``; "uniform" and "log-uniform" say how they are sampled."""

    laws: tuple[str, ...] = VARIATION_LAWS
    """Truth material laws, one drawn uniformly. The replay's corotational law is
    linear; a truth that stiffens with strain ("stable_yeoh") is one that no modulus of
    the replay model fits at every depth, as real gels and tissue (strain-stiffening,
    Yeoh 1993) are not."""
    stiffening_range: tuple[float, float] = (0.5, 3.0)
    """Yeoh coefficient k of "stable_yeoh" (dimensionless), uniform: from mildly to clearly
    nonlinear (measured on a clamped column against stable neo-Hookean: k = 1 is 3 % stiffer
    at 10 % compression and 9 % at 20 % with nu = 0.3; k = 2 is 12 % stiffer at 10 % with
    nu = 0.45). Drawn for every seed (so the stream does not depend on the law), used only
    by "stable_yeoh"."""
    poisson_ratio_range: tuple[float, float] = (0.42, 0.48)
    """Poisson's ratio, uniform. The paper takes a literature value (0.4-0.5) for a gel;
    the replay's 0.44 is an assumption, and the indentation force depends on it."""
    youngs_modulus_range: tuple[float, float] = (3e3, 1.5e4)
    """Young's modulus, Pa, log-uniform (a scale parameter). Soft gels and soft tissue span
    a few kPa to tens of kPa; a fit must not succeed only near the 5 kPa of Wu et al. 2020."""
    grids: tuple[tuple[int, int, int], ...] = ((19, 7, 7), (25, 9, 9), (31, 11, 11))
    """Truth meshes (nodes along x, y, z), one drawn uniformly, all finer than the replay's
    13 x 5 x 5: a real phantom is a continuum, and a fixed truth mesh would let a
    mesh-correction tuned to that one mesh pass for a physical one."""
    contact_stiffness_per_modulus_range: tuple[float, float] = (5e4, 2e6)
    """Contact penalty per unit area and per pascal of E, 1/m, log-uniform (the replay
    assumes 2e5, see ``SimulationConfig.contact_stiffness_per_modulus``). Always stiff, as
    a steel probe in a gel is: the sphere sinks at most ~0.5 mm, but by how much varies."""
    rayleigh_mass_range: tuple[float, float] = (0.05, 0.25)
    """Rayleigh damping on the mass matrix, 1/s, uniform (the replay assumes the paper's 0.1)."""
    rayleigh_stiffness_range: tuple[float, float] = (0.05, 0.25)
    """Rayleigh damping on the stiffness matrix, s, uniform (the replay assumes 0.1). The
    damping of a real gel is not known a priori and shapes the dynamic part of a replay."""
    depth_noise_scale_range: tuple[float, float] = (0.6, 1.6)
    """Factor on ``DepthNoise.sigma``, uniform: depth noise differs between units, surfaces
    and distances; a method tuned to one noise level must not break at another."""
    force_noise_range: tuple[float, float] = (0.003, 0.015)
    """Standard deviation of the written force per axis, N, uniform (replaces
    ``LabConfig.force_noise``): force sensors and force estimates from motor currents
    range from good to poor."""

    def __post_init__(self):
        if not self.laws or not set(self.laws) <= set(VARIATION_LAWS):
            raise ValueError(f"LabVariation.laws must be a non-empty subset of {VARIATION_LAWS}, got {self.laws!r}")
        if not self.grids or any(len(g) != 3 or min(g) < 2 for g in self.grids):
            raise ValueError(f"LabVariation.grids must be (nx, ny, nz) node counts >= 2, got {self.grids!r}")
        _check_range("stiffening_range", self.stiffening_range, positive=False)
        if self.stiffening_range[0] < 0:
            raise ValueError(f"LabVariation.stiffening_range must be >= 0, got {self.stiffening_range!r}")
        _check_range("poisson_ratio_range", self.poisson_ratio_range, upper=0.5)
        _check_range("youngs_modulus_range", self.youngs_modulus_range)
        _check_range("contact_stiffness_per_modulus_range", self.contact_stiffness_per_modulus_range)
        _check_range("rayleigh_mass_range", self.rayleigh_mass_range, positive=False)
        _check_range("rayleigh_stiffness_range", self.rayleigh_stiffness_range, positive=False)
        if min(self.rayleigh_mass_range[0], self.rayleigh_stiffness_range[0]) < 0:
            raise ValueError("LabVariation damping ranges must be >= 0")
        _check_range("depth_noise_scale_range", self.depth_noise_scale_range)
        _check_range("force_noise_range", self.force_noise_range, positive=False)
        if self.force_noise_range[0] < 0:
            raise ValueError(f"LabVariation.force_noise_range must be >= 0, got {self.force_noise_range!r}")

    def draw(self, rng: np.random.Generator) -> dict:
        """One lab: a JSON-ready dict of drawn values, always drawn in the same order.

        Keys: ``law`` (str), ``stiffening`` (float, 0.0 unless the law is "stable_yeoh"),
        ``youngs_modulus`` (Pa), ``poisson_ratio``, ``grid`` ([nx, ny, nz]),
        ``contact_stiffness_per_modulus`` (1/m), ``rayleigh_mass`` (1/s),
        ``rayleigh_stiffness`` (s), ``depth_noise_scale`` (factor on DepthNoise.sigma),
        ``force_noise`` (N).
        """

        def log_uniform(r) -> float:
            return float(np.exp(rng.uniform(np.log(r[0]), np.log(r[1]))))

        law = self.laws[int(rng.integers(len(self.laws)))]
        k = float(rng.uniform(*self.stiffening_range))
        out = {
            "law": law,
            "stiffening": k if law == "stable_yeoh" else 0.0,
            "youngs_modulus": log_uniform(self.youngs_modulus_range),
            "poisson_ratio": float(rng.uniform(*self.poisson_ratio_range)),
            "grid": [int(v) for v in self.grids[int(rng.integers(len(self.grids)))]],
            "contact_stiffness_per_modulus": log_uniform(self.contact_stiffness_per_modulus_range),
            "rayleigh_mass": float(rng.uniform(*self.rayleigh_mass_range)),
            "rayleigh_stiffness": float(rng.uniform(*self.rayleigh_stiffness_range)),
            "depth_noise_scale": float(rng.uniform(*self.depth_noise_scale_range)),
            "force_noise": float(rng.uniform(*self.force_noise_range)),
        }
        return out

    def to_dict(self) -> dict:
        """The ranges, JSON-ready (as recorded in truth.json ``lab_variation.ranges``)."""
        return {k: ([list(g) for g in v] if k == "grids" else list(v)) for k, v in asdict(self).items()}


def apply_variation(cfg: "LabConfig", drawn: dict) -> "LabConfig":
    """``cfg`` with the values of :meth:`LabVariation.draw` applied.

    Sets the truth's law, stiffening, Young's modulus (and clears
    ``youngs_modulus_range``), Poisson's ratio, grid, contact stiffness per modulus,
    Rayleigh damping, ``force_noise`` and ``depth_noise.sigma`` (scaled by
    ``depth_noise_scale``). Everything else, ``variation`` included, is kept.

    Raises:
        KeyError: ``drawn`` lacks one of the keys of :meth:`LabVariation.draw`.
    """
    return replace(
        cfg,
        law=str(drawn["law"]),
        stiffening=float(drawn["stiffening"]),
        youngs_modulus=float(drawn["youngs_modulus"]),
        youngs_modulus_range=None,
        poisson_ratio=float(drawn["poisson_ratio"]),
        grid=tuple(int(v) for v in drawn["grid"]),
        contact_stiffness_per_modulus=float(drawn["contact_stiffness_per_modulus"]),
        rayleigh_mass=float(drawn["rayleigh_mass"]),
        rayleigh_stiffness=float(drawn["rayleigh_stiffness"]),
        force_noise=float(drawn["force_noise"]),
        depth_noise=replace(cfg.depth_noise, sigma=cfg.depth_noise.sigma * float(drawn["depth_noise_scale"])),
    )
