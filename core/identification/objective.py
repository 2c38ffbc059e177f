"""The fit's objective J(E) and the pieces of its identifiability test, shared by
:func:`core.identification.fit.fit_youngs_modulus` and the sweep's verdict
(:mod:`core.identification.verdict`).

``J(E) = d(E) / d0 + f(E) / f0`` over a set of sequences: d is the RMS signed vertical
residual of points over the top face's interior (m; or the paper's mean point-to-mesh
distance with ``metric="paper"``), f the RMS of simulated minus measured probe force (N,
only with force columns); d0 (m) and f0 (N) are their noise levels measured on rest
frames, so each term is in units of its own noise (dimensionless).
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Sequence

import numpy as np

from core.identification.execution import Executor
from core.identification.trials import Trial, TrialResult, run_trial
from core.preparation import PreparedSession
from core.simulation.effects import EFFECT_KINDS

__all__ = ["Objective", "top_noise", "force_noise", "argmin_log", "bootstrap_argmin", "structurally_identifiable",
           "calibration_shift"]


class Objective:
    """Evaluates and caches J(E) (dimensionless) over the sequences ``names`` (one trial per
    sequence and E). ``cache[E]`` holds their :class:`TrialResult` in the order of ``names``:
    results replayed elsewhere (a sweep's) can be put there and are used as they are.

    Args:
        prepared: the session (:class:`~core.preparation.PreparedSession`).
        names: the sequences J sums over.
        base: template trial (its ``sequence`` and ``youngs_modulus`` are replaced per trial).
        executor: where the replays run.
        use_force: add the force term ``f / f0``.
        d0: noise of the top residual, m. f0: noise of the force, N (None without force).
        progress: ``progress(n_evaluated_E, message)`` after each batch, or None.
        metric: "top" or "paper" (see the module docstring).

    Attributes:
        evaluations: replays run so far (trials, i.e. sequences x values of E).
    """

    def __init__(self, prepared, names, base: Trial, executor: Executor, use_force: bool, d0, f0, progress, metric="top"):
        self.metric = metric
        self.prepared, self.names, self.base, self.executor = prepared, names, base, executor
        self.use_force, self.d0, self.f0 = use_force, d0, f0
        self.cache: dict[float, list[TrialResult]] = {}
        self.evaluations = 0
        self.progress = progress

    def results(self, Es: Sequence[float]) -> None:
        """Replay every sequence at each E of ``Es`` (Pa) not yet in :attr:`cache`, in one
        batch on the executor, and cache the results. Exceptions of the replays propagate."""
        todo = sorted({float(E) for E in Es} - set(self.cache))
        if not todo:
            return
        trials = [replace(self.base, sequence=n, youngs_modulus=E) for E in todo for n in self.names]
        out = self.executor.map(run_trial, self.prepared, trials)
        self.evaluations += len(trials)
        for i, E in enumerate(todo):
            self.cache[E] = out[i * len(self.names) : (i + 1) * len(self.names)]
        if self.progress:
            self.progress(len(self.cache), f"{self.evaluations} replays")

    def terms(self, E: float, weights: list[np.ndarray] | None = None) -> tuple[float, float, float | None]:
        """``(J, d, f)`` at ``E`` (Pa, in :attr:`cache`): J dimensionless, d in m, f in N (None
        without force); ``(inf, nan, None)`` when a replay diverged.

        Args:
            weights: per sequence (in the order of ``names``), an (F,) weight of each frame
                (the bootstrap's resampling counts); default all ones.

        Raises:
            KeyError: ``E`` was not evaluated (:meth:`results`).
        """
        rs = self.cache[float(E)]
        if not all(r.ok for r in rs):
            return math.inf, math.nan, None
        w = weights or [np.ones(r.frame_counts.size) for r in rs]
        if self.metric == "top":  # RMS signed top-face residual (unbiased under noise)
            d = math.sqrt(
                sum((wi * r.frame_top_sq).sum() for wi, r in zip(w, rs)) / sum((wi * r.frame_top_counts).sum() for wi, r in zip(w, rs))
            )
        else:  # the paper's mean distance to the nearest super-sampled vertex
            d = sum((wi * r.frame_sums).sum() for wi, r in zip(w, rs)) / sum((wi * r.frame_counts).sum() for wi, r in zip(w, rs))
        J = d / self.d0
        f = None
        if self.use_force:
            f = math.sqrt(sum((wi * r.frame_force_sq).sum() for wi, r in zip(w, rs)) / sum(wi.sum() for wi in w))
            J += f / self.f0
        return float(J), float(d), f

    def __call__(self, logE: float) -> float:
        """J (dimensionless) at ``E = 10**logE`` Pa, replayed if not cached: the function
        a scalar minimiser of log10 E calls."""
        E = float(10.0**logE)
        self.results([E])
        return self.terms(E)[0]


def top_noise(prepared: PreparedSession, names, grid, element_size: float | None = None) -> float:
    """RMS signed residual (m) of rest frames against the rest mesh (the box grid's top
    face, or any mesh's upward surface): its noise level.

    Method: :func:`core.identification.residuals.signed_residuals` of every rest frame
    (:meth:`~core.preparation.PreparedSession.rest_frames`) of the sequences ``names``
    against :func:`core.simulation.replay.replay_mesh` of ``grid`` (a box grid, (3,) nodes
    per axis) or ``element_size`` (m, an STL phantom); 1 mm when there are 10 residuals or fewer.

    Raises:
        KeyError: a name that is not a sequence of ``prepared``.
        SimulationError: a bad grid. MeshingError: a bad STL (:func:`~core.simulation.replay.replay_mesh`).
    """
    from core.identification.residuals import signed_residuals
    from core.preparation import release_pages
    from core.simulation.replay import replay_mesh

    mesh = replay_mesh(prepared, grid, element_size)
    res = []
    for n in names:
        clouds = prepared.sequences[n].clouds
        res += [signed_residuals(clouds[i], mesh.nodes, mesh, prepared.size) for i in prepared.rest_frames(n)]
        release_pages(clouds)
    res = np.concatenate(res) if res else np.zeros(0)
    return float(np.sqrt(np.mean(res**2))) if res.size > 10 else 1e-3


def force_noise(prepared: PreparedSession, names) -> float:
    """RMS probe force (N) on rest frames, the probe clear of the phantom: its noise level (at least 1 mN).

    Method: the norm of the (F, 3) force (N) interpolated at the rest frames'
    (:meth:`~core.preparation.PreparedSession.rest_frames`) times, RMS over those of the
    sequences ``names`` that have force columns; 1 mN when none has a rest frame with force.

    Raises:
        KeyError: a name that is not a sequence of ``prepared``.
    """
    vals = []
    for n in names:
        seq = prepared.sequences[n]
        idx = prepared.rest_frames(n)
        if seq.force is None or idx.size == 0:
            continue
        f = seq.force_at(seq.frame_times[idx])
        vals.append(np.sum(f**2, axis=1))
    if not vals:
        return 1e-3
    return max(float(np.sqrt(np.concatenate(vals).mean())), 1e-3)


def argmin_log(Es: np.ndarray, J: np.ndarray) -> float:
    """argmin over a sorted log grid, refined by a parabola through the neighbours.

    Args:
        Es: (n,) increasing values of E, Pa. J: (n,) the objective at them (NaN ignored).

    Returns:
        E (Pa) at the vertex of the parabola in log10 E through the grid's minimum and its two
        neighbours (clipped to them), when all three are finite and it opens upward; else
        the grid's minimum itself.

    Raises:
        ValueError: ``J`` empty or all NaN (:func:`numpy.nanargmin`).
    """
    i = int(np.nanargmin(J))
    x = np.log10(Es)
    if 0 < i < len(Es) - 1 and np.all(np.isfinite(J[i - 1 : i + 2])):
        x0, x1, x2 = x[i - 1 : i + 2]
        y0, y1, y2 = J[i - 1 : i + 2]
        den = (x0 - x1) * (x0 - x2) * (x1 - x2)
        a = (x2 * (y1 - y0) + x1 * (y0 - y2) + x0 * (y2 - y1)) / den
        b = (x2**2 * (y0 - y1) + x1**2 * (y2 - y0) + x0**2 * (y1 - y2)) / den
        if a > 0:
            return float(10.0 ** np.clip(-b / (2 * a), x0, x2))
    return float(Es[i])


def bootstrap_argmin(obj: Objective, Es: np.ndarray, n_boot: int, seed: int, block: float) -> np.ndarray:
    """``n_boot`` replicates (Pa) of the profile's argmin over ``Es`` (Pa, all in ``obj.cache``):
    sequences resampled with replacement, and within each its frames in blocks of ``block`` s.

    Method: a block bootstrap (Efron & Tibshirani 1993, Ch. 8) that reuses the simulated
    frames: each replicate reweights the frames of ``obj.cache`` by how often their block
    was drawn and takes :func:`argmin_log` of the reweighted J over ``Es``.

    Args:
        Es: (n,) increasing values of E, Pa. n_boot: replicates. seed: of the generator.
        block: block length, s.

    Returns:
        (n_boot,) float64, Pa.

    Raises:
        KeyError: an E of ``Es`` not in ``obj.cache``.
    """
    rng = np.random.default_rng(seed)
    first = obj.cache[float(Es[0])]
    blocks = []
    for r, n in zip(first, obj.names):
        t = obj.prepared.sequences[n].frame_times
        blocks.append(np.floor((t - t[0]) / block).astype(int))
    out = np.empty(n_boot)
    for b in range(n_boot):
        seqs = rng.integers(0, len(obj.names), len(obj.names))
        w = [np.zeros(len(bl)) for bl in blocks]
        for s in seqs:
            nb = blocks[s].max() + 1
            picks = rng.integers(0, nb, nb)
            counts = np.bincount(picks, minlength=nb)
            w[s] += counts[blocks[s]]
        J = np.array([obj.terms(E, w)[0] for E in Es])
        out[b] = argmin_log(Es, J)
    return out


def structurally_identifiable(base: Trial, use_force: bool) -> bool:
    """Whether anything in the data or the model sets a scale for E (Pa): measured force,
    a body force, or a foundation of fixed stiffness (Pa/m). Without them every
    quasi-static term is invariant to scaling E (stress ~ E strain, contact is a
    displacement constraint; a foundation fitted to the surface, ``Trial.effects_youngs``,
    scales with E), so only dynamics and damping remain -- the paper's flat
    Table 2. Such a minimum is weak and carries the model-form error (measured: 30 kPa
    on a 5 kPa truth, 13x5x5 corotational against 25x9x9 neo-Hookean, 6 s sequences).

    Method: True with ``use_force``; else whether an effect of ``base.effects`` (dicts
    ``{"kind": ..., **parameters}``) says it sets a scale
    (:meth:`core.simulation.effects.Effect.sets_youngs_scale`, asked with
    ``fitted_over_youngs`` when ``base.effects_youngs`` is set: a foundation fitted to the
    surface sets none, gravity still does). Effects of an unknown or missing kind set none.

    Raises:
        TypeError, ValueError: an effect that is not a dict, or a parameter a kind reads
            that is not numeric (gravity's ``g``).
    """
    if use_force:
        return True
    fitted = base.effects_youngs is not None
    for e in base.effects:
        e = dict(e)
        kind = e.get("kind")
        cls = EFFECT_KINDS.get(kind) if isinstance(kind, str) else None
        if cls is not None and cls.sets_youngs_scale(e, fitted_over_youngs=fitted):
            return True
    return False


def calibration_shift(obj: Objective, E_star: float, sigma: float) -> tuple[float, int]:
    """|log10 shift| of the optimum when the probe sits ``sigma`` (m) higher than calibrated,
    and the replays it took. Five points within 0.15 decade of ``E_star``, parabolic argmin.

    Method: ``obj``'s objective with a ``kinematic_offset`` of ``(0, 0, sigma)`` added to its
    base trial's effects, evaluated at ``E_star`` x 10^(-0.15, -0.05, 0, 0.05, 0.15) and
    minimised by :func:`argmin_log`.

    Args:
        E_star: the optimum of ``obj``, Pa. sigma: the probe's height uncertainty, m.

    Returns:
        (shift in decades, >= 0; 0 when every perturbed replay diverged, replays run).
    """
    offset = {"kind": "kinematic_offset", "offset": [0.0, 0.0, float(sigma)]}
    base = replace(obj.base, effects=tuple(obj.base.effects) + (offset,))
    pert = Objective(obj.prepared, obj.names, base, obj.executor, obj.use_force, obj.d0, obj.f0, None, obj.metric)
    Es = E_star * 10.0 ** np.array([-0.15, -0.05, 0.0, 0.05, 0.15])
    pert.results(Es)
    J = np.array([pert.terms(E)[0] for E in Es])
    if not np.isfinite(J).any():
        return 0.0, pert.evaluations
    return abs(math.log10(argmin_log(Es, J) / E_star)), pert.evaluations

