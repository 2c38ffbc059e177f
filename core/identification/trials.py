"""One trial = one sequence replayed with one set of model parameters, with a fresh model."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from core.identification.residuals import signed_residuals
from core.simulation import SimulationConfig, effect_from_dict
from core.preparation import PreparedSession, release_pages
from core.simulation.replay import ReplayConfig, replay_mesh, replay_sequence
__all__ = ["Trial", "TrialResult", "run_trial"]


@dataclass(frozen=True)
class Trial:
    """Parameters of one replay.

    Attributes:
        sequence: sequence name.
        youngs_modulus: Pa. poisson_ratio: -.
        grid: node grid (nx, ny, nz) of a box phantom. element_size: target element
            size of an STL phantom, m (None: its default; see ``ReplayConfig``).
            law: material law (see ``Material``). stiffening: its Yeoh coefficient
            ("stable_yeoh" only).
        effects: model extensions as ``{"kind": ..., **parameters}`` dicts (SI, phantom frame).
        simulation: numerical settings.
        paper_error: measure the paper's point-to-mesh error on every frame (False: only
            the top-face residuals and the force, which is all the fit's default metric
            needs; the paper's error is ~80 % of a trial's time on a paper-size sequence).
        effects_youngs: the E (Pa) at which ``effects`` were fitted to surface data, or
            None (their parameters are absolute). Given, their stiffnesses move with E
            (:meth:`~core.simulation.effects.Effect.at_youngs` with ``youngs_modulus /
            effects_youngs``): surface data measure a foundation's stiffness over E, so such
            a fitted stiffness does not set a scale for E.
    """

    sequence: str
    youngs_modulus: float
    poisson_ratio: float = 0.44
    grid: tuple[int, int, int] = (13, 5, 5)
    law: str = "corotational"
    effects: tuple = ()
    stiffening: float = 0.0
    element_size: float | None = None
    simulation: SimulationConfig = field(default_factory=SimulationConfig)
    paper_error: bool = True
    effects_youngs: float | None = None

    def model_effects(self) -> tuple:
        """The effects the replay runs with (:class:`~core.simulation.effects.Effect`
        objects): ``effects``, moved with E when ``effects_youngs`` is given."""
        out = tuple(effect_from_dict(dict(e)) for e in self.effects)
        if self.effects_youngs is not None:
            out = tuple(e.at_youngs(self.youngs_modulus / self.effects_youngs) for e in out)
        return out

    def replay_config(self) -> ReplayConfig:
        return ReplayConfig(
            youngs_modulus=self.youngs_modulus,
            poisson_ratio=self.poisson_ratio,
            grid=self.grid,
            element_size=self.element_size,
            law=self.law,
            stiffening=self.stiffening,
            simulation=self.simulation,
            effects=self.model_effects(),
            sequences=(self.sequence,),
        )


@dataclass(frozen=True)
class TrialResult:
    """Evidence of one trial.

    Attributes:
        trial: the parameters.
        status: "ok" or "diverged" (the paper's "N/A").
        message: why it diverged.
        mean_error: mean point-to-mesh distance over all points of all frames, m (NaN if
            diverged or not measured: ``Trial.paper_error`` False).
        frame_sums: (F,) sum of point distances per frame, m (NaN when not measured).
        frame_counts: (F,) points per frame.
        frame_force_sq: (F,) squared norm of simulated minus measured probe force, N^2,
            or None without force data.
        frame_top_sq: (F,) sum of squared signed top-face residuals, m^2 (see
            :func:`core.identification.residuals.top_residuals`); frame_top_counts: (F,).
        wall_time: s.
    """

    trial: Trial
    status: str
    message: str
    mean_error: float
    frame_sums: np.ndarray
    frame_counts: np.ndarray
    frame_force_sq: np.ndarray | None
    wall_time: float
    frame_top_sq: np.ndarray | None = None
    frame_top_counts: np.ndarray | None = None

    @property
    def ok(self) -> bool:
        return self.status == "ok"


def run_trial(prepared: PreparedSession, trial: Trial) -> TrialResult:
    """Replay ``trial.sequence`` of ``prepared`` with a model built for this trial only."""
    t0 = time.perf_counter()
    seq = prepared.sequences[trial.sequence]
    config = trial.replay_config()
    mesh = replay_mesh(prepared, config.grid, config.element_size)
    r = replay_sequence(prepared, trial.sequence, config, paper_error=trial.paper_error)
    counts = np.array([c.shape[0] for c in seq.clouds], dtype=np.int64)
    sums = r.frame_errors * counts
    force_sq = None
    if seq.force is not None:
        measured = seq.force_at(seq.frame_times)
        force_sq = np.sum((r.simulation.contact_force - measured) ** 2, axis=1)
    top_sq = np.full(counts.size, np.nan)
    top_n = np.zeros(counts.size, dtype=np.int64)
    for f, pts in enumerate(seq.clouds):
        if not np.all(np.isfinite(r.simulation.positions[f])):
            continue  # diverged: NaN sum, as the paper's "N/A"
        res = signed_residuals(pts, r.simulation.positions[f], mesh, prepared.size)
        top_sq[f], top_n[f] = float(np.sum(res**2)), res.size
    release_pages(seq.clouds)
    return TrialResult(
        frame_top_sq=top_sq,
        frame_top_counts=top_n,
        trial=trial,
        status=r.status,
        message=r.message,
        mean_error=r.mean_error,
        frame_sums=sums,
        frame_counts=counts,
        frame_force_sq=force_sq,
        wall_time=time.perf_counter() - t0,
    )
