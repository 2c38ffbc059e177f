"""Fit Young's modulus to a session, with an interval and an honest "cannot tell".

Method (chosen over Optuna's TPE: the search is one-dimensional, smooth in log E away
from divergence, and every evaluation is a full replay, so a deterministic bracketing
method needs the fewest simulations):

1. the paper's coarse decade scan (Table 1) on the train sequences, in parallel;
2. bounded Brent minimisation of the objective over log10 E within one decade of the
   best coarse value (scipy ``minimize_scalar(method="bounded")``);
3. a profile of the objective on a log grid around the optimum; a 95 % interval from
   a block bootstrap over frames (1 s blocks) and sequences of the profile's argmin
   (Efron & Tibshirani 1993, Ch. 8; every replicate reuses the simulated frames),
   widened by the robot calibration's uncertainty, which the bootstrap cannot see
   because it is common to every frame: the fit is repeated near the optimum with the
   probe one standard error (``Calibration.probe_sigma``, from the corner touches)
   higher, and that shift of log E is added in quadrature (delta method, 1.96 sigma);
4. identifiability (:func:`core.identification.verdict.youngs_verdict`, the one rule the
   sweep's verdict applies too): something must set a scale for E (force data, gravity, a foundation
   of fixed stiffness), the profile must rise by at least ``min_rise`` (relative) within
   a decade on both sides, and the interval must span less than ``max_ratio``. A
   displacement-controlled probe without gravity or force data fails the first test:
   a homogeneous linear-elastic body's quasi-static shape does not depend on E;
5. discretisation: linear tetrahedra lock at nu ~ 0.44, so the E a coarse grid needs
   is lower than the material's. The fit is repeated on a refined grid (2 n - 1 nodes
   per axis) near the coarse optimum and that value is reported, with the coarse one.

Objective: ``J(E) = d(E) / d0 + f(E) / f0`` on the train sequences, where d is the RMS
signed vertical residual of points over the top face's interior (m; see
:mod:`core.identification.residuals` for why not the paper's unsigned metric, which
stays available as ``metric="paper"`` and is what the reported errors use) and f the
RMS of simulated minus measured probe force (N, only when the session has force
columns). The weights are noise levels measured from the data: d0 is the same residual
on rest frames against the rest mesh and f0 the RMS force read while the probe is clear
of the phantom (at least 1 mN). Each term is thus in units of its own noise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np
from scipy.optimize import minimize_scalar

from core.errors import TissueTwinError
from core.identification.execution import Executor, SerialExecutor
from core.identification.objective import (  # the objective and its pieces moved there (issue 19)
    Objective,
    bootstrap_argmin,
    calibration_shift,
    force_noise,
    structurally_identifiable,
    top_noise,
)
from core.identification.sweep import PAPER_COARSE
from core.identification.trials import Trial, run_trial
from core.identification.verdict import MAX_RATIO, MIN_RISE, widen_interval, youngs_verdict
from core.preparation import PreparedSession
from core.simulation.meshing import refined_element_size
from core.simulation.replay import noise_floor, replay_mesh

__all__ = ["FitResult", "fit_youngs_modulus", "refined_grid"]

Progress = Callable[[float, str], None]


def refined_grid(grid) -> tuple[int, int, int]:
    """Each cell split in two along every axis: (2 nx - 1, 2 ny - 1, 2 nz - 1)."""
    return tuple(2 * int(n) - 1 for n in grid)


@dataclass(frozen=True)
class FitResult:
    """Evidence of a fit (frozen; see module docstring for the method).

    Attributes:
        youngs_modulus: reported E (Pa): the refined-grid value when identifiable, else None.
        interval: 95 % interval (Pa) or None.
        identifiable: whether the data pin E down.
        reason: one line saying why (always set).
        coarse_value: E on the replay grid (Pa), the argmin even when not identifiable.
        refined_value: E on the refined grid (Pa) or None.
        grid, refined: the two grids.
        poisson_ratio: held fixed (value).
        errors: mean point-to-mesh distance (m) per role at the fitted E on the replay grid.
        profile: sorted (E, J, d, f) rows evaluated on the replay grid.
        weights: (d0 m, f0 N or None).
        evaluations: number of sequence replays run.
        uses_force: whether the force term was in the objective.
    """

    youngs_modulus: float | None
    interval: tuple[float, float] | None
    identifiable: bool
    reason: str
    coarse_value: float
    refined_value: float | None
    grid: tuple[int, int, int]
    refined: tuple[int, int, int]
    poisson_ratio: float
    errors: dict[str, float]
    profile: list[tuple[float, float, float, float | None]]
    weights: tuple[float, float | None]
    evaluations: int
    uses_force: bool
    metric: str = "top"
    law: str = "corotational"
    bootstrap_interval: tuple[float, float] | None = None
    probe_sigma: float = float("nan")
    calibration_shift: float = 0.0
    model_form: dict | None = None
    """E refitted to the force under other laws, Poisson's ratios and grids
    (:func:`core.identification.model_form.youngs_model_form`, on the replay grid's scale),
    or, without force, to the surface under both laws at the ends of nu (``channel``
    "surface", :func:`_surface_model_form`), whose range the interval holds; None when E is
    not identifiable or the phantom is an STL."""
    statistic: dict | None = None
    """What the identifiability rule compared (``statistic`` of
    :func:`core.identification.verdict.youngs_verdict`, on the replay grid: rises of J a
    decade either side, the interval before the model form and its ratio, Pa)."""
    element_sizes: tuple[float | None, float] | None = None
    """For an STL phantom: the replay mesh's target element size (None: the default)
    and the refined mesh's, m; None for a box (``grid`` and ``refined`` hold its meshes)."""

    def to_json(self) -> dict:
        return {
            "youngs_modulus": {
                "value": self.youngs_modulus,
                "interval": list(self.interval) if self.interval else None,
                "identifiable": self.identifiable,
                "reason": self.reason,
                "grid_value": ({"grid": list(self.grid), "value": self.coarse_value} if self.element_sizes is None
                               else {"element_size": self.element_sizes[0], "value": self.coarse_value}),
                "refined_value": None
                if self.refined_value is None
                else ({"grid": list(self.refined), "value": self.refined_value} if self.element_sizes is None
                      else {"element_size": self.element_sizes[1], "value": self.refined_value}),
                "interval_sources": {
                    "bootstrap_frames_sequences": list(self.bootstrap_interval) if self.bootstrap_interval else None,
                    "model_form": self.model_form,
                    "probe_height_sigma_m": None if not math.isfinite(self.probe_sigma) else self.probe_sigma,
                    "relative_shift_per_probe_sigma": self.calibration_shift,
                },
                "statistic": self.statistic,
                "law": self.law,
                "law_note": "E is the modulus of this material law; the paper's corotational law read "
                "~18 % higher than stable neo-Hookean on force data and ~6 % on gravity data with "
                "3-10 mm indentations (model-form bias, not in the interval)",
            },
            "poisson_ratio": {
                "value": self.poisson_ratio,
                "interval": None,
                "identifiable": False,
                "reason": "held fixed (literature value for such gels, as in the paper)",
            },
            "errors": self.errors,
            "objective": {
                "terms": [
                    "rms_signed_top_residual / its_noise" if self.metric == "top" else "point_to_mesh_distance / noise_floor"
                ]
                + (["force_rms / force_noise"] if self.uses_force else []),
                "noise_floor_m": self.weights[0],
                "force_noise_N": self.weights[1],
            },
            "profile": [
                {"youngs_modulus": E, "objective": J, "mean_error": d, "force_rms": f} for E, J, d, f in self.profile
            ],
            "evaluations": self.evaluations,
        }


def _surface_variants():
    """The variants of :data:`core.identification.model_form.VARIANTS` a trial can express
    (both laws at the ends of the plausible nu range; the Yeoh stiffening is not a trial
    field), as :class:`~core.identification.model_form.ModelFormVariant`."""
    from core.identification.model_form import VARIANTS

    return [v for v in VARIANTS if v.stiffening == 0.0]


def _surface_model_form(prepared: PreparedSession, names, base: Trial, executor: Executor, d0: float,
                        progress, metric: str, E_star: float) -> dict:
    """E refitted to the train surface (the fit's own objective, no force) under each of
    :func:`_surface_variants` on the base's grid, within 0.3 decades of ``E_star``.

    Without force, E is set by a body force's sag or a foundation (~ rho g H^2 / E), which
    depends on the law and on Poisson's ratio as well: measured on a field session (seed 52,
    gravity, no force; the lab neo-Hookean at nu 0.42 on a 19x7x7 mesh) the diagnosis stated
    E 4.03 kPa with a bootstrap interval of 3.96-4.12 kPa for the lab's 4.51.

    Returns:
        ``{"variants": [{"model": label, "youngs_modulus": Pa or None}], "low", "high" (Pa or
        None), "channel": "surface", "evaluations": replays}``.
    """
    out, evaluations = [], 0
    for v in _surface_variants():
        obj = Objective(prepared, names, replace(base, law=v.law, poisson_ratio=v.poisson_ratio), executor, False,
                        d0, None, progress, metric)
        r = minimize_scalar(obj, bounds=(math.log10(E_star) - 0.3, math.log10(E_star) + 0.3), method="bounded",
                            options={"xatol": 0.004})
        evaluations += obj.evaluations
        E_v = float(10.0**r.x) if np.isfinite(r.fun) else None
        out.append({"model": replace(v, grid=tuple(base.grid)).label, "youngs_modulus": E_v})
    vals = [o["youngs_modulus"] for o in out if o["youngs_modulus"] is not None]
    return {"variants": out, "low": min(vals) if vals else None, "high": max(vals) if vals else None,
            "channel": "surface", "evaluations": evaluations}


def _say(progress: Progress | None, obj: Objective, stage: str) -> None:
    """Report the stage the fit enters (``progress(n_evaluated_E, message)``)."""
    if progress:
        progress(len(obj.cache), f"{stage} ({obj.evaluations} replays so far)")


def fit_youngs_modulus(
    prepared: PreparedSession,
    *,
    base: Trial | None = None,
    executor: Executor | None = None,
    bounds: tuple[float, float] = (1e1, 1e6),
    use_force: bool | None = None,
    refine_mesh: bool = True,
    min_rise: float = MIN_RISE,
    max_ratio: float = MAX_RATIO,
    n_boot: int = 400,
    seed: int = 0,
    metric: str = "top",
    progress: Progress | None = None,
) -> FitResult:
    """Fit E on the ``train`` sequences; report validation and test errors.

    Args:
        prepared: calibrated session with cleaned clouds (``prepare_session``).
        base: template trial: Poisson's ratio, grid, model extensions (e.g. gravity), numerics.
        executor: where replays run (default: in this process).
        bounds: search range of E, Pa.
        use_force: include the force term (default: when every train sequence has force columns).
        refine_mesh: refit on the refined grid to correct for volumetric locking.
        min_rise: relative rise of J within one decade, both sides, below which the
            profile counts as flat.
        max_ratio: widest interval (hi/lo) still called identifiable.
        n_boot: bootstrap replicates. seed: their seed.
        metric: "top" (RMS signed vertical residual over the top face's interior; the
            default, unbiased under noise) or "paper" (mean distance to the nearest
            super-sampled vertex, which favours a slightly high top under ~1 mm noise).
        progress: ``progress(n_evaluated_E, message)``.

    Raises:
        TissueTwinError: no train sequence, or every trial diverged.
    """
    executor = executor or SerialExecutor()
    base = base or Trial(sequence="", youngs_modulus=1.0)
    names = [n for n, s in prepared.sequences.items() if s.role == "train"]
    if not names:
        raise TissueTwinError("the session has no 'train' sequence to fit on")
    has_force = all(prepared.sequences[n].force is not None for n in names)
    use_force = has_force if use_force is None else (use_force and has_force)
    d0 = (top_noise(prepared, names, base.grid, base.element_size) if metric == "top"
          else noise_floor(prepared, base.grid, mesh=replay_mesh(prepared, base.grid, base.element_size)))
    if not np.isfinite(d0) or d0 <= 0:
        d0 = 1e-3
    f0 = force_noise(prepared, names) if use_force else None
    # the objective's trials measure only what J needs: the paper's per-frame error (most of
    # a paper-size trial's time) is measured once, at the fitted E, for the errors per role
    scored = replace(base, paper_error=metric == "paper")
    obj = Objective(prepared, names, scored, executor, use_force, d0, f0, progress, metric)

    lo, hi = math.log10(bounds[0]), math.log10(bounds[1])
    coarse = [E for E in PAPER_COARSE if bounds[0] <= E <= bounds[1]] or [10 ** ((lo + hi) / 2)]
    _say(progress, obj, "coarse scan")
    obj.results(coarse)
    Jc = {E: obj.terms(E)[0] for E in coarse}
    finite = {E: J for E, J in Jc.items() if np.isfinite(J)}
    if not finite:
        raise TissueTwinError("every trial of the coarse scan diverged")
    best = min(finite, key=finite.get)
    a, b = max(lo, math.log10(best) - 1), min(hi, math.log10(best) + 1)
    _say(progress, obj, "minimising J")
    res = minimize_scalar(obj, bounds=(a, b), method="bounded", options={"xatol": 0.004})
    E_star = float(10.0**res.x)
    # profile: a log grid of half-decade steps up to a decade either side, plus all evaluated points
    grid_pts = [E_star * 10.0**k for k in (-1.0, -0.5, -0.25, -0.1, 0.1, 0.25, 0.5, 1.0)]
    _say(progress, obj, "profile")
    obj.results([E for E in grid_pts if bounds[0] <= E <= bounds[1]])
    Es = np.array(sorted(obj.cache))
    rows = [(float(E), *obj.terms(E)) for E in Es]
    J = np.array([r[1] for r in rows])
    J_star = obj.terms(E_star)[0]

    boot = bootstrap_argmin(obj, Es, n_boot, seed, block=1.0)
    lo_b, hi_b = (float(v) for v in np.percentile(boot, [2.5, 97.5]))

    # identifiability: the one rule of core.identification.verdict (the sweep applies it too)
    structural = structurally_identifiable(base, use_force)
    d_star = obj.terms(E_star)[1]
    rule = dict(structural=structural, bootstrap=(lo_b, hi_b), E_star=E_star, J_star=J_star, min_rise=min_rise,
                max_ratio=max_ratio, residual=d_star, metric=metric, use_force=use_force)
    verdict = youngs_verdict(Es, J, **rule)
    probe_sigma = float(prepared.calibration.probe_sigma)
    shift = 0.0
    if verdict["identifiable"] and math.isfinite(probe_sigma) and probe_sigma > 0:
        _say(progress, obj, "calibration shift")
        shift, n_cal = calibration_shift(obj, E_star, probe_sigma)
        obj.evaluations += n_cal
        verdict = youngs_verdict(Es, J, calibration_shift=shift, **rule)
    identifiable, reason = verdict["identifiable"], verdict["reason"]
    lo_i, hi_i = widen_interval(E_star, (lo_b, hi_b), shift)

    refined = refined_grid(base.grid)
    stl = prepared.stl_path is not None
    coarse_mesh = replay_mesh(prepared, base.grid, base.element_size)
    sizes = None
    if stl:  # an STL phantom: refine by halving the element size (Gmsh), as 2 n - 1 halves a grid's
        sizes = (base.element_size, refined_element_size(coarse_mesh, base.element_size))
    refined_value = None
    if identifiable and refine_mesh:
        fine_base = replace(scored, element_size=sizes[1]) if stl else replace(scored, grid=refined)
        _say(progress, obj, "refit on the refined mesh")
        fine = Objective(prepared, names, fine_base, executor, use_force, d0, f0, progress, metric)
        r2 = minimize_scalar(fine, bounds=(math.log10(E_star) - 0.3, math.log10(E_star) + 0.3), method="bounded", options={"xatol": 0.004})
        refined_value = float(10.0**r2.x)
        obj.evaluations += fine.evaluations

    # errors per role at the fitted E on the replay grid
    _say(progress, obj, "errors per role")
    errors = {}
    for role in ("train", "validation", "test"):
        ns = [n for n, s in prepared.sequences.items() if s.role == role]
        if not ns:
            continue
        if role == "train" and metric == "paper":
            rs = obj.cache[float(10.0**res.x)] if float(10.0**res.x) in obj.cache else None
            if rs and all(r.ok for r in rs):
                errors[role] = float(sum(r.frame_sums.sum() for r in rs) / sum(r.frame_counts.sum() for r in rs))
                continue
        out = executor.map(run_trial, prepared, [replace(base, sequence=n, youngs_modulus=E_star) for n in ns])
        obj.evaluations += len(ns)
        ok = [r for r in out if r.ok]
        errors[role] = float(sum(r.frame_sums.sum() for r in ok) / sum(r.frame_counts.sum() for r in ok)) if ok else float("nan")

    scale = (refined_value / E_star) if refined_value else 1.0
    model_form = None
    if identifiable and use_force:
        # the interval holds E under other laws, Poisson's ratios and meshes (model form):
        # the box's grids, or an STL phantom's own mesh at its element size and half of it
        from core.identification.model_form import youngs_model_form

        _say(progress, obj, "model form (force)")
        at_star = [e.to_dict() for e in replace(base, youngs_modulus=E_star).model_effects()]
        model_form = youngs_model_form(prepared, at_star, E_star, names=names, executor=executor,
                                       element_size=base.element_size)
        obj.evaluations += len(model_form["variants"]) * len(names)
        if model_form["low"] is not None:
            lo_i = min(lo_i, model_form["low"] / scale * (lo_i / E_star))
            hi_i = max(hi_i, model_form["high"] / scale * (hi_i / E_star))
            reason += (f"; widened to the model form: E refitted under {len(model_form['variants'])} laws, "
                       f"Poisson's ratios and grids spans {model_form['low']:.3g}-{model_form['high']:.3g} Pa")
    elif identifiable and stl:
        reason += ("; the model-form spread without force (E refitted to the surface under other laws and "
                   "Poisson's ratios) is not measured on an STL phantom")
    elif identifiable:
        # no force: a body force's sag (or a foundation) sets E, and the sag depends on the
        # law and on Poisson's ratio too; E is refitted to the surface under each
        _say(progress, obj, "model form (surface)")
        model_form = _surface_model_form(prepared, names, scored, executor, d0, progress, metric, E_star)
        obj.evaluations += model_form.pop("evaluations")
        if model_form["low"] is not None:
            lo_i = min(lo_i, model_form["low"] * (lo_i / E_star))
            hi_i = max(hi_i, model_form["high"] * (hi_i / E_star))
            reason += (f"; widened to the model form: E refitted to the surface under {len(model_form['variants'])} "
                       f"laws and Poisson's ratios spans {model_form['low']:.3g}-{model_form['high']:.3g} Pa")
    return FitResult(
        youngs_modulus=(refined_value or E_star) if identifiable else None,
        interval=(lo_i * scale, hi_i * scale) if identifiable else None,
        identifiable=bool(identifiable),
        reason=reason,
        coarse_value=E_star,
        refined_value=refined_value,
        grid=tuple(base.grid),
        refined=refined,
        element_sizes=sizes,
        poisson_ratio=base.poisson_ratio,
        errors=errors,
        profile=[(E, Jv, d, f) for E, Jv, d, f in rows],
        weights=(float(d0), f0),
        evaluations=obj.evaluations,
        uses_force=use_force,
        metric=metric,
        law=base.law,
        bootstrap_interval=(lo_b * scale, hi_b * scale) if identifiable else None,
        probe_sigma=probe_sigma,
        calibration_shift=float(10.0**shift - 1.0),
        model_form=model_form,
        statistic=verdict["statistic"],
    )
