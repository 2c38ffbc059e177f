"""Levenberg-Marquardt fits of the candidate causes (and of Young's modulus) on train."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from core.diagnosis.evidence import Discrepancy, Evidence, Spec
from core.diagnosis.inference import cluster_robust_covariance
from core.diagnosis.nuisance import Nuisance
from core.diagnosis.trials import Directions
from core.identification.model_form import ModelFormVariant
from core.simulation.effects import EFFECT_KINDS, FitSpace

__all__ = ["Fit", "fit_candidate", "rss", "SCALE_FREE", "E_STEP", "LM_DAMPING", "LM_DAMPING_SHORT", "SPECULATIVE_TRIALS"]

SCALE_FREE = frozenset(k for k, c in EFFECT_KINDS.items() if c.scales_with_youngs)
"""Effect kinds that keep the model's displacements unchanged and scale its forces with E
(declared by each kind: ``Effect.scales_with_youngs``)."""
E_STEP = 0.02
"""Forward-difference step of log10 E in the joint fits where it is not semi-analytic."""
LM_DAMPING = (1e-3, 1e-1, 1.0)
"""Levenberg-Marquardt damping values (times the diagonal of J^T J) of each iteration's trial steps."""
LM_DAMPING_SHORT = (10.0, 100.0)
"""Further damping values a fit of one to three variables tries in turn when none of
:data:`LM_DAMPING`'s steps lowered its misfit (shorter steps along the gradient). Without
them a 5 mm robot offset's fit (field seed 11, no force) stopped at 0.77 mm, its misfit
still falling along the offset (30084 there, 29182 at 2 mm, 27649 at 5 mm, chi2 units);
with them it went on to 3.5 mm in the same iterations."""

SPECULATIVE_TRIALS = 1
"""How many of a fit's trial steps (tried in turn, longest first) are replayed with their
derivatives, so that the next iteration's Jacobian is ready if the step is taken; the
shorter ones are plain replays. Measured on field gravity seed 0 (4 x 12 s, force; stop 58):
the first trial step was taken in 44 of 57 iterations, and 29 shorter ones had been replayed
with derivatives, of which 7 were taken (in two iterations, of a compliant base and a robot
offset, all five steps were refused)."""


@dataclass
class Fit:
    """A candidate's fit.

    Attributes:
        x: (n,) fit variables (with a joint E, log10 E is the last). se: (n,) their
            standard errors (inf when the Jacobian is singular).
        train_rss: squared norm of the (nuisance-projected) train residual vector.
        effect: the effect dict at ``x`` (None for an E-only fit).
        youngs_modulus: the model's E, Pa.
        jacobian: (L, n) the last Jacobian on train (of the residual vector itself, not
            nuisance-projected; at the last iterate but one when the last step was
            accepted), or None.
        starts: number of starting points tried (a look-elsewhere factor).
        discrepancy: the fine-minus-coarse fields (:data:`~core.diagnosis.evidence.Discrepancy`)
            its coarse runs were corrected by where they are not the base model's: those
            given to the fit, and for a kind that moves the contact those measured at the
            fit on train and validation (None: the base model's).
    """

    x: np.ndarray
    se: np.ndarray
    train_rss: float
    effect: dict | None
    youngs_modulus: float
    jacobian: np.ndarray | None = None
    starts: int = 1
    discrepancy: dict | None = None

    @property
    def effects(self) -> list[dict]:
        return [] if self.effect is None else [self.effect]



def rss(v: np.ndarray) -> float:
    return float(v @ v) if np.all(np.isfinite(v)) else math.inf


def fit_candidate(eng: Evidence, cand: FitSpace | None, fixed: list[dict], *, E: float | None = None,
                  fit_youngs: bool = False, start: np.ndarray | None = None, fine: bool = False,
                  iterations: int | None = None, nuisance: Nuisance | None = None,
                  world: ModelFormVariant | None = None, differences: bool = False,
                  discrepancy: Discrepancy | None = None, relinearise: int | None = None) -> Fit:
    """Levenberg-Marquardt fit of one candidate's variables on train, the other effects
    ``fixed`` (on the coarse grid with the discrepancy shift, or on the fine grid when
    ``fine``); Nocedal & Wright (2006), Sec. 10.3. The Jacobian (the candidate's
    signature) is the replay's exact sensitivity (:mod:`core.simulation.sensitivity`),
    or with ``cfg.sensitivities`` False a forward difference of one replay per variable.

    Args:
        cand: the candidate; None fits E alone (``fit_youngs`` must be set).
        E: Young's modulus of the model (Pa; default the configured one); the start of
            log10 E when ``fit_youngs``.
        fit_youngs: fit log10 E jointly, as the last variable.
        start: a single starting vector (candidate's variables only) instead of ``cand.starts``.
        iterations: most iterations (default ``cfg.lm_iterations``).
        nuisance: fit the residual that the nuisance directions leave (variable
            projection: their coefficients are solved in closed form at every point).
        world: fit in another model-form world: this law, Poisson's ratio and Yeoh
            stiffening (its grid is ignored: ``fine`` chooses), coarse runs unshifted
            (the discrepancy shift maps the replay's coarse model onto its fine one,
            not another model's).
        differences: forward-difference Jacobians even with ``cfg.sensitivities`` (a
            step's secant, where the exact derivative is local to a near-bifurcation:
            measured on field seed 68's compliant base on 13x5x5 at nu 0.48, d force /
            d log10 E up to 39 kN on a train sequence where nu 0.44 gives at most 0.15 N,
            and the fit then took no step).
        discrepancy: the fine-minus-coarse fields that correct the coarse runs where they
            are not the base model's (the round's model's, :class:`~core.diagnosis.rounds.Round`).
        relinearise: for a kind that moves the contact (``Effect.moves_contact``) on the
            coarse grid, how often the discrepancy is measured again at the fit and the fit
            continued from there (default ``cfg.contact_relinearisations``); the returned
            fit carries the discrepancy at its parameters on train and validation.
    """
    sigma2 = eng.sigma2
    E0 = float(E or eng.cfg.youngs_modulus)
    nv = 0 if cand is None else len(cand.names)
    steps = np.zeros(0) if cand is None else cand.steps
    lo_E, hi_E = math.log10(E0) - 2.0, math.log10(E0) + 2.0

    def clip(x):
        head = x[:nv] if cand is None else cand.clip(x[:nv])
        return np.concatenate([head, np.clip(x[nv:], lo_E, hi_E)])

    # fits on the fine grid step at cfg.fine_fit_dt (its reported runs at the simulator's default)
    sim = eng.cfg.fine_step if fine else ()

    material = {} if world is None else {"law": world.law, "poisson_ratio": world.poisson_ratio,
                                         "stiffening": world.stiffening}
    shifted = not fine and world is None

    def spec(x) -> Spec:
        eff = [] if cand is None else [cand.to_effect(x[:nv])]
        return Spec(tuple(fixed) + tuple(eff), float(10.0 ** x[nv]) if fit_youngs else E0, simulation=sim, **material)

    def runs(xs):
        return eng.runs([spec(x) for x in xs], "train", fine=fine)

    def raw(r):
        return eng.vector(r, shifted=shifted, discrepancy=discrepancy)

    def vec(r):
        v = raw(r)
        return v if nuisance is None else nuisance.project(v)

    tail = [math.log10(E0)] if fit_youngs else []
    kinds = {e["kind"] for e in fixed} | ({cand.kind} if cand is not None else set())
    semi_analytic = kinds <= SCALE_FREE and nuisance is None
    heads = [start] if start is not None else ([np.zeros(0)] if cand is None else list(cand.starts))
    starts = [clip(np.concatenate([np.asarray(h, dtype=np.float64), tail])) for h in heads]
    n_iter = eng.cfg.lm_iterations if iterations is None else iterations
    # exact Jacobians, except for E alone among scale-free kinds: its semi-analytic column
    # (below) needs no replay of its own
    exact = eng.cfg.sensitivities and not differences and not (cand is None and fit_youngs and semi_analytic)

    def jacobian_at(x):
        """(raw vector, its exact Jacobian) at x: one replay differentiated along every variable."""
        d = Directions(tuple(fixed), cand, x[:nv], spec(x).youngs_modulus, fit_youngs, simulation=sim, **material)
        rj = eng.jacobian_runs([d], "train", fine=fine)[0]
        return raw(rj), eng.jacobian(rj, shifted=shifted, discrepancy=discrepancy)

    J = J_raw = J_next = None
    if exact and len(starts) == 1 and starts[0].size > 0 and n_iter > 0:
        # a single start: its replay with derivatives is the first iteration's Jacobian too
        # (a plain replay of it first would be thrown away)
        x = starts[0]
        raw_x, J_next = jacobian_at(x)
    else:
        runs0 = runs(starts)
        misfits = [rss(vec(r)) for r in runs0]
        i = int(np.argmin(misfits))
        x, raw_x = starts[i], raw(runs0[i])
    r_x = raw_x if nuisance is None else nuisance.project(raw_x)
    for it in range(n_iter):
        if not np.all(np.isfinite(r_x)) or x.size == 0:
            break
        pts = []
        for j, h in enumerate(steps):
            xj = x.copy()
            xj[j] = x[j] + h if x[j] + h <= cand.upper[j] else x[j] - h
            pts.append(xj)
        if exact:
            # the exact Jacobian: the replay at x differentiated along every variable (the
            # accepted trial step of the last iteration already was)
            J_raw = J_next if J_next is not None else jacobian_at(x)[1]
            J_next = None
        elif fit_youngs and semi_analytic:
            # the log10 E column is semi-analytic: with every stiffness proportional to E
            # (the contact's too), the quasi-static force is proportional to E at a fixed
            # dent and the field does not depend on it (trial steps are real runs)
            cols = runs(pts)
            J_raw = np.stack([(raw(c) - raw_x) / (s[j] - x[j]) for j, (c, s) in enumerate(zip(cols, pts))]
                             + [eng.youngs_column(runs([x])[0], shifted=shifted)], axis=1)
        else:
            if fit_youngs:
                xe = x.copy()
                xe[nv] = x[nv] + E_STEP
                pts.append(xe)
            cols = runs(pts)
            J_raw = np.stack([(raw(c) - raw_x) / (s[j] - x[j]) for j, (c, s) in enumerate(zip(cols, pts))], axis=1)
        if not np.all(np.isfinite(J_raw)):
            J = J_raw = None
            break
        if nuisance is None:
            J = J_raw
        else:  # the projection is linear on the coefficients inside their bounds
            lin = nuisance.active(raw_x)
            J = np.stack([lin.project(c) for c in J_raw.T], axis=1)
        A, g = J.T @ J, J.T @ r_x
        D = np.diag(np.maximum(np.diag(A), 1e-30))
        previous = rss(r_x)
        steps_lm = []
        in_turn = fine or x.size < 4
        for lam in LM_DAMPING + (LM_DAMPING_SHORT if in_turn else ()):
            try:
                steps_lm.append(clip(x + np.linalg.solve(A + lam * D, -g)))
            except np.linalg.LinAlgError:
                continue
        accepted = None
        if in_turn:
            # the damping values are tried in turn and the first step that lowers the misfit
            # is taken (Levenberg-Marquardt as in Nocedal & Wright Sec. 10.3): on the fine
            # grid a replay costs ~20 coarse ones, and fits of one to three variables are
            # close to linear
            for k_try, x_try in enumerate(steps_lm):
                # the first trial's Jacobian serves the next iteration if it is taken (none
                # follows the last); the shorter steps, tried only once a longer one was
                # refused, are plain replays (their Jacobian, one replay with derivatives,
                # 2-5 plain ones, is made at the next iteration if one is taken):
                # :data:`SPECULATIVE_TRIALS`
                if exact and it < n_iter - 1 and k_try < SPECULATIVE_TRIALS:
                    raw_try, J_try = jacobian_at(x_try)
                else:
                    raw_try, J_try = raw(runs([x_try])[0]), None
                r_try = raw_try if nuisance is None else nuisance.project(raw_try)
                if rss(r_try) < previous:
                    accepted = (x_try, r_try, raw_try)
                    J_next = J_try
                    break
        elif steps_lm:
            # fits of four variables or more (an inclusion): all of them are replayed and the
            # best is taken, fewer iterations for a nonlinear fit far from its start
            out = [raw(o) for o in runs(steps_lm)]
            projected = [o if nuisance is None else nuisance.project(o) for o in out]
            vals = [rss(o) for o in projected]
            k = int(np.argmin(vals))
            if vals[k] < previous:
                accepted = (steps_lm[k], projected[k], out[k])
        if accepted is None:
            break
        x, r_x, raw_x = accepted
        if previous - rss(r_x) < eng.cfg.lm_tolerance * sigma2:
            break  # converged: the last step gained less than lm_tolerance in chi2
    se = np.full(x.size, np.inf)
    if J is not None:
        try:
            var = np.diag(sigma2 * np.linalg.inv(J.T @ J))
            # the model-form gap leaves residuals correlated over a poke: the cluster-robust
            # covariance over the bootstrap's blocks, where it is the wider
            blocks = eng.blocks("train")
            robust = cluster_robust_covariance(J, r_x, blocks) if blocks.shape == r_x.shape else None
            if robust is not None and np.all(np.isfinite(robust)):
                var = np.maximum(var, np.diag(robust))
            se = np.sqrt(np.maximum(var, 0.0))
        except np.linalg.LinAlgError:
            pass
    sp = spec(x)
    fit = Fit(x, se, rss(r_x), None if cand is None else cand.to_effect(x[:nv]), sp.youngs_modulus,
              jacobian=J_raw, starts=len(starts), discrepancy=None if discrepancy is None else dict(discrepancy))
    rounds = eng.cfg.contact_relinearisations if relinearise is None else relinearise
    if (cand is None or not EFFECT_KINDS[cand.kind].moves_contact or not shifted or not eng.cfg.fine_grid
            or rounds <= 0 or not np.all(np.isfinite(x))):
        return fit
    # the mesh error moves with the press: measured again at the fit, and the fit continued
    # from there (Evidence.discrepancy_at); the last fit's, on train and validation, goes with it
    for i in range(rounds + 1):
        model = Spec(sp.effects, sp.youngs_modulus, **material)
        here = dict(discrepancy or {})
        here.update(eng.discrepancy_at(model, ("train",) if i < rounds else ("train", "validation")))
        if i == rounds:
            return replace(fit, discrepancy=here)
        fit = fit_candidate(eng, cand, fixed, E=fit.youngs_modulus if fit_youngs else E, fit_youngs=fit_youngs,
                            start=fit.x[:nv], iterations=iterations, nuisance=nuisance, world=world,
                            differences=differences, discrepancy=here, relinearise=0)
        fit = replace(fit, starts=len(starts))
        sp = spec(fit.x)
    return fit


