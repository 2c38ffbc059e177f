"""One verdict on Young's modulus, the same for the fit, the sweep and the diagnosis.

The rule is the fit's (:func:`core.identification.fit.fit_youngs_modulus`, step 4; it
lives here and the fit calls it). On the fit's objective ``J(E)`` (dimensionless: each
term in units of its measured noise, :mod:`core.identification.objective`) E is
identifiable when all three hold:

1. **structural**: something sets a scale for E (force data, gravity, a foundation of
   fixed stiffness; :func:`core.identification.objective.structurally_identifiable`);
2. **profile rise**: J rises by at least :data:`MIN_RISE` (relative, 2 %) at the evaluated
   E nearest a decade below and nearest a decade above its minimum (no evaluated E on a
   side: no evidence there, a rise of 0);
3. **interval**: the 95 % interval of the argmin (block bootstrap over frames and
   sequences, widened in quadrature by the shift a one-sigma error of the robot's
   calibration causes) spans at most :data:`MAX_RATIO` (hi / lo).

:func:`youngs_verdict` applies the rule to a profile; :func:`sweep_verdict` builds that
profile from a sweep's trials (the paper's grid search, Tables 1-2), so a sweep whose
whole error range is within the noise says "not identifiable" rather than naming the
grid value that happened to be lowest.

Verdicts are JSON-ready dicts: ``{"identifiable": bool, "value": Pa or None, "interval":
[lo, hi] Pa or None, "reason": str, "statistic": {...}}``.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Mapping, Sequence

import numpy as np

from core.identification.execution import Executor, SerialExecutor
from core.identification.objective import (
    Objective,
    argmin_log,
    bootstrap_argmin,
    calibration_shift,
    force_noise,
    structurally_identifiable,
    top_noise,
)
from core.preparation import PreparedSession

__all__ = ["MIN_RISE", "MAX_RATIO", "profile_rise", "widen_interval", "youngs_verdict", "sweep_verdict"]

MIN_RISE = 0.02
"""Smallest relative rise of J a decade from its minimum, on both sides, that is not a flat profile."""
MAX_RATIO = 3.0
"""Widest 95 % interval (hi / lo) still called identifiable."""


def _num(x) -> float | None:
    """A finite float, or None (JSON has no inf / NaN)."""
    return float(x) if x is not None and math.isfinite(float(x)) else None


def profile_rise(Es: Sequence[float], J: Sequence[float], E_star: float, J_star: float) -> tuple[float, float]:
    """Relative rise ``(J - J*) / J*`` of the objective a decade below and above ``E_star``.

    Args:
        Es: evaluated E, Pa. J: the objective there (inf where a trial diverged).
        E_star: the optimum, Pa. J_star: the objective there.

    Returns:
        (below, above): on each side, the rise at the evaluated E nearest (in log E) to
        ``E_star / 10`` resp. ``10 E_star``; 0 when nothing was evaluated on that side
        (at the search bound: no evidence there).
    """

    def rise(side: int) -> float:
        E_side = E_star * 10.0**side
        cand = [(abs(math.log10(E / E_side)), j) for E, j in zip(Es, J) if (E - E_star) * side > 0]
        if not cand:
            return 0.0
        return (min(cand)[1] - J_star) / J_star

    return rise(-1), rise(+1)


def widen_interval(centre: float, bootstrap: tuple[float, float], shift: float) -> tuple[float, float]:
    """The bootstrap interval (Pa) widened by a calibration shift of ``shift`` decades
    (log10 E per sigma of the probe's height) in quadrature, 1.96 sigma (delta method),
    about ``centre`` (Pa). ``shift = 0`` returns the bootstrap interval."""
    lo_b, hi_b = bootstrap
    if shift == 0.0:
        return lo_b, hi_b
    widen = (1.96 * shift) ** 2
    lo = centre / 10.0 ** math.sqrt(math.log10(centre / lo_b) ** 2 + widen) if lo_b < centre else lo_b
    hi = centre * 10.0 ** math.sqrt(math.log10(hi_b / centre) ** 2 + widen) if hi_b > centre else hi_b
    return lo, hi


def youngs_verdict(
    Es: Sequence[float],
    J: Sequence[float],
    *,
    structural: bool,
    bootstrap: tuple[float, float],
    E_star: float | None = None,
    J_star: float | None = None,
    value: float | None = None,
    calibration_shift: float = 0.0,
    min_rise: float = MIN_RISE,
    max_ratio: float = MAX_RATIO,
    residual: float | None = None,
    metric: str = "top",
    use_force: bool = False,
    scope: str = "train",
    errors: Mapping[float, float] | None = None,
) -> dict:
    """Whether the profile ``J(E)`` pins E down, by the fit's rule (module docstring).

    Args:
        Es: evaluated E, Pa. J: the fit's objective there (dimensionless; inf = diverged).
        structural: whether the data or the model set a scale for E.
        bootstrap: 95 % bootstrap interval of the argmin, Pa.
        E_star: the optimum the rise is measured from, Pa (default: the argmin over Es);
            J_star: J there (default: its value in J).
        value: the point estimate, Pa, the centre of the widening (default: E_star).
        calibration_shift: |shift of log10 E| per sigma of the probe's height (decades);
            0 = not (yet) measured.
        min_rise, max_ratio: the thresholds (:data:`MIN_RISE`, :data:`MAX_RATIO`).
        residual: the RMS residual at the optimum, m (for the reason).
        metric: "top" or "paper" (which residual). use_force: force in J.
        scope: which sequences J is over, for the reason ("train").
        errors: the paper's mean error (m) per E, when a sweep has it: its spread enters
            the reason and the statistic.

    Returns:
        ``{"identifiable", "value" (Pa or None), "interval" ([lo, hi] Pa or None),
        "reason", "statistic"}``; ``statistic`` holds the numbers the rule compared
        (rises, thresholds, the interval and its ratio, ...), whatever the outcome.
    """
    Es = np.asarray(Es, dtype=np.float64)
    J = np.asarray(J, dtype=np.float64)
    finite = np.isfinite(J)
    span_err = None
    if errors:
        e = np.array([v for v in errors.values() if v is not None and math.isfinite(v)])
        if e.size:
            span_err = (float(e.min()), float(e.max()))
    if not finite.any():
        return {"identifiable": False, "value": None, "interval": None,
                "reason": "every trial diverged: no profile to compare",
                "statistic": {"rule": "core.identification.verdict.youngs_verdict", "structural": bool(structural),
                              "min_rise": min_rise, "max_ratio": max_ratio}}
    if E_star is None:
        i = int(np.argmin(np.where(finite, J, np.inf)))
        E_star, J_star = float(Es[i]), float(J[i])
    elif J_star is None:
        J_star = float(J[np.argmin(np.abs(np.log10(Es / E_star)))])
    centre = float(E_star if value is None else value)
    rise_lo, rise_hi = profile_rise(Es, J, E_star, J_star)
    profiled = rise_lo >= min_rise and rise_hi >= min_rise
    lo_i, hi_i = widen_interval(centre, bootstrap, calibration_shift)
    ratio = hi_i / lo_i
    identifiable = bool(profiled and structural and ratio <= max_ratio)
    if identifiable:
        reason = (
            f"profile rises {100 * rise_lo:.0f} % / {100 * rise_hi:.0f} % a decade below / above the optimum; "
            f"95 % interval spans a factor {ratio:.2f}"
        )
    elif profiled and not structural:
        reason = (
            f"structurally not identifiable: without force data, gravity or a foundation of known stiffness "
            f"the quasi-static shape under a displacement-controlled probe does not depend on E; the profile's "
            f"minimum near {centre:.3g} Pa (rises {100 * rise_lo:.0f} % / {100 * rise_hi:.0f} % a decade away) comes "
            f"from dynamics and damping, where model-form error dominates, and is not reported"
        )
    elif profiled:
        reason = (
            f"the profile has a minimum, but the 95 % interval {lo_i:.3g}-{hi_i:.3g} Pa spans a factor "
            f"{ratio:.2f} (> {max_ratio:g}): the data and the calibration cannot pin E down"
        )
    else:
        span = Es[finite]
        res = "nan" if residual is None else f"{residual * 1e3:.3f}"
        reason = (
            f"flat profile: a tenfold change of E changes the {scope} objective by only "
            f"{100 * max(rise_lo, 0):.1f} % / {100 * max(rise_hi, 0):.1f} % ({'RMS top residual' if metric == 'top' else 'error'} {res} mm); "
            f"bootstrap argmin ranges {lo_i:.3g}-{hi_i:.3g} Pa over {span.min():.3g}-{span.max():.3g} Pa"
            + ("" if structural else "; without force data or gravity a displacement-controlled probe says almost nothing about E")
        )
    if not identifiable and span_err is not None:
        ok = [E for E, v in (errors or {}).items() if v is not None and math.isfinite(v)]
        reason += (f"; the mean error (the paper's metric) spans {span_err[0] * 1e3:.3f}-{span_err[1] * 1e3:.3f} mm "
                   f"({100 * (span_err[1] - span_err[0]) / span_err[0]:.2g} %) over {min(ok):.3g}-{max(ok):.3g} Pa")
    statistic = {
        "rule": "core.identification.verdict.youngs_verdict (the fit's: structural scale, profile rise, interval width)",
        "objective": "rms_signed_top_residual / its_noise" if metric == "top" else "point_to_mesh_distance / noise_floor",
        "uses_force": bool(use_force),
        "structural": bool(structural),
        "optimum": _num(E_star),
        "objective_at_optimum": _num(J_star),
        "rise_below": _num(rise_lo),
        "rise_above": _num(rise_hi),
        "min_rise": min_rise,
        "interval": [_num(lo_i), _num(hi_i)],
        "interval_ratio": _num(ratio),
        "max_ratio": max_ratio,
        "bootstrap_interval": [_num(bootstrap[0]), _num(bootstrap[1])],
        "calibration_shift_decades": float(calibration_shift),
        "evaluated": [_num(Es[finite].min()), _num(Es[finite].max())],
        "error_span_m": list(span_err) if span_err else None,
    }
    if use_force:
        statistic["objective"] += " + force_rms / force_noise"
    return {
        "identifiable": identifiable,
        "value": centre if identifiable else None,
        "interval": [lo_i, hi_i] if identifiable else None,
        "reason": reason,
        "statistic": statistic,
    }


def sweep_verdict(
    prepared: PreparedSession,
    result,
    *,
    executor: Executor | None = None,
    use_force: bool | None = None,
    noise: tuple[float, float | None] | None = None,
    n_boot: int = 400,
    seed: int = 0,
    calibration: bool = True,
    min_rise: float = MIN_RISE,
    max_ratio: float = MAX_RATIO,
) -> dict:
    """The fit's verdict on E from a sweep's trials (:func:`core.identification.sweep.sweep`).

    The sweep's replays are the profile: the fit's objective J (the RMS signed top
    residual over its noise, plus the force RMS over its noise with force data) is
    evaluated from their per-frame residuals at every swept E, the bootstrap resamples
    their frames and sequences, and :func:`youngs_verdict` decides. The point estimate is
    the parabolic argmin of J through the grid's minimum and its two neighbours (log E), the
    bootstrap's estimator. When the rest of the rule holds, the calibration term is
    measured as the fit does (5 more E values near the optimum, with the probe one
    sigma higher; ``calibration=False`` skips it and says so).

    Args:
        prepared: the session the sweep replayed. result: its ``SweepResult``.
        executor: where the calibration replays run (default: in this process).
        use_force: the force term (default: when every swept sequence has force columns).
        noise: the weights (d0 m, f0 N or None) when known; default: measured on the
            rest frames of the swept sequences, as the fit measures them on its train ones.
        n_boot, seed: bootstrap replicates and seed (the fit's defaults).

    Returns:
        the verdict of :func:`youngs_verdict`, plus ``"method"``, ``"grid"``, ``"law"``,
        ``"interval_sources"`` and ``"objective"`` (the noise levels, m and N).
        Everything is on the sweep's grid: the fit also refits on a refined grid and
        widens its interval by the model form (with force data), which a sweep does not.
    """
    rows = list(result.results)
    if not rows:
        return {"identifiable": False, "value": None, "interval": None, "reason": "the sweep has no trials", "statistic": {}}
    names = list(dict.fromkeys(r.trial.sequence for r in rows))
    by_E: dict[float, dict] = {}
    for r in rows:
        by_E.setdefault(float(r.trial.youngs_modulus), {})[r.trial.sequence] = r
    base = replace(rows[0].trial, sequence="", youngs_modulus=1.0)
    has_force = all(prepared.sequences[n].force is not None for n in names)
    use_force = has_force if use_force is None else (use_force and has_force)
    if noise is not None:
        d0, f0 = float(noise[0]), (None if noise[1] is None or not use_force else float(noise[1]))
    else:
        d0 = top_noise(prepared, names, base.grid)
        if not np.isfinite(d0) or d0 <= 0:
            d0 = 1e-3
        f0 = force_noise(prepared, names) if use_force else None
    obj = Objective(prepared, names, base, executor or SerialExecutor(), use_force, d0, f0, None, "top")
    obj.cache = {E: [rs[n] for n in names] for E, rs in by_E.items() if all(n in rs for n in names)}
    Es = np.array(sorted(obj.cache))
    J = np.array([obj.terms(E)[0] for E in Es])
    scope = "train" if all(prepared.sequences[n].role == "train" for n in names) else "swept sequences'"
    structural = structurally_identifiable(base, use_force)
    extra = {
        "method": "the fit's rule (core.identification.verdict) on the swept values of E",
        "grid": list(base.grid),
        "law": base.law,
        "sequences": names,
        "objective": {"noise_floor_m": float(d0), "force_noise_N": f0},
    }
    errors = result.table()
    if not np.isfinite(J).any():
        out = youngs_verdict(Es, J, structural=structural, bootstrap=(math.nan, math.nan), errors=errors,
                             min_rise=min_rise, max_ratio=max_ratio)
        return {**out, **extra, "interval_sources": None}
    i = int(np.argmin(np.where(np.isfinite(J), J, np.inf)))
    E_star, J_star = float(Es[i]), float(J[i])
    d_star = obj.terms(E_star)[1]
    boot = bootstrap_argmin(obj, Es, n_boot, seed, 1.0)
    lo_b, hi_b = (float(v) for v in np.percentile(boot, [2.5, 97.5]))
    value = argmin_log(Es, J)
    kw = dict(structural=structural, bootstrap=(lo_b, hi_b), E_star=E_star, J_star=J_star, value=value,
              min_rise=min_rise, max_ratio=max_ratio, residual=d_star, metric="top", use_force=use_force,
              scope=scope, errors=errors)
    out = youngs_verdict(Es, J, **kw)
    sigma = float(prepared.calibration.probe_sigma)
    shift, calibrated = 0.0, False
    if out["identifiable"] and calibration and math.isfinite(sigma) and sigma > 0:
        shift, _ = calibration_shift(obj, value, sigma)
        calibrated = True
        out = youngs_verdict(Es, J, calibration_shift=shift, **kw)
    if out["identifiable"] and not calibrated:
        out["reason"] += "; the robot calibration's uncertainty is not in this interval"
    out.update(extra)
    out["interval_sources"] = {
        "bootstrap_frames_sequences": [lo_b, hi_b],
        "probe_height_sigma_m": sigma if math.isfinite(sigma) else None,
        "relative_shift_per_probe_sigma": float(10.0**shift - 1.0) if calibrated else None,
        "model_form": None,
    }
    return out
