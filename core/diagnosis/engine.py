"""Discovery: name what the base model lacks, extend it, and measure the gain.

Method (nested model comparison on the residual field of :mod:`core.diagnosis.fields`):

1. **Base.** The paper's model (corotational, no effects) is replayed on every
   sequence. The noise variance ``sigma^2`` of a point's signed top residual is the
   pooled scatter of points within a bin and frame; a bin mean of ``n`` points has
   variance ``sigma^2 / n`` under noise alone, so ``chi2 = sum n r^2 / sigma^2`` over
   bins and frames is about their number, ``N``, for a perfect model.
2. **Signatures and fits.** For each candidate kind (:mod:`core.diagnosis.candidates`)
   its parameters are fitted on the ``train`` sequences by Levenberg-Marquardt on the
   weighted residual field, with forward-difference signatures (the change of the
   field per unit parameter) as Jacobian; nonlinear kinds start from a small grid.
3. **Selection.** A candidate is judged on the ``validation`` sequences, which its fit
   never saw: ``delta_chi2`` is the drop of chi2 from the current model, per channel
   (the field; the force, when recorded). Its evidence is each channel's drop in units
   of that kind's threshold, calibrated on sessions that do not hold it (per top-face
   bin-frame for the field, per frame for the force; ``DiagnosisConfig``), summed; it is
   claimed when that exceeds 1 and ``delta_chi2`` is significant on its own; the best
   (largest ``delta_chi2``) is claimed, the others refitted on top of it (greedy forward
   selection, as orthogonal matching pursuit). When a rival's validation gain is within
   20 % of the best's and their changes correlate above 0.9, each is fitted on top of
   the other: one that adds significant evidence to the other while the other adds none
   to it is kept (a kinematic offset's lateral part, which a probe radius cannot mimic);
   when neither adds to the other they are reported as confounded and neither is
   claimed. Confidence is the bootstrap support of the claim (1 s blocks of validation
   frames resampled).
4. **Extension and gain.** The claimed causes are refitted jointly on train, then on the
   fine grid; the paper's error on the ``test`` sequences (and, with force data, the
   RMS force error) is compared with the base model's, with a frame-block bootstrap
   interval of the gain.

**Force data** (kinematics.csv ``fx, fy, fz``). The force residual, simulated minus
measured per frame and axis in units of the force noise measured on rest frames, joins
the field in the chi2. Force scales with Young's modulus, so E is fitted jointly with
every candidate and the base model's E is fitted first: the base model is the paper's
with E identified, and E is reported from the joint fit of the claimed causes. This is
what makes the effects visible that change the force more than the surface under a
displacement-controlled probe: a stiff inclusion under the palpated region, friction
with sliding pokes, a deeper probe. The force is read on the robot's clock, as the
kinematics are: a clock offset hypothesis reads it shifted with them.

**Without force data**, per-candidate fits hold E at the base value, since the field
hardly depends on it. Where an effect's signature scales with 1/E (gravity: sag ~
rho g H^2 / E; a foundation of stiffness k: its share of a dent ~ E / k), the fit
measures g / E or k / E; gravity is then fixed at its physical value and E fitted
(:func:`core.identification.fit_youngs_modulus`, which says when it cannot be
identified), and the foundation stiffness is reported with the E it assumed.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from dataclasses import field as dc_field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from core.diagnosis.candidates import KINDS, Candidate, candidates, top_presses
from core.diagnosis.fields import FACES, PHASES, FieldLayout, frame_bins, phase_labels, residual_field
from core.errors import TissueTwinError
from core.identification.execution import Executor, SerialExecutor
from core.identification.fit import fit_youngs_modulus
from core.identification.trials import Trial
from core.simulation import SimulationConfig
from core.simulation.replay import PreparedSession, build_replay_model, frame_errors
from core.simulation.solver import simulate

SCALE_FREE = frozenset({"inclusion", "viscoelasticity", "friction", "probe_radius", "time_offset", "kinematic_offset"})
"""Effect kinds that keep the model's displacements unchanged and scale its forces with E
(their stiffnesses are ratios of E, or they act on the probe's input). Gravity (a fixed
body force) and a foundation (a fixed stiffness in Pa/m) set a scale for E of their own."""
E_STEP = 0.02
"""Forward-difference step of log10 E in the joint fits where it is not semi-analytic."""
LM_DAMPING = (1e-3, 1e-1, 1.0)
"""Levenberg-Marquardt damping values (times the diagonal of J^T J) of each iteration's trial steps."""

__all__ = ["DiagnosisConfig", "FieldTrial", "FieldRun", "run_field", "Diagnosis", "CauseReport", "diagnose_prepared"]

Callback = Callable[[float, str], None]


@dataclass(frozen=True)
class DiagnosisConfig:
    """Settings of a diagnosis.

    Attributes:
        youngs_modulus: E of the base model, Pa (the paper's 5e3 unless the session pins it).
        poisson_ratio, grid, law: the replay model (the paper's 0.44, 13x5x5, corotational).
        fine_grid: the grid the base residual and the reported errors come from
            (multi-fidelity: signatures and fits run on ``grid``, their fields shifted by
            the discrepancy ``fine - coarse`` of the base model, sequence by sequence; an
            additive model-discrepancy correction, Kennedy & O'Hagan 2001). The coarse
            grid's dent is ~1 mm off a 25x9x9 one's, more than several causes' signal.
            None: everything on ``grid``.
        coarse_dt: time step (s) of the coarse-grid runs when ``fine_grid`` is set (None:
            the simulator's 1/120 s). They are a surrogate whose base field and force are
            shifted onto the fine grid's, which absorbs the step's error with the grid's.
            Measured on a 6 s session, 1/60 s against 1/120 s: fields within 0.002 mm
            (noise 0.77 mm), forces within 1-4 mN (noise 8 mN), signatures within 1-3 %
            (a clock offset's force signature within 6-25 %; the fine refit uses 1/120 s),
            at about half the cost.
        layout_bins: bins of the residual field along x and y.
        side_rows: bins along z on each side face (0: the top face only). Side faces
            carry what the top cannot: side pokes, where a probe's radius and lateral
            offsets show directly. Each face's noise is estimated on its own, and its
            bins weighted by it. Off by default: with 4 rows, a hidden gravity of 9.81
            was fitted at 7.63 m/s^2 (top only: 10.57) and a foundation and friction were
            claimed beside it; the 5-node-high coarse grid does not resolve the sides'
            bulge, and the multi-fidelity shift corrects the base field, not signatures.
        probe_exclusion: bins whose centre lies within this horizontal distance (m) of
            the measured probe centre are left out of fits and selection (0: none). The
            dent is where the coarse grid's discretisation error lives (a 5 mm sphere on
            6 x 10 mm elements); without ``fine_grid`` a 12 mm exclusion cut the spurious
            validation chi2 drop on a no-effect session from 2700 to 870; with it, the
            dent's own evidence (probe radius, offsets) is kept.
        min_delta_chi2: a claim must lower the validation chi2 by at least this much
            (significance; 25 is a 5-sigma drop for one parameter)...
        min_gain_per_bin: ...and by at least this much per top-face validation
            bin-frame (top bins only, so side bins do not dilute it), unless the kind has
            its own value in ``gain_per_bin`` (the floor: half the largest null of any
            kind on our lab's sessions).
        gain_per_bin: per-kind thresholds, calibrated on the null drops of each kind:
            its validation drop per top-face bin-frame on sessions that do not hold it.
            Two kinds of no-effect data were measured: our lab's `small` sessions (seed
            0, 6 s; a no-effect session and sessions hiding another, unrelated kind) and
            the shared sample session, written by an independent generator (coarser
            truth mesh, its own contact and integrator: the nearest thing to real-world
            model-form error we have). The sample's nulls are the larger:

            kind: our lab / sample -> threshold
              gravity 0.039 / 0.096-0.107 -> 0.16; inclusion < 0.003 / 0.0002-0.21 -> 0.31;
              viscoelasticity < 0.003 / 0.026-0.098 -> 0.15 (see below); friction < 0.003 / 0.027-0.062
              -> 0.09; base_compliance 0.020 / 0.080-0.187 -> 0.28; probe_radius 0.010 /
              0.14 -> 0.21; time_offset < 0.003 / 0.001 -> 0.02 (the floor);
              kinematic_offset < 0.003 / 0.194-0.207 -> 0.31.

            (ranges: runs of successive versions of the method.) Since the coarse runs
            step at 1/60 s, a Maxwell arm mimics the sample's gap more: its null there is
            0.098 with relaxation times from 0.05 s (0.133 when they could reach 0.01 s,
            below the time step), so its threshold is 0.15; the other kinds' sample nulls
            stayed below their thresholds (the largest: probe_radius at 0.89 of its own).
            Thresholds are 1.5x the largest null; a thin margin, since each null is measured on few sessions. On
            the sample, the large nulls share one residual: its dent is ~1.4 mm deeper
            than our replay's, which a vertical probe offset, a foundation, an inclusion
            or a bigger probe each mimic. Our penalty contact (1e7 Pa/m per unit area)
            lets the sphere sink ~0.5-1.5 mm into the mesh at these pressures; a generator
            with stiffer contact would show exactly this (a hypothesis, not measured).
        force_gain_per_frame, min_force_gain_per_frame: the force channel's claim
            thresholds, per kind and the default: its validation chi2 drop per validation
            frame (three axes). Measured on 6 s sessions with force (noise 8-9 mN per
            axis): on sessions without effects, every kind's drop was at most 0.25 per
            frame; after a true cause was claimed, the next round's candidates gained up to
            3.4 per frame from E moving with them (a rigid foundation after an inclusion).
            Hidden causes gained 3.5-52 per frame (a 1.5 mm probe offset, viscoelasticity,
            an inclusion under the palpated region, friction with sliding pokes).
        lm_iterations: most Levenberg-Marquardt iterations per candidate...
        lm_tolerance: ...which stop early once a step lowers the train chi2 by less than
            this (a fraction of one unit of chi2 cannot change a claim).
        fine_refit_iterations: Levenberg-Marquardt iterations of the final refit of the
            claimed causes on ``fine_grid`` (0: keep the coarse fits).
        max_causes: most causes claimed.
        fit_youngs: fit E with the claimed causes (otherwise keep ``youngs_modulus``).
        refine_mesh, n_boot: passed to the E fit.
        kinds: candidate kinds considered (all by default).
        seed: of the bootstraps.
        use_force: put the probe force residual (simulated minus measured, per frame and
            axis, in units of the force noise measured on rest frames) into the evidence
            beside the residual field, and fit Young's modulus jointly with every
            candidate (force scales with E, so an unfitted E would dominate it). None:
            when every sequence has force columns (kinematics.csv ``fx, fy, fz``).
    """

    youngs_modulus: float = 5000.0
    poisson_ratio: float = 0.44
    grid: tuple[int, int, int] = (13, 5, 5)
    law: str = "corotational"
    fine_grid: tuple[int, int, int] | None = (25, 9, 9)
    coarse_dt: float | None = 1.0 / 60.0
    layout_bins: tuple[int, int] = (16, 8)
    side_rows: int = 0
    probe_exclusion: float = 0.0
    min_delta_chi2: float = 25.0
    min_gain_per_bin: float = 0.02
    gain_per_bin: dict = dc_field(default_factory=lambda: {
        "gravity": 0.16, "inclusion": 0.31, "viscoelasticity": 0.15, "friction": 0.09, "base_compliance": 0.28,
        "probe_radius": 0.21, "time_offset": 0.02, "kinematic_offset": 0.31})
    force_gain_per_frame: dict = dc_field(default_factory=dict)
    min_force_gain_per_frame: float = 4.0
    lm_iterations: int = 4
    lm_tolerance: float = 1.0
    fine_refit_iterations: int = 2
    max_causes: int = 3
    fit_youngs: bool = True
    refine_mesh: bool = True
    n_boot: int = 200
    kinds: tuple[str, ...] = KINDS
    seed: int = 0
    use_force: bool | None = None


@dataclass(frozen=True)
class FieldTrial:
    """One replay for the diagnosis: a trial, the field layout, and whether to compute
    the paper's point-to-mesh error too (slower: a KD-tree per frame)."""

    trial: Trial
    layout: FieldLayout
    paper_error: bool = False


@dataclass(frozen=True)
class FieldRun:
    """Evidence of one :class:`FieldTrial`.

    Attributes:
        sequence: name. ok: the simulation did not diverge.
        field: (F, B) float64 mean signed normal residual per bin and frame, m.
        ss, dof: per face of ``fields.FACES``, within-bin sums of squares (5,) m^2 and
            their degrees of freedom (5,).
        frame_sums: (F,) sum of point-to-mesh distances per frame, m, or None.
        frame_counts: (F,) measured points per frame.
        probe_centres: (F, 3) probe sphere centres at frame times, m, phantom frame.
        force: (F, 3) simulated force of the probe on the phantom at frame times, N,
            phantom frame.
        youngs_modulus: E of the replay, Pa.
        clock_offset: the replay's ``time_offset`` effect, s (0 without one): the robot's
            clock, which stamps kinematics and force alike, runs this far ahead of the
            camera's, so the force measured at camera time t is the row at t + offset.
    """

    sequence: str
    ok: bool
    field: np.ndarray
    ss: np.ndarray
    dof: np.ndarray
    frame_sums: np.ndarray | None
    frame_counts: np.ndarray
    probe_centres: np.ndarray
    force: np.ndarray
    youngs_modulus: float
    clock_offset: float = 0.0


def run_field(prepared: PreparedSession, item: FieldTrial) -> FieldRun:
    """Replay ``item.trial`` (a fresh model) and measure its residual field (worker function)."""
    t = item.trial
    seq = prepared.sequences[t.sequence]
    model = build_replay_model(prepared, t.replay_config())
    sim = simulate(model, seq.probe, prepared.probe_radius, seq.frame_times)
    pts, bins, counts = frame_bins(seq.clouds, item.layout)
    fld, ss, dof = residual_field(sim.positions, t.grid, item.layout, pts, bins, counts)
    n = np.array([c.shape[0] for c in seq.clouds], dtype=np.int64)
    sums = None
    if item.paper_error:
        means, _ = frame_errors(sim.positions, t.grid, seq.clouds)
        sums = means * n  # NaN where the frame diverged
    offset = sum(float(e["offset"]) for e in t.effects if e["kind"] == "time_offset")
    return FieldRun(t.sequence, bool(sim.ok), fld, ss, dof, sums, n, np.asarray(sim.probe_centres),
                    np.asarray(sim.contact_force, dtype=np.float64), float(t.youngs_modulus), offset)


@dataclass
class _Fit:
    """A candidate's fit: its variables ``x`` with standard errors ``se`` (with a joint
    E, log10 E is the last of each), the train rss, the effect dict and the model's E (Pa)."""

    x: np.ndarray
    se: np.ndarray
    train_rss: float
    effect: dict | None
    youngs_modulus: float

    @property
    def effects(self) -> list[dict]:
        return [] if self.effect is None else [self.effect]


@dataclass(frozen=True)
class CauseReport:
    """One candidate's evidence in one selection round.

    Attributes:
        kind: effect kind. parameters: SESSION_FORMAT parameters at the fit.
        fit_variables: {name: (value, standard error, unit)} of the fit variables.
        identifiable: {name: bool}: the 95 % interval of a variable is narrower than
            half a decade (log variables) or than half its value (others).
        delta_chi2: drop of validation chi2 against the model of the round.
        explained: fraction of that model's validation chi2 it removes.
        confidence: bootstrap support of the claim, [0, 1].
        round: selection round (0 = against the base model).
        claimed: whether it was claimed.
        test_error, gain: paper error on test (m) with this cause alone, and its relative
            gain against the base (claimed causes only, else None).
        delta_chi2_field, delta_chi2_force: ``delta_chi2`` split by channel (force: None
            without force data). score: the evidence in units of the claim thresholds
            (a claim needs more than 1; see ``_score``).
        force_test_rms, force_gain: with force data, the RMS force error on test (N) with
            this cause alone (and its E), and its relative gain against the base model
            with its own fitted E (claimed causes only, else None).
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
    score: float | None = None


@dataclass(frozen=True)
class Diagnosis:
    """Evidence of a diagnosis (see module docstring), ready for diagnosis.json and the report."""

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
    learned_correction: dict | None = None
    """:meth:`core.diagnosis.explain.CorrectionExplanation.to_json` of a trained network, when one was given."""
    force: dict | None = None
    """With force data: the force noise per axis (N), the base model's fitted E (Pa), and
    the RMS force error on test (N) of the base and the extended model with its gain."""
    force_note: str = ""
    """Whether the force was used, and why (not)."""

    def to_json(self) -> dict:
        """The diagnosis.json contract of SESSION_FORMAT.md (format tissue-diagnosis/1), plus extra keys."""
        return {
            "format": "tissue-diagnosis/1",
            "session": str(self.session),
            "youngs_modulus": self.youngs,
            "baseline": {"test_error": self.baseline_test_error},
            "causes": [
                {"kind": c.kind, "parameters": c.parameters, "test_error": c.test_error, "gain": c.gain,
                 "confidence": c.confidence, "identifiable": c.identifiable,
                 "evidence": {"delta_chi2": c.delta_chi2, "explained": c.explained, "round": c.round},
                 **({"force_test_rms": c.force_test_rms, "force_gain": c.force_gain} if c.force_gain is not None else {})}
                for c in self.causes
            ],
            "extended": {"kinds": self.extended_kinds, "test_error": self.extended_test_error, "gain": self.extended_gain,
                         "gain_interval": list(self.gain_interval), "effects": self.extended_effects,
                         **({"force_test_rms": self.force["extended_test_rms_N"], "force_gain": self.force["gain"]}
                            if self.force else {})},
            "unexplained": {"test_error": self.extended_test_error, "noise_floor": self.noise_floor,
                            "above_noise_floor": self.extended_test_error - self.noise_floor},
            "confounded": self.confounded,
            "candidates": [
                {"kind": c.kind, "round": c.round, "delta_chi2": c.delta_chi2, "delta_chi2_field": c.delta_chi2_field,
                 "delta_chi2_force": c.delta_chi2_force, "score": c.score, "explained": c.explained,
                 "confidence": c.confidence, "claimed": c.claimed, "parameters": c.parameters,
                 "fit_variables": c.fit_variables}
                for c in self.candidates
            ],
            "residuals": self.summary,
            "noise": {"point_sigma_m": self.noise_sigma,
                      **({"force_sigma_N": self.force["noise_N"]} if self.force else {})},
            "force": {"note": self.force_note, **(self.force or {})},
            "method": "signature fits (Levenberg-Marquardt on the binned signed top residual"
                      + (" and the probe force, with E fitted jointly" if self.force else "")
                      + ") with greedy selection on validation chi2; thresholds calibrated on no-effect sessions",
            "thresholds": {"min_delta_chi2": self.config.min_delta_chi2,
                           "per_top_bin_frame": {k: _threshold(self.config, k) for k in self.config.kinds}},
            "simulations": self.simulations,
            "timings_s": self.timings,
            **({"learned_correction": self.learned_correction} if self.learned_correction else {}),
        }


@dataclass(frozen=True)
class _Spec:
    """A model of the diagnosis: effect dicts (SESSION_FORMAT.md) and Young's modulus (Pa)."""

    effects: tuple
    youngs_modulus: float


class _Engine:
    """Runs field trials through an executor and caches them by (effects, sequence, E);
    holds the weights of the evidence: bin counts per face noise, and with force data
    the measured force and its noise."""

    def __init__(self, prepared: PreparedSession, cfg: DiagnosisConfig, executor: Executor, layout: FieldLayout):
        self.prepared, self.cfg, self.executor, self.layout = prepared, cfg, executor, layout
        self.cache: dict = {}
        self.delta: dict[str, np.ndarray] = {}
        self.force_delta: dict[str, np.ndarray] = {}
        self.force_ratio: dict[str, float] = {}
        self.simulations = 0
        self.names = {role: [n for n, s in prepared.sequences.items() if s.role == role] for role in ("train", "validation", "test")}
        self.counts, self.raw_counts = {}, {}
        centres = layout.centres3()
        for n, s in prepared.sequences.items():
            counts = frame_bins(s.clouds, layout)[2]
            self.raw_counts[n] = counts
            if cfg.probe_exclusion > 0:
                c = s.probe.at(s.frame_times)
                near = np.linalg.norm(centres[None, :, :] - c[:, None, :], axis=2) < cfg.probe_exclusion
                counts = np.where(near, 0, counts)
            self.counts[n] = counts.astype(np.float64)
        self.force, self.force_sigma, self.force_note = _force_evidence(prepared, cfg.use_force)
        self.sigma2 = 1.0  # the top face's point noise variance, m^2 (set by weigh_faces)

    @property
    def use_force(self) -> bool:
        return self.force is not None

    def weigh_faces(self, face_sigma2: np.ndarray, sigma2: float) -> None:
        """Scale each bin's point count by ``sigma2 / face_sigma2`` of its face, so that
        ``n r^2 / sigma2`` is chi2 on every face (a face without noise estimate gets 0)."""
        face_of = self.layout.face_of_bin()
        ratio = np.where(face_sigma2 > 0, sigma2 / np.where(face_sigma2 > 0, face_sigma2, 1.0), 0.0)[face_of]
        for n in self.counts:
            self.counts[n] = self.counts[n] * ratio[None, :]
            self.raw_counts[n] = self.raw_counts[n] * ratio[None, :]
        self.sigma2 = float(sigma2)

    def spec(self, effects: Sequence[dict] = (), E: float | None = None) -> _Spec:
        return _Spec(tuple(effects), float(E or self.cfg.youngs_modulus))

    def trial(self, seq: str, spec: _Spec, grid) -> Trial:
        c = self.cfg
        coarse = c.fine_grid is not None and tuple(grid) != tuple(c.fine_grid)
        sim = SimulationConfig(dt=c.coarse_dt) if coarse and c.coarse_dt else SimulationConfig()
        return Trial(sequence=seq, youngs_modulus=spec.youngs_modulus, poisson_ratio=c.poisson_ratio,
                     grid=tuple(grid), law=c.law, effects=spec.effects, simulation=sim)

    @staticmethod
    def _key(spec: _Spec, seq, paper, grid):
        return (repr(tuple(sorted(repr(sorted(e.items())) for e in spec.effects))), seq, spec.youngs_modulus, paper, grid)

    def runs(self, models: Sequence[_Spec | Sequence[dict]], role: str, *, paper: bool = False,
             fine: bool = False) -> list[list[FieldRun]]:
        """Field runs of every model (a :class:`_Spec`, or effect dicts at the configured
        E) on every sequence of ``role`` (on the fine grid when ``fine`` and one is configured)."""
        names = self.names[role]
        grid = tuple(self.cfg.fine_grid) if fine and self.cfg.fine_grid else tuple(self.cfg.grid)
        specs = [m if isinstance(m, _Spec) else self.spec(m) for m in models]
        todo, keys = [], []
        for m in specs:
            for n in names:
                k = self._key(m, n, paper, grid)
                if k not in self.cache and k not in keys:
                    keys.append(k)
                    todo.append(FieldTrial(self.trial(n, m, grid), self.layout, paper))
        if todo:
            out = self.executor.map(run_field, self.prepared, todo)
            self.simulations += len(todo)
            self.cache.update(zip(keys, out))
        return [[self.cache[self._key(m, n, paper, grid)] for n in names] for m in specs]

    def discrepancy(self, role: str) -> None:
        """Store ``fine - coarse`` base fields (and forces) of the sequences of ``role``
        (see ``fine_grid``)."""
        if not self.cfg.fine_grid:
            return
        coarse, fine = self.runs([[]], role)[0], self.runs([[]], role, fine=True)[0]
        for c, f in zip(coarse, fine):
            if not (c.ok and f.ok):
                raise TissueTwinError(f"{self.prepared.path}: the base model diverged on {c.sequence}")
            self.delta[c.sequence] = f.field - c.field
            cc = float(np.sum(c.force**2))
            ratio = float(np.sum(f.force * c.force)) / cc if cc > 0 else 1.0
            self.force_ratio[c.sequence] = ratio
            self.force_delta[c.sequence] = f.force - ratio * c.force

    def field(self, r: FieldRun) -> np.ndarray:
        """(F, B) residual field of a coarse run, discrepancy-corrected."""
        d = self.delta.get(r.sequence)
        return r.field if d is None else r.field + d

    def _shifted_force(self, r: FieldRun, shifted: bool) -> np.ndarray:
        """(F, 3) force of a run, N; a coarse run's (``shifted``) mapped onto the fine grid:
        ``c f + (f_fine - c f_coarse)(E / E_base)``, with ``c`` the least-squares ratio of
        the base model's fine to coarse force on the sequence. The coarse grid locks
        (measured c = 0.57-0.93 per sequence), so every force it makes, the changes a
        candidate makes included (a friction force, a deeper dent), is too large by
        about 1 / c; the remainder is additive, and proportional to E, as the force is
        at a fixed dent."""
        if not shifted or r.sequence not in self.force_delta:
            return r.force
        E = r.youngs_modulus / self.cfg.youngs_modulus
        return self.force_ratio[r.sequence] * r.force + self.force_delta[r.sequence] * E

    def force_residual(self, r: FieldRun, shifted: bool = True) -> np.ndarray:
        """(F, 3) simulated minus measured force in units of the force noise (a coarse
        run's force mapped onto the fine grid's, see :meth:`_shifted_force`)."""
        return (self._shifted_force(r, shifted) - self.measured_force(r)) / self.force_sigma

    def measured_force(self, r: FieldRun) -> np.ndarray:
        """(F, 3) measured force at the run's frame times, N, read on the robot's clock as
        the run assumes it (see ``FieldRun.clock_offset``)."""
        if r.clock_offset == 0.0:
            return self.force[r.sequence]
        seq = self.prepared.sequences[r.sequence]
        return seq.force_at(seq.frame_times + r.clock_offset)

    def vector(self, runs: list[FieldRun], shifted: bool = True) -> np.ndarray:
        """Weighted residual vector over the runs (inf if diverged): sqrt(n) r over bins
        and frames, then, with force data, the force residual in noise units;
        ``shifted``: coarse runs, discrepancy-corrected (fine runs: False)."""
        parts = []
        for r in runs:
            w = np.sqrt(self.counts[r.sequence].astype(np.float64))
            v = (w * (self.field(r) if shifted else r.field)).ravel()
            if self.use_force:
                v = np.concatenate([v, np.sqrt(self.sigma2) * self.force_residual(r, shifted).ravel()])
            parts.append(v if r.ok else np.full(v.size, np.inf))
        return np.concatenate(parts)

    def frame_chi2(self, runs: list[FieldRun], shifted: bool = True) -> list[np.ndarray]:
        """(F, 2) chi2 per frame of each run (inf where diverged): column 0 the field's
        bins, column 1 the force's three axes (zero without force data)."""
        out = []
        for r in runs:
            c = np.zeros((r.field.shape[0], 2))
            if not r.ok:
                out.append(c + np.inf)
                continue
            fld = self.field(r) if shifted else r.field
            c[:, 0] = np.sum(self.counts[r.sequence] * fld**2, axis=1) / self.sigma2
            if self.use_force:
                c[:, 1] = np.sum(self.force_residual(r, shifted) ** 2, axis=1)
            out.append(c)
        return out

    def youngs_column(self, runs: list[FieldRun], shifted: bool = True) -> np.ndarray:
        """d vector / d log10 E of the runs if force is proportional to E and the field
        does not depend on it: zero on the bins, ln(10) times the (shifted) force in
        noise units (the vector's scale) on the force."""
        parts = []
        for r in runs:
            z = np.zeros(r.field.size)
            f = self._shifted_force(r, shifted)
            parts += [z, math.log(10.0) * np.sqrt(self.sigma2) * (f / self.force_sigma).ravel()]
        return np.concatenate(parts)

    def force_rms(self, runs: list[FieldRun], shifted: bool = False) -> float:
        """RMS norm of simulated minus measured force over the frames of ``runs``, N."""
        res = np.concatenate([self.force_residual(r, shifted) * self.force_sigma for r in runs])
        return float(np.sqrt(np.mean(np.sum(res**2, axis=1)))) if np.all(np.isfinite(res)) else math.nan


def _force_evidence(prepared: PreparedSession, use_force: bool | None):
    """Measured force at frame times per sequence, its noise per axis, and a note.

    The noise is the RMS of each axis over rest frames (probe clear of the phantom for a
    second), where the true force is zero, floored at 1 mN as the E fit's
    (``core.identification.fit._force_noise``).

    Returns:
        ({sequence: (F, 3) N} or None, (3,) N or None, note: why force is (not) used).

    Raises:
        TissueTwinError: ``use_force`` is True and a sequence has no force columns.
    """
    seqs = prepared.sequences
    missing = [n for n, s in seqs.items() if s.force is None]
    if use_force is False:
        return None, None, "not used (use_force=False)"
    if missing:
        if use_force:
            raise TissueTwinError(f"{prepared.path}: use_force needs force columns (fx, fy, fz) in every "
                                  f"kinematics.csv; {', '.join(missing)} has none")
        return None, None, "no force columns in kinematics.csv"
    force = {n: s.force_at(s.frame_times) for n, s in seqs.items()}
    rest = np.concatenate([force[n][prepared.rest_frames(n)] for n in seqs])
    if rest.shape[0] < 10:
        if use_force:
            raise TissueTwinError(f"{prepared.path}: cannot estimate the force noise: {rest.shape[0]} frames "
                                  "with the probe clear of the phantom (need 10)")
        return None, None, f"not used: {rest.shape[0]} rest frames to estimate the force noise (need 10)"
    sigma = np.maximum(np.sqrt(np.mean(rest**2, axis=0)), 1e-3)
    return force, sigma, f"used: noise {', '.join(f'{1e3 * v:.1f}' for v in sigma)} mN (x, y, z) from {rest.shape[0]} rest frames"



def _threshold(cfg: DiagnosisConfig, kind: str) -> float:
    """Per top-face validation bin-frame drop of chi2 a claim of ``kind`` needs."""
    return float(cfg.gain_per_bin.get(kind, cfg.min_gain_per_bin))


def _force_threshold(cfg: DiagnosisConfig, kind: str) -> float:
    """Per validation frame drop of the force's chi2 a claim of ``kind`` needs."""
    return float(cfg.force_gain_per_frame.get(kind, cfg.min_force_gain_per_frame))


def _score(cfg: DiagnosisConfig, kind: str, drop: np.ndarray, n_bins: float, n_frames: float) -> float:
    """Evidence for ``kind``: the validation chi2 drop of each channel, (field, force),
    in units of that channel's claim threshold (``n_frames`` = 0: no force channel).
    A claim needs a score above 1: one channel past its threshold, or both part way."""
    s = float(drop[0]) / (n_bins * _threshold(cfg, kind))
    if n_frames:
        s += float(drop[1]) / (n_frames * _force_threshold(cfg, kind))
    return s


def _rss(v: np.ndarray) -> float:
    return float(v @ v) if np.all(np.isfinite(v)) else math.inf


def _fit_candidate(eng: _Engine, cand: Candidate | None, fixed: list[dict], *, E: float | None = None,
                   fit_youngs: bool = False, start: np.ndarray | None = None, fine: bool = False,
                   iterations: int | None = None) -> _Fit:
    """Levenberg-Marquardt fit of one candidate's variables on train, the other effects
    ``fixed`` (on the coarse grid with the discrepancy shift, or on the fine grid when
    ``fine``), forward-difference Jacobian (the candidate's signature).

    Args:
        cand: the candidate; None fits E alone (``fit_youngs`` must be set).
        E: Young's modulus of the model (Pa; default the configured one); the start of
            log10 E when ``fit_youngs``.
        fit_youngs: fit log10 E jointly, as the last variable (force data: force scales
            with E, so a candidate fitted at a wrong E would explain E's error).
        start: a single starting vector (candidate's variables only) instead of ``cand.starts``.
    """
    sigma2 = eng.sigma2
    E0 = float(E or eng.cfg.youngs_modulus)
    nv = 0 if cand is None else len(cand.names)
    steps = np.zeros(0) if cand is None else cand.steps
    lo_E, hi_E = math.log10(E0) - 2.0, math.log10(E0) + 2.0

    def clip(x):
        head = x[:nv] if cand is None else cand.clip(x[:nv])
        return np.concatenate([head, np.clip(x[nv:], lo_E, hi_E)])

    def spec(x) -> _Spec:
        eff = [] if cand is None else [cand.to_effect(x[:nv])]
        return _Spec(tuple(fixed) + tuple(eff), float(10.0 ** x[nv]) if fit_youngs else E0)

    def runs(xs):
        return eng.runs([spec(x) for x in xs], "train", fine=fine)

    def vec(r):
        return eng.vector(r, shifted=not fine)

    tail = [math.log10(E0)] if fit_youngs else []
    kinds = {e["kind"] for e in fixed} | ({cand.kind} if cand is not None else set())
    semi_analytic = kinds <= SCALE_FREE
    heads = [start] if start is not None else ([np.zeros(0)] if cand is None else list(cand.starts))
    starts = [clip(np.concatenate([np.asarray(h, dtype=np.float64), tail])) for h in heads]
    runs0 = runs(starts)
    rss = [_rss(vec(r)) for r in runs0]
    i = int(np.argmin(rss))
    x, r_x = starts[i], vec(runs0[i])
    J = None
    for _ in range(eng.cfg.lm_iterations if iterations is None else iterations):
        if not np.all(np.isfinite(r_x)) or x.size == 0:
            break
        pts = []
        for j, h in enumerate(steps):
            xj = x.copy()
            xj[j] = x[j] + h if x[j] + h <= cand.upper[j] else x[j] - h
            pts.append(xj)
        if fit_youngs and semi_analytic:
            # the log10 E column is semi-analytic: with every stiffness proportional to E,
            # the force is proportional to E at a fixed dent and the field does not depend
            # on it (measured: the force grows 0.94-0.99x as fast as E over E x 1.1-1.7,
            # the rest is the penalty contact's fixed stiffness; trial steps are real runs)
            cols = runs(pts)
            J = np.stack([(vec(c) - r_x) / (s[j] - x[j]) for j, (c, s) in enumerate(zip(cols, pts))]
                         + [eng.youngs_column(runs([x])[0], shifted=not fine)], axis=1)
        else:
            if fit_youngs:
                xe = x.copy()
                xe[nv] = x[nv] + E_STEP
                pts.append(xe)
            cols = runs(pts)
            J = np.stack([(vec(c) - r_x) / (s[j] - x[j]) for j, (c, s) in enumerate(zip(cols, pts))], axis=1)
        if not np.all(np.isfinite(J)):
            J = None
            break
        A, g = J.T @ J, J.T @ r_x
        D = np.diag(np.maximum(np.diag(A), 1e-30))
        previous = _rss(r_x)
        steps_lm = []
        for lam in LM_DAMPING:
            try:
                steps_lm.append(clip(x + np.linalg.solve(A + lam * D, -g)))
            except np.linalg.LinAlgError:
                continue
        accepted = None
        if fine:
            # on the fine grid a replay costs ~20 coarse ones: the damping values are tried
            # in turn and the first step that lowers the misfit is taken (Levenberg-
            # Marquardt as in Nocedal & Wright Sec. 10.3), from the coarse optimum
            for x_try in steps_lm:
                r_try = vec(runs([x_try])[0])
                if _rss(r_try) < previous:
                    accepted = (x_try, r_try)
                    break
        elif steps_lm:
            # on the coarse grid all of them are replayed and the best is taken: fewer
            # iterations for a nonlinear fit far from its start (an inclusion)
            out = runs(steps_lm)
            vals = [_rss(vec(o)) for o in out]
            k = int(np.argmin(vals))
            if vals[k] < previous:
                accepted = (steps_lm[k], vec(out[k]))
        if accepted is None:
            break
        x, r_x = accepted
        if previous - _rss(r_x) < eng.cfg.lm_tolerance * sigma2:
            break  # converged: the last step gained less than lm_tolerance in chi2
    se = np.full(x.size, np.inf)
    if J is not None:
        try:
            cov = sigma2 * np.linalg.inv(J.T @ J)
            se = np.sqrt(np.maximum(np.diag(cov), 0.0))
        except np.linalg.LinAlgError:
            pass
    sp = spec(x)
    return _Fit(x, se, _rss(r_x), None if cand is None else cand.to_effect(x[:nv]), sp.youngs_modulus)


def _fit_fields(cand: Candidate, fit: _Fit) -> dict:
    """The :class:`CauseReport` fields that come from a fit of ``cand`` (with a joint
    E, its log10 is the fit's last variable and is reported as ``log10_youngs_modulus``)."""
    nv = len(cand.names)
    names, units = cand.names + ("log10_youngs_modulus",), cand.units + ("Pa",)
    return {"parameters": cand.to_parameters(fit.x[:nv]),
            "fit_variables": {n: (float(v), float(s), u) for n, v, s, u in zip(names, fit.x, fit.se, units)},
            "identifiable": _identifiable(names, fit.x, fit.se)}


def _identifiable(names: Sequence[str], x: np.ndarray, se: np.ndarray) -> dict:
    """{name: bool}: the 95 % interval is narrower than half a decade (log10 variables)
    or than half the value (others)."""
    out = {}
    for name, v, s in zip(names, x, se):
        if name.startswith("log10_"):
            out[name[6:]] = bool(1.96 * s < 0.5)
        else:
            out[name] = bool(1.96 * s < 0.5 * max(abs(v), 1e-12))
    return out


def _blocks(prepared: PreparedSession, names: list[str], block: float = 1.0) -> list[np.ndarray]:
    out = []
    for n in names:
        t = prepared.sequences[n].frame_times
        out.append(np.floor((t - t[0]) / block).astype(int))
    return out


def _support(base_f, cand_f, dof_f, blocks, cfg: DiagnosisConfig, kind: str, use_force: bool, n_boot: int, rng) -> float:
    """Bootstrap support: fraction of block resamples of validation frames (1 s blocks)
    where the claim passes (``base_f``, ``cand_f``: (F, 2) chi2 per frame and channel)."""
    hits = 0
    for _ in range(n_boot):
        d = np.zeros(2)
        e = nfr = 0.0
        for b0, bc, nf, bl in zip(base_f, cand_f, dof_f, blocks):
            nb = bl.max() + 1
            w = np.bincount(rng.integers(0, nb, nb), minlength=nb)[bl]
            d += w @ (b0 - bc)
            e += float(w @ nf)
            nfr += float(w.sum())
        hits += d.sum() > cfg.min_delta_chi2 and _score(cfg, kind, d, e, nfr if use_force else 0.0) > 1.0
    return hits / n_boot


def _test_error(runs: list[FieldRun]) -> tuple[float, list[np.ndarray], list[np.ndarray]]:
    sums = [r.frame_sums for r in runs]
    counts = [r.frame_counts for r in runs]
    if not all(r.ok for r in runs):
        return math.nan, sums, counts
    return float(sum(np.nansum(s) for s in sums) / sum(c.sum() for c in counts)), sums, counts


def _gain_interval(base, ext, blocks, n_boot: int, rng) -> tuple[float, float]:
    (bs, bc), (es, _) = base, ext
    vals = []
    for _ in range(n_boot):
        tb = te = tc = 0.0
        for s0, s1, c, bl in zip(bs, es, bc, blocks):
            nb = bl.max() + 1
            w = np.bincount(rng.integers(0, nb, nb), minlength=nb)[bl]
            tb += float(w @ np.nan_to_num(s0))
            te += float(w @ np.nan_to_num(s1))
            tc += float(w @ c)
        vals.append(1.0 - te / tb if tb > 0 else 0.0)
    return tuple(float(v) for v in np.percentile(vals, [2.5, 97.5]))


def _summary(eng: _Engine, runs: list[FieldRun], sigma2: float, prepared: PreparedSession) -> dict:
    """Where and when the base model is wrong: systematic residual variance (m^2 beyond
    noise) by phase, by distance from the probe and by region of the top face."""
    centres = eng.layout.centres3()
    face_of = eng.layout.face_of_bin()
    by_face = {f: [0.0, 0.0, 0] for f in eng.layout.faces()}
    by_phase = {p: [0.0, 0.0, 0] for p in PHASES}
    by_dist = {"near (<10 mm)": [0.0, 0.0, 0], "mid (10-25 mm)": [0.0, 0.0, 0], "far (>25 mm)": [0.0, 0.0, 0]}
    mean_map = np.zeros(eng.layout.n_bins)
    sq_map = np.zeros(eng.layout.n_bins)
    cnt_map = np.zeros(eng.layout.n_bins)
    for r in runs:
        n = eng.raw_counts[r.sequence].astype(np.float64)
        fld = eng.field(r)
        seq = prepared.sequences[r.sequence]
        ph = phase_labels(seq.frame_times, r.probe_centres, prepared.size, prepared.probe_radius)
        has = n > 0
        excess = np.where(has, fld**2 - sigma2 / np.where(has, n, 1.0), 0.0)  # n: noise-weighted counts
        for k, p in enumerate(PHASES):
            m = (ph == k)[:, None] & has
            by_phase[p][0] += float(excess[m].sum())
            by_phase[p][1] += float((fld[m] ** 2).sum())
            by_phase[p][2] += int(m.sum())
        for k, f in enumerate(eng.layout.faces()):
            m = (face_of == FACES.index(f))[None, :] & has
            by_face[f][0] += float(excess[m].sum())
            by_face[f][1] += float((fld[m] ** 2).sum())
            by_face[f][2] += int(m.sum())
        d = np.linalg.norm(centres[None, :, :] - r.probe_centres[:, None, :], axis=2)
        for key, (lo, hi) in zip(by_dist, ((0, 0.010), (0.010, 0.025), (0.025, np.inf))):
            m = (d >= lo) & (d < hi) & has
            by_dist[key][0] += float(excess[m].sum())
            by_dist[key][1] += float((fld[m] ** 2).sum())
            by_dist[key][2] += int(m.sum())
        mean_map += np.where(has, fld, 0.0).sum(axis=0)
        sq_map += np.where(has, excess, 0.0).sum(axis=0)
        cnt_map += has.sum(axis=0)

    def table(d):
        return {k: {"systematic_rms_m": math.sqrt(max(v[0], 0.0) / v[2]) if v[2] else None,
                    "total_rms_m": math.sqrt(v[1] / v[2]) if v[2] else None, "bin_frames": v[2]} for k, v in d.items()}

    total_sys = sum(v[0] for v in by_phase.values())
    total = sum(v[1] for v in by_phase.values())
    return {
        "by_phase": table(by_phase),
        "by_distance_from_probe": table(by_dist),
        "by_face": table(by_face),
        "systematic_fraction_of_variance": max(total_sys, 0.0) / total if total else 0.0,
        "mean_map_m": (mean_map / np.maximum(cnt_map, 1))[: eng.layout.top_bins].reshape(eng.layout.bins).tolist(),
        "systematic_rms_map_m": np.sqrt(np.maximum(sq_map / np.maximum(cnt_map, 1), 0.0))[: eng.layout.top_bins].reshape(eng.layout.bins).tolist(),
    }


def diagnose_prepared(
    prepared: PreparedSession,
    config: DiagnosisConfig | None = None,
    *,
    executor: Executor | None = None,
    callback: Callback | None = None,
) -> Diagnosis:
    """Diagnose a prepared session (see the module docstring for the method).

    Args:
        prepared: calibrated session with cleaned clouds (``prepare_session``); needs
            train, validation and test sequences.
        config: settings (defaults: the paper's base model, calibrated thresholds).
        executor: where the replays run (default: this process); use
            :func:`core.identification.executor` for Dask, as sweeps do.
        callback: ``callback(fraction, message)`` for progress.

    Returns:
        A :class:`Diagnosis`.

    Raises:
        TissueTwinError: a role without sequences, or a base model that diverges.
    """
    cfg = config or DiagnosisConfig()
    executor = executor or SerialExecutor()
    t0 = time.perf_counter()
    say = callback or (lambda f, m: None)
    layout = FieldLayout(tuple(float(v) for v in prepared.size), cfg.layout_bins, side_rows=cfg.side_rows)
    eng = _Engine(prepared, cfg, executor, layout)
    for role, names in eng.names.items():
        if not names:
            raise TissueTwinError(f"{prepared.path}: the diagnosis needs a '{role}' sequence (session.json roles)")
    presses = [p for n in eng.names["train"] for p in
               top_presses(prepared.sequences[n].probe.at(prepared.sequences[n].frame_times), prepared.size, prepared.probe_radius)]
    presses = [p for i, p in enumerate(presses) if all(np.linalg.norm(p - q) >= 0.005 for q in presses[:i])]
    cands = {k: v for k, v in candidates(prepared.size, prepared.probe_radius, np.array(presses)).items() if k in cfg.kinds}
    rng = np.random.default_rng(cfg.seed)
    joint = eng.use_force  # fit E with every candidate
    timings: dict[str, float] = {}
    clock = [time.perf_counter()]

    def lap(name: str) -> None:
        now = time.perf_counter()
        timings[name] = timings.get(name, 0.0) + now - clock[0]
        clock[0] = now

    say(0.02, "replaying the base model")
    for role in ("train", "validation"):
        eng.discrepancy(role)
    base = {role: eng.runs([[]], role)[0] for role in ("train", "validation")}
    all_base = base["train"] + base["validation"]
    if not all(r.ok for r in all_base):
        raise TissueTwinError(f"{prepared.path}: the base model diverged at E = {cfg.youngs_modulus:g} Pa")
    noise_runs = (eng.runs([[]], "train", fine=True)[0] + eng.runs([[]], "validation", fine=True)[0]) if cfg.fine_grid else all_base
    ss = np.sum([r.ss for r in noise_runs], axis=0)
    dof = np.sum([r.dof for r in noise_runs], axis=0)
    face_sigma2 = np.where(dof > 0, ss / np.maximum(dof, 1), 0.0)
    sigma2 = float(face_sigma2[0]) if dof[0] > 0 else float(ss.sum() / max(dof.sum(), 1))
    eng.weigh_faces(face_sigma2, sigma2)
    val_names = eng.names["validation"]
    top = eng.layout.top_bins
    val_nf = [(eng.counts[n][:, :top] > 0).sum(axis=1).astype(np.float64) for n in val_names]  # top bin-frames
    val_blocks = _blocks(prepared, val_names)

    # the base model's E: with force data it is fitted (the base model is the paper's
    # with E identified); without, the field hardly depends on it and it stays as given
    E_base = cfg.youngs_modulus
    base_fit = None
    if joint:
        say(0.04, "fitting Young's modulus of the base model to the force")
        base_fit = _fit_candidate(eng, None, [], E=E_base, fit_youngs=True)
        E_base = base_fit.youngs_modulus
    E_cur, e_fit = E_base, base_fit  # the current E and the joint fit it came from
    lap("base")

    fixed: list[dict] = []
    claimed: list[tuple[Candidate, _Fit, CauseReport]] = []
    reports: list[CauseReport] = []
    confounded: list[list[str]] = []
    active = list(cands)
    n_val = sum(n.sum() for n in val_nf)
    n_frames = float(sum(n.size for n in val_nf)) if joint else 0.0  # validation frames of the force channel

    def drop(before, after) -> np.ndarray:
        """(field, force) chi2 drop over validation sequences."""
        return sum((a - b).sum(axis=0) for a, b in zip(before, after))

    for rnd in range(cfg.max_causes):
        if joint and rnd > 0:
            # the round's reference model at its own optimum in E: otherwise any candidate,
            # even one fitted to nothing, gains by moving E further (measured: a foundation
            # of 8e7 Pa/m, a rigid base, claimed after an inclusion for its E alone)
            e_fit = _fit_candidate(eng, None, fixed, E=E_cur, fit_youngs=True)
            E_cur = e_fit.youngs_modulus
        cur_val = eng.runs([eng.spec(fixed, E_cur)], "validation")[0]
        cur_f = eng.frame_chi2(cur_val)
        chi_cur = sum(f.sum() for f in cur_f)
        fits, evid = {}, {}
        for i, kind in enumerate(active):
            say(0.05 + 0.6 * (rnd + i / len(active)) / cfg.max_causes, f"round {rnd}: fitting {kind}")
            fit = _fit_candidate(eng, cands[kind], fixed, E=E_cur, fit_youngs=joint)
            val = eng.runs([eng.spec(fixed + fit.effects, fit.youngs_modulus)], "validation")[0]
            f_k = eng.frame_chi2(val)
            dd = drop(cur_f, f_k)
            d = float(dd.sum())
            fits[kind] = fit
            evid[kind] = (d, d / chi_cur if chi_cur > 0 else 0.0, f_k, val, dd, _score(cfg, kind, dd, n_val, n_frames))
        passing = [k for k in active if evid[k][0] > cfg.min_delta_chi2 and evid[k][5] > 1.0]
        round_reports = {}
        for k in active:
            d, phi, f_k, _, dd, score = evid[k]
            conf = _support(cur_f, f_k, val_nf, val_blocks, cfg, k, joint, cfg.n_boot, rng) if k in passing else 0.0
            c = cands[k]
            round_reports[k] = CauseReport(kind=k, **_fit_fields(c, fits[k]), delta_chi2=d, explained=float(phi),
                                           confidence=float(conf), round=rnd, delta_chi2_field=float(dd[0]),
                                           delta_chi2_force=float(dd[1]) if joint else None, score=score)
        lap(f"round {rnd}")
        if not passing:
            reports += list(round_reports.values())
            break
        passing.sort(key=lambda k: -evid[k][0])
        best = passing[0]
        # confounding: a rival explains nearly as much with a field change like the best's
        def change(k):
            parts = [(a.field - b.field).ravel() for a, b in zip(cur_val, evid[k][3])]
            if joint:
                parts += [(eng.force_residual(a) - eng.force_residual(b)).ravel() for a, b in zip(cur_val, evid[k][3])]
            return np.concatenate(parts)

        ref = change(best)
        rivals = []
        for k in passing[1:]:
            if evid[k][0] < 0.8 * evid[best][0]:
                continue
            other = change(k)
            cos = float(ref @ other / (np.linalg.norm(ref) * np.linalg.norm(other) + 1e-30))
            if cos > 0.9:
                rivals.append(k)
        if rivals:
            # nested comparison: does either add significant validation evidence on top of
            # the other? The one that explains what the other cannot is kept.
            def extra(kind: str, given: str) -> np.ndarray:
                g = fits[given]
                f = _fit_candidate(eng, cands[kind], fixed + g.effects, E=g.youngs_modulus, fit_youngs=joint)
                val = eng.runs([eng.spec(fixed + g.effects + f.effects, f.youngs_modulus)], "validation")[0]
                return drop(evid[given][2], eng.frame_chi2(val))

            def significant(d: np.ndarray, kind: str) -> bool:
                return d.sum() > cfg.min_delta_chi2 and _score(cfg, kind, d, n_val, n_frames) > 0.3

            survivors = [best]
            for k in rivals:
                best_over_k, k_over_best = extra(best, k), extra(k, best)
                if significant(k_over_best, k) and not significant(best_over_k, best):
                    survivors = [k]  # the rival explains what the best cannot
                elif not significant(best_over_k, best) and not significant(k_over_best, k):
                    survivors.append(k)  # neither adds to the other: confounded
            if len(survivors) > 1:
                # the largest residual has two explanations: claim neither, and stop, since
                # the other candidates would be fitted against a residual it dominates
                # (measured: a foundation claimed after kinematic offset / probe radius tied)
                confounded.append(survivors)
                reports += list(round_reports.values())
                break
            best = survivors[0]
        round_reports[best] = replace(round_reports[best], claimed=True)
        reports += list(round_reports.values())
        claimed.append((cands[best], fits[best], round_reports[best]))
        fixed = fixed + fits[best].effects
        E_cur, e_fit = fits[best].youngs_modulus, fits[best]
        active = [k for k in active if k != best and evid[k][5] > 0.3]
        if not active:
            break

    nv = {c.kind: len(c.names) for c, _, _ in claimed}
    # joint refit of the claimed causes (each refitted with the others fixed)
    if len(claimed) > 1:
        say(0.7, "refitting the claimed causes jointly")
        for i, (c, f, rep) in enumerate(list(claimed)):
            others = [e for j, (_, g, _) in enumerate(claimed) if j != i for e in g.effects]
            g = _fit_candidate(eng, c, others, E=E_cur, fit_youngs=joint, start=f.x[: nv[c.kind]])
            E_cur, e_fit = g.youngs_modulus, g
            claimed[i] = (c, g, replace(rep, **_fit_fields(c, g)))
    # final refit on the fine grid: the coarse signatures of local causes (a dent's
    # shift, a clock offset) are blurred by 6 x 10 mm elements, and the discrepancy
    # shift corrects the base field, not the derivatives (measured: a 0.15 s offset
    # fitted at 0.074 s, a lateral probe offset at about half, gravity 8 % high)
    if claimed and cfg.fine_grid and cfg.fine_refit_iterations > 0:
        say(0.72, "refitting the claimed causes on the fine grid")
        for i, (c, f, rep) in enumerate(list(claimed)):
            others = [e for j, (_, g, _) in enumerate(claimed) if j != i for e in g.effects]
            g = _fit_candidate(eng, c, others, E=E_cur, fit_youngs=joint, start=f.x[: nv[c.kind]], fine=True,
                               iterations=cfg.fine_refit_iterations)
            E_cur, e_fit = g.youngs_modulus, g
            claimed[i] = (c, g, replace(rep, **_fit_fields(c, g)))
    ext_effects = [e for _, f, _ in claimed for e in f.effects]
    lap("refits")

    E_ext = E_cur
    if joint:
        # E is fitted with the claimed causes; its interval comes from the fit that set it
        youngs = _joint_youngs(e_fit)
    else:
        # Young's modulus with the claimed causes (gravity at its physical value)
        say(0.75, "fitting Young's modulus with the claimed causes")
        fit_effects = [({"kind": "gravity", "g": [0.0, 0.0, -9.81]} if e["kind"] == "gravity" else e) for e in ext_effects]
        youngs = {"value": None, "interval": None, "identifiable": False, "reason": "not fitted"}
        if cfg.fit_youngs:
            fit = fit_youngs_modulus(
                prepared, base=Trial(sequence="", youngs_modulus=1.0, poisson_ratio=cfg.poisson_ratio, grid=cfg.grid, law=cfg.law,
                                     effects=tuple(fit_effects)),
                executor=executor, refine_mesh=cfg.refine_mesh, n_boot=cfg.n_boot, seed=cfg.seed)
            eng.simulations += fit.evaluations
            youngs = fit.to_json()["youngs_modulus"]
            if fit.identifiable:
                E_ext = fit.coarse_value
                ext_effects = fit_effects
    youngs["replay_grid_value_used"] = E_ext
    lap("youngs")

    # test errors: base, each cause alone, extended
    say(0.9, "measuring the gain on the test sequences")
    test_blocks = _blocks(prepared, eng.names["test"])
    base_spec = eng.spec([], E_base)
    base_test = eng.runs([base_spec], "test", paper=True, fine=True)[0]
    b_err, b_s, b_c = _test_error(base_test)
    ext_runs = eng.runs([eng.spec(ext_effects, E_ext)], "test", paper=True, fine=True)[0]
    e_err, e_s, _ = _test_error(ext_runs)
    gain = 1.0 - e_err / b_err if b_err > 0 else 0.0
    gain_iv = _gain_interval((b_s, b_c), (e_s, b_c), test_blocks, cfg.n_boot, rng) if claimed else (0.0, 0.0)
    force = None
    if joint:
        fb, fe = eng.force_rms(base_test), eng.force_rms(ext_runs)
        force = {"noise_N": eng.force_sigma.tolist(), "base_youngs_modulus": E_base,
                 "baseline_test_rms_N": fb, "extended_test_rms_N": fe, "gain": 1.0 - fe / fb if fb > 0 else 0.0}
    causes = []
    for c, f, rep in claimed:
        runs_c = eng.runs([eng.spec(f.effects, f.youngs_modulus)], "test", paper=True, fine=True)[0]
        err, _, _ = _test_error(runs_c)
        extra = {}
        if joint:
            fc = eng.force_rms(runs_c)
            extra = {"force_test_rms": fc, "force_gain": 1.0 - fc / force["baseline_test_rms_N"]}
        causes.append(replace(rep, test_error=err, gain=1.0 - err / b_err if b_err > 0 else 0.0, **extra))
    causes.sort(key=lambda c: -(c.gain or 0.0) - (c.force_gain or 0.0))
    reports = [next((c for c in causes if c.kind == r.kind and r.claimed), r) for r in reports]

    ext_spec = eng.spec(ext_effects, E_ext) if claimed else base_spec
    ext_train = eng.runs([ext_spec], "train", fine=True)[0]
    ext_val = eng.runs([ext_spec], "validation", fine=True)[0]
    lap("test")
    timings["total"] = time.perf_counter() - t0
    say(1.0, "done")
    return Diagnosis(
        session=prepared.path, config=cfg, noise_sigma=math.sqrt(sigma2),
        noise_floor=float(prepared.noise_floor(cfg.fine_grid or cfg.grid)), youngs=youngs, baseline_test_error=b_err,
        causes=causes, candidates=reports, confounded=confounded,
        extended_kinds=[c.kind for c in causes], extended_effects=ext_effects,
        extended_test_error=e_err, extended_gain=gain, gain_interval=gain_iv,
        summary=dict(_summary(eng, all_base, sigma2, prepared), validation_bin_frames=int(sum(n.sum() for n in val_nf)),
                     noise_by_face_m={f: math.sqrt(face_sigma2[FACES.index(f)]) for f in layout.faces()}),
        base_fields={r.sequence: r for r in eng.runs([base_spec], "train", fine=True)[0] + eng.runs([base_spec], "validation", fine=True)[0] + base_test},
        extended_fields={r.sequence: r for r in ext_train + ext_val + ext_runs},
        layout=layout, timings=timings, simulations=eng.simulations,
        force=force, force_note=eng.force_note,
    )


def _joint_youngs(fit: _Fit) -> dict:
    """The youngs_modulus entry of diagnosis.json from a joint fit (log10 E last):
    value, 95 % interval from the Levenberg-Marquardt covariance, identifiable when the
    interval spans less than half a decade."""
    lg, se = float(fit.x[-1]), float(fit.se[-1])
    ok = bool(np.isfinite(se) and 1.96 * se < 0.5)
    return {"value": fit.youngs_modulus, "interval": [10.0 ** (lg - 1.96 * se), 10.0 ** (lg + 1.96 * se)] if np.isfinite(se) else None,
            "identifiable": ok, "method": "fitted jointly with the claimed causes to the force and the residual field",
            "reason": "force data set the scale of E" if ok else "the joint fit's interval spans half a decade or more"}
