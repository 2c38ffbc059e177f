"""What a diagnosis returns: per-candidate evidence, per-kind detectability, and the
diagnosis.json contract of ``SESSION_FORMAT.md``."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from core.diagnosis.config import DiagnosisConfig
from core.diagnosis.fields import FieldLayout

__all__ = ["CauseReport", "Detectability", "Diagnosis", "ANSWERS"]

ANSWERS = ("found", "confounded", "not_found", "cannot_tell")
"""The answer for every effect kind: claimed with its parameters; one of two or more kinds
that explain the same residual; nothing of it above its ``min_size``; even a large
effect of it would not show in these sequences and channels."""


@dataclass(frozen=True)
class CauseReport:
    """One candidate's evidence in one selection round.

    Attributes:
        kind: effect kind. parameters: SESSION_FORMAT parameters at the fit.
        fit_variables: {name: (value, standard error, unit)} of the fit variables.
        identifiable: {name: bool}: the 95 % interval of a variable is narrower than
            half a decade (log variables) or than half its value (others).
        delta_chi2: the held-out statistic T: drop of validation chi2 against the model
            of the round (nuisance coefficients carried over from train).
        explained: fraction of that model's validation chi2 it removes.
        confidence: 1 - its Holm-adjusted p-value, [0, 1].
        round: selection round (0 = against the base model).
        claimed: whether it was claimed.
        test_error, gain: paper error on test (m) with this cause alone, and its relative
            gain against the base (claimed causes only, else None).
        force_test_rms, force_gain: with force data, the RMS force error on test (N) with
            this cause alone, and its relative gain (claimed causes only, else None).
        delta_chi2_field, delta_chi2_force: ``delta_chi2`` split by channel (force: None
            without force data).
        p_value: the share of the session's null replicates at or above ``delta_chi2``,
            times the places its fit searched (:mod:`core.diagnosis.inference`).
        critical: the T a claim of this kind needed in its round (its null's quantile at
            alpha over the kinds tested). score: ``delta_chi2 / critical``.
        significant: rejected by Holm's procedure at the round's alpha, and no channel
            made significantly worse (``channels``).
        channels: per channel of the held-out data ("top", "sides", "force"): its chi2
            drop, the wild cluster t of its worsening, that t's critical value and
            whether it was significantly worse (``core.diagnosis.claims.channel_worsening``).
        reproduction: the held-out drop ("observed") against the drop the fitted change
            itself would make ("expected"), chi2 (``core.diagnosis.claims.reproduction``).
        intervals: a claimed cause's 95 % intervals by parameter, statistical and model-form
            (:func:`core.diagnosis.worlds.parameter_intervals`; empty before they are known).
        model_form_bar: the largest held-out drop of the round's model at the ends of its
            model-form range, chi2 (diagnosis.json's ``model_form`` is the last round's), or
            None when its worlds were not simulated (no kind of the round reached the nested
            test: none passed Holm's procedure and :func:`core.diagnosis.claims.claim_check`).
        model_form_nested: for a kind that passed Holm's procedure and
            :func:`core.diagnosis.claims.claim_check`, the nested test in the model-form
            worlds (:func:`core.diagnosis.rounds.beyond_verdict`): ``{"world": the world that
            decided (the first that refused, else where the fit explained least), "delta_chi2":
            the fit's held-out drop added to that world (where the unchanged fit fell short
            there, the drop of its size refitted there: ``DiagnosisConfig.nested_size_refit``),
            "passed": bool}``; None when it did not run.
    """

    kind: str
    parameters: dict
    fit_variables: dict
    identifiable: dict
    delta_chi2: float
    explained: float
    confidence: float
    round: int
    claimed: bool = False
    test_error: float | None = None
    gain: float | None = None
    force_test_rms: float | None = None
    force_gain: float | None = None
    delta_chi2_field: float | None = None
    delta_chi2_force: float | None = None
    p_value: float | None = None
    critical: float | None = None
    score: float | None = None
    significant: bool = False
    channels: dict = field(default_factory=dict)
    reproduction: dict = field(default_factory=dict)
    model_form_bar: float | None = None
    model_form_nested: dict | None = None
    intervals: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Detectability:
    """What this session's data could have told about one effect kind.

    Attributes:
        kind: effect kind.
        min_size: the smallest size of the kind (its size measure of SESSION_FORMAT.md's
            ``detectability`` table) that these data would have claimed, or None: it could
            not be told at any plausible size (up to the kind's ``max_size``).
        parameters: the other parameters it assumed (a vector's direction, an inclusion's
            placement and radius, a relaxation time).
        why: the same in words.
        answer: one of :data:`ANSWERS`.
        unit: the size's unit.
    """

    kind: str
    min_size: float | None
    parameters: dict
    why: str
    answer: str
    unit: str = ""

    def to_json(self) -> dict:
        return {"min_size": self.min_size, "parameters": self.parameters, "why": self.why}


def _num(v):
    return None if v is None or (isinstance(v, float) and not math.isfinite(v)) else v


@dataclass(frozen=True)
class Diagnosis:
    """Evidence of a diagnosis (see :mod:`core.diagnosis.engine`), ready for diagnosis.json
    and the report."""

    session: Path
    config: DiagnosisConfig
    noise_sigma: float
    noise_floor: float
    youngs: dict
    baseline_test_error: float
    causes: list[CauseReport]
    candidates: list[CauseReport]
    confounded: list[list[str]]
    extended_kinds: list[str]
    extended_effects: list[dict]
    extended_test_error: float
    extended_gain: float
    gain_interval: tuple[float, float]
    summary: dict
    base_fields: dict
    extended_fields: dict
    layout: FieldLayout
    timings: dict
    simulations: int
    simulations_by_stage: dict = field(default_factory=dict)
    """{stage: simulations} in the stages of ``timings``."""
    simulations_repeated: int = 0
    """Simulations of runs made before and dropped by the runs cache (:data:`core.diagnosis.evidence.RUNS_CACHE_BYTES`)."""
    learned_correction: dict | None = None
    """:meth:`core.diagnosis.explain.CorrectionExplanation.to_json` of a trained network, when one was given."""
    force: dict | None = None
    """With force data: the force noise per axis (N), the base model's fitted E (Pa), and
    the RMS force error on test (N) of the base and the extended model with its gain."""
    force_note: str = ""
    """Whether the force was used, and why (not)."""
    detectability: dict | None = None
    """{kind: :class:`Detectability`} for every effect kind."""
    palpation: dict | None = None
    """How the sequences palpated (``core.diagnosis.summary.palpation``)."""
    nuisances: tuple = ()
    """The nuisance directions the base model carried (``core.diagnosis.nuisance``)."""
    notes: tuple = ()
    """What the diagnosis had to change from its configuration, and why (diagnosis.json ``notes``)."""
    model_form: dict | None = None
    """The last round's model-form worlds: {"drops": {variant: held-out chi2 drop}, "variant",
    "bar"} (:func:`core.diagnosis.model_form.model_form_drops`; "bar" the largest drop), when
    they were simulated (a kind of that round passed Holm's procedure and was held to them,
    :func:`core.diagnosis.model_form.beyond_model_form`); else None."""

    def answers(self) -> dict:
        """{kind: one of :data:`ANSWERS`} for every kind with a detectability statement."""
        return {k: d.answer for k, d in (self.detectability or {}).items()}

    def to_json(self) -> dict:
        """The diagnosis.json contract of SESSION_FORMAT.md (format tissue-diagnosis/1), plus extra keys."""
        cfg = self.config
        return {
            "format": "tissue-diagnosis/1",
            "session": str(self.session),
            "youngs_modulus": self.youngs,
            "baseline": {"test_error": self.baseline_test_error},
            "causes": [
                {"kind": c.kind, "parameters": c.parameters, "test_error": c.test_error, "gain": c.gain,
                 "confidence": c.confidence, "identifiable": c.identifiable,
                 **({"intervals": c.intervals} if c.intervals else {}),
                 "evidence": {"delta_chi2": c.delta_chi2, "p_value": c.p_value, "critical": c.critical,
                              "explained": c.explained, "round": c.round},
                 **({"force_test_rms": c.force_test_rms, "force_gain": c.force_gain} if c.force_gain is not None else {})}
                for c in self.causes
            ],
            "extended": {"kinds": self.extended_kinds, "test_error": self.extended_test_error, "gain": self.extended_gain,
                         "gain_interval": list(self.gain_interval), "effects": self.extended_effects,
                         **({"force_test_rms": self.force["extended_test_rms_N"], "force_gain": self.force["gain"]}
                            if self.force else {})},
            "unexplained": {"test_error": self.extended_test_error, "noise_floor": self.noise_floor,
                            "above_noise_floor": self.extended_test_error - self.noise_floor},
            "detectability": {k: d.to_json() for k, d in (self.detectability or {}).items()},
            "confounded": self.confounded,
            "answers": self.answers(),
            "candidates": [
                {"kind": c.kind, "round": c.round, "delta_chi2": c.delta_chi2, "delta_chi2_field": c.delta_chi2_field,
                 "delta_chi2_force": c.delta_chi2_force, "p_value": c.p_value, "critical": _num(c.critical),
                 "score": _num(c.score), "significant": c.significant, "channels": c.channels, "reproduction": c.reproduction, "model_form_bar": c.model_form_bar,
                 "model_form_nested": c.model_form_nested, "explained": c.explained,
                 "confidence": c.confidence, "claimed": c.claimed, "parameters": c.parameters,
                 "fit_variables": c.fit_variables}
                for c in self.candidates
            ],
            "residuals": self.summary,
            "noise": {"point_sigma_m": self.noise_sigma,
                      **({"force_sigma_N": self.force["noise_N"]} if self.force else {})},
            "force": {"note": self.force_note, **(self.force or {})},
            "palpation": self.palpation,
            "method": "signature fits (Levenberg-Marquardt on the binned signed surface residual"
                      + (" and the probe force" if self.force else "")
                      + ") beside the base model's nuisances (" + ", ".join(self.nuisances)
                      + "); a kind is claimed when its held-out chi-square drop passes Holm's procedure over "
                        "its null distribution from a wild block bootstrap of the session's own residuals and "
                        "its fit, added to each phantom at an end of the model-form range that explains part of "
                        "the residual (model_form), still explains its critical value there (model_form_nested)",
            "claims": {"false_claim_rate": cfg.alpha, "meaning": "per selection round, family-wise over the candidate "
                       "kinds: on a session without any effect, the chance that anything is claimed",
                       "null_replicates": cfg.n_null, "block_s": cfg.block},
            "simulations": self.simulations,
            "simulations_by_stage": self.simulations_by_stage,
            "simulations_repeated": self.simulations_repeated,
            "timings_s": self.timings,
            "notes": list(self.notes),
            **({"model_form": self.model_form} if self.model_form is not None else {}),
            **({"learned_correction": self.learned_correction} if self.learned_correction else {}),
        }
