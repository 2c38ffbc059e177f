"""A selection round of the diagnosis and its candidates' held-out evidence.

:class:`Round` is the model of one round of the greedy forward selection
(:func:`core.diagnosis.engine.diagnose_prepared`): its fixed causes, Young's modulus,
nuisances and held-out test. :func:`assess_all` fits every candidate kind on train beside
the round's nuisances and :func:`judge` turns each fit into its held-out evidence: the drop
of the validation chi-square, its null distribution from the wild block bootstrap
(:class:`core.diagnosis.inference.HeldOutTest`), the critical value at the kind's share of
the family-wise rate, the per-channel worsening and the reproduction check.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from core.diagnosis.claims import channel_worsening, claim_check, reproduction
from core.diagnosis.config import DiagnosisConfig
from core.diagnosis.evidence import Evidence, Request, Spec
from core.diagnosis.fitting import Fit, fit_candidate
from core.diagnosis.inference import HeldOutTest
from core.diagnosis.model_form import beyond_finer_mesh, beyond_model_form, model_form_drops, refit_size
from core.diagnosis.nuisance import Nuisance
from core.diagnosis.trials import Directions, FieldRun
from core.simulation.effects import EFFECT_KINDS, FitSpace

__all__ = ["Round", "CandidateEvidence", "channel_masks", "TANGENT_BLOWUP", "trusted_columns", "assess_all", "judge",
           "beyond_verdict", "model_form_json"]


@dataclass
class Round:
    """The model of a selection round and its held-out test."""

    fixed: list
    youngs_modulus: float
    nuisance: Nuisance
    test: HeldOutTest
    train: list          # FieldRun of the round's model on train
    validation: list     # ... on validation
    r_train: np.ndarray  # its residual vectors
    r_validation: np.ndarray
    chi2: float          # its held-out validation chi2
    _model_form: dict | None = None
    discrepancy: dict | None = None  # its coarse runs' fine-minus-coarse fields, where not the base model's

    def model_form(self, ev: Evidence) -> tuple[str, float]:
        """(variant, T): the model-form variant at an end of its plausible range with the
        largest held-out drop on this round's model (:func:`core.diagnosis.model_form.model_form_drops`),
        ("", 0.0) when none lowers it. Simulated once per round, when first asked."""
        if self._model_form is None:
            self._model_form = model_form_drops(ev, self.fixed, self.youngs_modulus, self.nuisance,
                                                self.r_train, self.r_validation, discrepancy=self.discrepancy)
        best = max(self._model_form.items(), key=lambda kv: kv[1], default=("", 0.0))
        return best if best[1] > 0 else ("", 0.0)

    @classmethod
    def build(cls, ev: Evidence, fixed: list, E: float, cfg: DiagnosisConfig, seed: int) -> "Round":
        """The round of the model ``fixed`` at ``E`` (Pa): its nuisances, runs, residuals and
        held-out test. When the model holds a cause that moves the contact
        (``Effect.moves_contact``), its coarse runs are corrected by the mesh error measured
        on it (:meth:`~core.diagnosis.evidence.Evidence.discrepancy_at`), not the base model's."""
        nuis = Nuisance.build(ev, fixed, E, cfg.nuisances)
        spec = Spec(tuple(fixed), float(E))
        disc = None
        if cfg.contact_relinearisations > 0 and any(EFFECT_KINDS[e["kind"]].moves_contact for e in fixed):
            disc = ev.discrepancy_at(spec, ("train", "validation")) or None
        tr, va = ev.runs([spec], "train")[0], ev.runs([spec], "validation")[0]
        r_t, r_v = ev.vector(tr, discrepancy=disc), ev.vector(va, discrepancy=disc)
        e_t, e_v = nuis.project(r_t), nuis.held_out(r_v, r_t)
        test = HeldOutTest(nuis.active(r_t), e_t, e_v, ev.blocks("train"), ev.blocks("validation"), ev.sigma2,
                           replicates=cfg.n_null, seed=seed)
        return cls(list(fixed), float(E), nuis, test, tr, va, r_t, r_v, float(e_v @ e_v) / ev.sigma2,
                   discrepancy=disc)


@dataclass
class CandidateEvidence:
    """One candidate's fit and held-out evidence in a round."""

    fit: Fit
    validation: list     # FieldRun of the round's model plus the candidate on validation
    statistic: float     # T, chi2 units
    by_channel: tuple    # (field, force or None)
    null: np.ndarray
    p_value: float
    critical: float
    channels: dict       # channel_worsening of the held-out residual, per channel
    reproduction: dict   # core.diagnosis.claims.reproduction: the drop against the fitted change's own worth


def channel_masks(ev: Evidence, role: str) -> dict[str, np.ndarray]:
    """{channel: (L,) bool} over a residual vector of ``role``: the top face's bins
    ("top"), the side faces' bins ("sides", when the layout has them) and the force
    ("force", with force data)."""
    side_of_bin = ev.layout.face_of_bin() > 0
    top, side, force = [], [], []
    B = ev.layout.n_bins
    for n in ev.names[role]:
        F = ev.prepared.sequences[n].frame_times.size
        s = np.tile(side_of_bin, F)
        top.append(~s), side.append(s), force.append(np.zeros(F * B, dtype=bool))
        if ev.use_force:
            z = np.zeros(F * 3, dtype=bool)
            top.append(z), side.append(z), force.append(np.ones(F * 3, dtype=bool))
    out = {"top": np.concatenate(top), "sides": np.concatenate(side), "force": np.concatenate(force)}
    return {k: v for k, v in out.items() if v.any()}


TANGENT_BLOWUP = 1e4
"""A signature column whose RMS per residual on validation exceeds this many times its RMS on
train is no local signature: train and validation palpate the same phantom with the same
probe. Measured: a compliant base's exact sensitivity on the validation sequence of field
seed 51 (4 x 12 s, a side poke) came out 1.3e19 against 70 on train (the forward runs
finite), and the null built from it put the kind's critical value at 2.6e35, so it could
neither be claimed nor bounded. The replay there is not smooth in the parameter: on that
soft base (log10 k = 5, about 270 N/m in every direction under the whole phantom) the held
side press makes the contact force chatter from frame to frame, and central differences of
it grow as 1/h (a jump of ~1 N)."""


def trusted_columns(J_t: np.ndarray, J_v: np.ndarray) -> np.ndarray:
    """(p,) bool: the columns of the train and validation signatures ``J_t`` (L_t, p), ``J_v``
    (L_v, p) that carry a signature: finite on both, and not blown up on validation
    (:data:`TANGENT_BLOWUP`). The others are dropped from the null, as a run that diverged."""
    finite = np.all(np.isfinite(J_t), axis=0) & np.all(np.isfinite(J_v), axis=0)
    with np.errstate(over="ignore", invalid="ignore"):  # a NaN or an overflow compares False
        rms_t = np.sqrt(np.mean(J_t**2, axis=0))
        rms_v = np.sqrt(np.mean(J_v**2, axis=0))
    return finite & (rms_v <= TANGENT_BLOWUP * rms_t)


def validation_jacobian(ev: Evidence, cand: FitSpace, fixed: list, E: float, x: np.ndarray,
                         r_v: np.ndarray, runs: list[FieldRun] | None,
                         discrepancy: dict | None = None) -> np.ndarray | None:
    """(L_v, n) signature of ``cand`` at ``x`` on validation: the exact sensitivity (``runs``,
    the validation runs of :func:`held_out_requests`' jacobian request), or with
    ``cfg.sensitivities`` False a forward difference (``discrepancy``: the fit's, as in
    :meth:`~core.diagnosis.evidence.Evidence.vector`)."""
    if ev.cfg.sensitivities:
        J = ev.jacobian(runs, discrepancy=discrepancy)
        return J if np.all(np.isfinite(J)) else None
    pts = []
    for j, h in enumerate(cand.steps):
        xj = x.copy()
        xj[j] = x[j] + h if x[j] + h <= cand.upper[j] else x[j] - h
        pts.append(cand.clip(xj))
    runs = ev.runs([Spec(tuple(fixed) + (cand.to_effect(p),), E) for p in pts], "validation")
    cols = []
    for p, r, j in zip(pts, runs, range(len(pts))):
        d = p[j] - x[j]
        if d == 0:
            return None
        cols.append((ev.vector(r, discrepancy=discrepancy) - r_v) / d)
    J = np.stack(cols, axis=1)
    return J if np.all(np.isfinite(J)) else None


def held_out_requests(ev: Evidence, cand: FitSpace, rnd: Round, fit: Fit) -> list[Request]:
    """The runs :func:`judge` needs of a fit: the round's model plus the fitted cause on
    train and validation, and with exact sensitivities its validation signature."""
    spec = Spec(tuple(rnd.fixed) + tuple(fit.effects), rnd.youngs_modulus)
    reqs = [Request([spec], "train"), Request([spec], "validation")]
    if fit.jacobian is not None and ev.cfg.sensitivities:
        d = Directions(tuple(rnd.fixed), cand, fit.x[: len(cand.names)], rnd.youngs_modulus)
        reqs.append(Request([d], "validation", jacobian=True))
    return reqs


def assess_all(ev: Evidence, cands: dict[str, FitSpace], rnd: Round, cfg: DiagnosisConfig, n_kinds: int,
                channels: dict[str, np.ndarray], starts: dict[str, np.ndarray | None] | None = None,
                progress: Callable[[int, str], None] | None = None) -> dict[str, CandidateEvidence]:
    """Fit every kind of ``cands`` on train beside the round's nuisances (from ``starts[kind]``
    when given, else from the kind's starts; its look-elsewhere factor is the kind's declared
    ``searches`` either way), then judge each on validation (:func:`judge`). The fits run
    one after another; their held-out runs (a validation sequence each, one worker's work
    when asked alone) all go through one executor map."""
    starts = starts or {}
    fits = {}
    for i, (kind, cand) in enumerate(cands.items()):
        if progress is not None:
            progress(i, kind)
        fits[kind] = fit_candidate(ev, cand, rnd.fixed, E=rnd.youngs_modulus, nuisance=rnd.nuisance,
                                   start=starts.get(kind), discrepancy=rnd.discrepancy)
    reqs = {kind: held_out_requests(ev, cand, rnd, fits[kind]) for kind, cand in cands.items()}
    flat = ev.runs_together([r for rs in reqs.values() for r in rs])
    out, at = {}, 0
    for kind, cand in cands.items():
        got = [runs[0] for runs in flat[at: at + len(reqs[kind])]]
        at += len(reqs[kind])
        out[kind] = judge(ev, cand, rnd, cfg, n_kinds, channels, fits[kind], got[0], got[1],
                           got[2] if len(got) > 2 else None)
    return out


def judge(ev: Evidence, cand: FitSpace, rnd: Round, cfg: DiagnosisConfig, n_kinds: int,
           channels: dict[str, np.ndarray], fit: Fit, tr: list[FieldRun], va: list[FieldRun],
           jac_v: list[FieldRun] | None) -> CandidateEvidence:
    """A candidate's held-out evidence from its fit and the runs of :func:`held_out_requests`
    (``tr``, ``va``: the fitted model on train and validation; ``jac_v``: its validation
    signature runs, or None); ``channels``: :func:`channel_masks` of the validation vector.
    The fitted model's coarse runs are corrected by the fit's discrepancy (``Fit.discrepancy``:
    the round's, or for a kind that moves the contact the one measured at the fit)."""
    r_t, r_v = ev.vector(tr, discrepancy=fit.discrepancy), ev.vector(va, discrepancy=fit.discrepancy)
    h = rnd.nuisance.held_out(r_v, r_t)
    e_v = rnd.nuisance.held_out(rnd.r_validation, rnd.r_train)
    if not np.all(np.isfinite(h)):
        return CandidateEvidence(fit, va, -math.inf, (-math.inf, None), np.zeros(1), 1.0, math.inf, {}, {})
    d = (e_v**2 - h**2) / ev.sigma2
    T = float(d.sum())
    force = channels.get("force", np.zeros(d.size, dtype=bool))
    chans = (float(d[~force].sum()), float(d[force].sum()) if ev.use_force else None)
    # the null's signature: the fit's local Jacobian and the secant of the change it made
    # (where the local signature on validation vanishes, the secant still carries the
    # change; a null without it let a fit far from linear pass with any held-out drop)
    cols_t, cols_v = [r_t - rnd.r_train], [r_v - rnd.r_validation]
    if fit.jacobian is not None:
        J_v = validation_jacobian(ev, cand, rnd.fixed, rnd.youngs_modulus, fit.x[: len(cand.names)], r_v, jac_v,
                                  discrepancy=fit.discrepancy)
        if J_v is not None:
            cols_t, cols_v = list(fit.jacobian[:, : len(cand.names)].T) + cols_t, list(J_v.T) + cols_v
    J_t, J_v = np.stack(cols_t, axis=1), np.stack(cols_v, axis=1)
    # a direction whose run diverged (a fit's last train Jacobian at a far-off parameter),
    # or whose tangent blew up on validation, carries no signature: the null is built from
    # the others (a NaN in it failed the SVD of the whole diagnosis on a dome)
    finite = trusted_columns(J_t, J_v)
    J_t, J_v = np.where(finite[None], J_t, 0.0), np.where(finite[None], J_v, 0.0)
    keep = finite & (np.linalg.norm(J_t, axis=0) > 0)
    # cfg.null_residual "candidate": the null is drawn from the residual the candidate's fit
    # leaves (HeldOutTest.under), which no longer holds the effect its kind explains
    test = rnd.test.under(rnd.nuisance.project(r_t), h) if cfg.null_residual == "candidate" else rnd.test
    if not np.any(keep):
        null, p = np.zeros(1), 1.0
    else:
        null = test.null(J_t[:, keep], J_v[:, keep])
        # a cause must improve held-out data: the null of a many-parameter fit sits below
        # zero (fitting noise on train costs on validation), and a fit that made
        # validation worse, but less than noise would, is no evidence for the kind
        p = rnd.test.p_value(T, null, cand.searches) if T > 0 else 1.0
    crit = rnd.test.critical(null, cfg.alpha / max(n_kinds * cand.searches, 1))
    blocks = rnd.test.blocks_validation
    worse = channel_worsening(e_v, h, channels, blocks, cfg.consistency_alpha, ev.sigma2) if cfg.consistency_alpha > 0 else {}
    return CandidateEvidence(fit, va, T, chans, null, p, crit, worse, reproduction(e_v, h, ev.sigma2))


def beyond_verdict(rnd: Round, ev: Evidence, e: CandidateEvidence,
                   cand: FitSpace) -> tuple[tuple[str, str] | None, dict | None]:
    """Whether a candidate whose held-out drop passed Holm's procedure is claimed: not when
    its fit sits at a bound of the kind's plausible range (:meth:`FitSpace.at_bound` of
    ``cand``: "at_bound", answer "cannot tell"), then
    :func:`core.diagnosis.claims.claim_check` (reproduced at its fitted size, no channel
    made worse), then the nested test in the model-form worlds
    (:func:`core.diagnosis.model_form.beyond_model_form`):
    "model_form" (answer "cannot tell") when one of them explains its residual; a kind that
    moves the contact also on a mesh finer than the fine reference
    (:func:`core.diagnosis.model_form.beyond_finer_mesh`), "model_form" when it explains
    less than its critical value there.

    A fit at the edge of the range asked for more of the kind than a phantom plausibly
    holds: its residual is of another shape, which the kind takes up as far as it can.
    Measured (with a null drawn from each candidate's own residual, tried at stop 51):
    a hidden compliant base, force, 4 x 6 s, answered by a 15 mm probe radius (3x the
    nominal, its bound); friction claims at mu 1.8-2.0 (its bound 2) before friction
    needed slides.

    Returns:
        (None or ``(reason, why)`` as ``claim_check``'s, ``{"world", "delta_chi2", "passed"}``
        of the nested test for :class:`~core.diagnosis.results.CauseReport`
        ``model_form_nested``, None when it did not run).
    """
    edges = cand.at_bound(e.fit.x)
    if edges:
        return ("at_bound",
                f"cannot tell from this data: its fit explained {e.statistic:.0f} (chi2) of the held-out residual "
                f"with {', '.join(edges)} (the edge of this kind's plausible range): the residual asks for more of "
                "this kind than a phantom plausibly holds, a residual of another shape (a model-form gap) that the "
                "kind took up as far as it could"), None
    verdict = claim_check(e.statistic, e.critical, e.reproduction, e.channels)
    if verdict is not None:
        return verdict, None
    rnd.model_form(ev)  # the worlds' drops, simulated once per round when first asked
    def resize(fields: dict) -> list[dict] | None:  # the candidate's size refitted in a world that refuses it
        return refit_size(ev, rnd.fixed, rnd.youngs_modulus, rnd.nuisance, cand, e.fit.x, fields)

    ok, label, t_w = beyond_model_form(ev, rnd.fixed, rnd.youngs_modulus, rnd.nuisance, e.fit.effects,
                                       rnd._model_form or {}, e.critical,
                                       resize=resize if ev.cfg.nested_size_refit and cand.absent else None)
    nested = {"world": label or None, "delta_chi2": t_w if math.isfinite(t_w) else None, "passed": bool(ok)}
    if ok and EFFECT_KINDS[cand.kind].moves_contact:
        finer = beyond_finer_mesh(ev, rnd.fixed, rnd.youngs_modulus, rnd.nuisance, e.fit.effects, e.critical)
        if finer is not None and not finer[0]:
            _, mesh, t_m = finer
            gain = f"{t_m:.0f} (chi2)" if math.isfinite(t_m) else "nothing (a run diverged)"
            return ("model_form",
                    f"cannot tell from this data: its fit explained {e.statistic:.0f} (chi2) of the held-out residual, "
                    f"but replayed on {mesh} (finer than the fine reference the fit was corrected to) the same fit "
                    f"explains {gain} where a claim needs {e.critical:.0f}: the dent it changes is the mesh's, and the "
                    "data do not tell this kind from the mesh's resolution of the dent"), \
                {"world": mesh, "delta_chi2": t_m if math.isfinite(t_m) else None, "passed": False}
    if ok:
        return None, nested
    gain = f"{t_w:.0f} (chi2)" if math.isfinite(t_w) else "nothing (a run diverged)"
    sized = "the same fit, its size refitted there, " if ev.cfg.nested_size_refit and cand.absent else "the same fit "
    return ("model_form",
            f"cannot tell from this data: its fit explained {e.statistic:.0f} (chi2) of the held-out residual, but "
            f"added to a phantom with {label} (within the model-form gap's plausible range, which explains "
            f"{rnd._model_form[label]:.0f} of it) {sized}explains {gain} where a claim needs "
            f"{e.critical:.0f}: the data do not tell this kind from the base model's own form gap"), nested


def model_form_json(rnd: Round | None, ev: Evidence) -> dict | None:
    """diagnosis.json ``model_form``: the last round's drops and bar, when they were simulated."""
    if rnd is None or rnd._model_form is None:
        return None
    variant, bar = rnd.model_form(ev)
    return {"drops": {k: float(v) for k, v in rnd._model_form.items()}, "variant": variant or None, "bar": float(bar)}
