"""Young's modulus of the diagnosis's extended model, and the interval it can state.

With force data, E is fitted jointly with the claimed causes to the force and the residual
field, and its 95 % interval holds the Levenberg-Marquardt covariance and the model-form
range (:func:`core.identification.model_form.youngs_model_form`: other laws, Poisson's
ratios and grids). Without force data E comes from
:func:`core.identification.fit_youngs_modulus`, which says when it cannot be identified.
Split from the engine (over 600 lines), which holds the selection rounds.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from core.diagnosis.config import DiagnosisConfig
from core.diagnosis.evidence import Evidence
from core.diagnosis.fitting import Fit, fit_candidate
from core.identification.fit import fit_youngs_modulus
from core.identification.model_form import youngs_model_form
from core.identification.trials import Trial
from core.identification.verdict import MAX_RATIO
from core.preparation import PreparedSession

__all__ = ["joint_youngs", "gravity_at_reported_youngs", "youngs_of_extended"]


def joint_youngs(fit: Fit, model_form: dict | None = None) -> dict:
    """The youngs_modulus entry of diagnosis.json from a joint fit (log10 E last): the
    value, and a 95 % interval that holds the Levenberg-Marquardt covariance's and the
    model-form range (``model_form`` of
    :func:`core.identification.model_form.youngs_model_form`: E refitted under other
    laws, Poisson's ratios and grids, each widened by the statistical interval);
    identifiable by the fit's rule (:mod:`core.identification.verdict`): force data set a
    scale, and the interval spans at most :data:`~core.identification.verdict.MAX_RATIO`
    (3x). ``value`` stays the estimate either way (SESSION_FORMAT: it may be null)."""
    lg, se = float(fit.x[-1]), float(fit.se[-1])
    if not np.isfinite(se):
        return {"value": fit.youngs_modulus, "interval": None, "identifiable": False,
                "method": "fitted jointly with the claimed causes to the force and the residual field",
                "reason": "the joint fit's Jacobian is singular"}
    stat = [10.0 ** (lg - 1.96 * se), 10.0 ** (lg + 1.96 * se)]
    lo, hi = stat
    out = {"value": fit.youngs_modulus, "statistical_interval": stat,
           "method": "fitted jointly with the claimed causes to the force and the residual field"}
    if model_form and model_form.get("low") is not None:
        f = 10.0 ** (1.96 * se)
        lo, hi = min(lo, model_form["low"] / f), max(hi, model_form["high"] * f)
        out["model_form"] = model_form
        # the reported value: the middle of the model-form range on a log scale (no variant
        # preferred, the largest factor off any of them the smallest); the replay's E beside it
        out["model_value"] = fit.youngs_modulus
        out["value"] = float(np.sqrt(model_form["low"] * model_form["high"]))
    holds = ("statistical and model form: the law, Poisson's ratio and grid variants" if model_form
             else "statistical")
    # the fit's rule (core.identification.verdict): force sets a scale (structural), and the
    # 95 % interval spans at most MAX_RATIO; here the interval also holds the model form
    ratio = hi / lo
    ok = bool(ratio <= MAX_RATIO)
    interval = f"the 95 % interval {lo:.3g}-{hi:.3g} Pa ({holds}) spans a factor {ratio:.2f}"
    out.update({"interval": [lo, hi], "identifiable": ok,
                "reason": (f"force data set the scale of E; {interval}" if ok else
                           f"force data set a scale, but {interval} (> {MAX_RATIO:g}): the data and the model form "
                           "cannot pin E down"),
                "statistic": {"rule": "core.identification.verdict (the fit's): structural and interval",
                              "structural": True, "interval": [lo, hi], "ratio": ratio, "max_ratio": MAX_RATIO}})
    return out


def gravity_at_reported_youngs(g, youngs: dict | None) -> float | None:
    """|g| (m/s^2) of a gravity fitted on the replay grid, read at the reported E.

    The sag is set by rho g / E, so a gravity fitted at the replay grid's E (stiffened by
    volumetric locking on 13x5x5) reads, at the reported mesh-corrected E, as
    ``|g| x value / replay_grid_value_used``.

    Args:
        g: (3,) the fitted gravity, m/s^2. youngs: diagnosis.json's ``youngs_modulus``.

    Returns:
        that |g|, or None when the two E are missing or equal within 1 %.
    """
    E, E_grid = (youngs or {}).get("value"), (youngs or {}).get("replay_grid_value_used")
    if not E or not E_grid or abs(E / E_grid - 1.0) <= 0.01:
        return None
    return float(np.linalg.norm(np.asarray(g, dtype=np.float64)) * E / E_grid)


def youngs_of_extended(prepared: PreparedSession, ev: Evidence, cfg: DiagnosisConfig, executor, *,
                       joint: bool, claimed: bool, effects: list[dict], youngs_modulus: float, e_fit: Fit | None,
                       say: Callable[[float, str], None] = lambda p, m: None) -> tuple[dict, float, list[dict]]:
    """Young's modulus of the extended model: diagnosis.json's ``youngs_modulus``.

    With force data (``joint``), E is refitted with the claimed ``effects`` on the fine grid
    (when a cause was ``claimed``; else ``e_fit``, the last round's fit, stands), under the
    model-form variants. Without force data :func:`core.identification.fit_youngs_modulus`
    fits E with the claimed effects (a gravity at its physical 9.81 m/s^2, since the fit
    measures g / E).

    Args:
        executor: the diagnosis's :class:`~core.identification.execution.Executor`.
        effects: the claimed causes' effect dicts (fitted on the fine grid).
        youngs_modulus: the model's current E (Pa, coarse grid).

    Returns:
        (the ``youngs_modulus`` dict with ``replay_grid_value_used``, the E the test stage
        replays with (Pa), the effects it replays with).
    """
    E_ext = youngs_modulus
    if joint:
        if claimed:
            e_fit = fit_candidate(ev, None, effects, E=youngs_modulus, fit_youngs=True, fine=bool(cfg.fine_grid),
                                  iterations=max(cfg.fine_refit_iterations, 1))
        E_ext = e_fit.youngs_modulus
        say(0.74, "Young's modulus under other laws, Poisson's ratios and grids")
        mf = youngs_model_form(prepared, effects, E_ext, executor=executor, element_size=cfg.element_size)
        ev.simulations += len(mf["variants"]) * len(ev.names["train"])
        youngs = joint_youngs(e_fit, mf)
    else:
        say(0.75, "fitting Young's modulus with the claimed causes")
        fit_effects = [({"kind": "gravity", "g": list(9.81 * np.asarray(e["g"]) / max(np.linalg.norm(e["g"]), 1e-12))}
                        if e["kind"] == "gravity" else e) for e in effects]
        youngs = {"value": None, "interval": None, "identifiable": False, "reason": "not fitted"}
        if cfg.fit_youngs:
            fit = fit_youngs_modulus(
                prepared, base=Trial(sequence="", youngs_modulus=1.0, poisson_ratio=cfg.poisson_ratio, grid=cfg.grid,
                                     law=cfg.law, effects=tuple(fit_effects)),
                executor=executor, refine_mesh=cfg.refine_mesh, n_boot=cfg.n_boot, seed=cfg.seed)
            ev.simulations += fit.evaluations
            youngs = fit.to_json()["youngs_modulus"]
            if fit.identifiable:
                E_ext = fit.coarse_value
                effects = fit_effects
    youngs["replay_grid_value_used"] = E_ext
    return youngs, E_ext, effects
