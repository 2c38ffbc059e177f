"""The experiment that would tell: a palpation protocol that makes undetectable or
confounded effect kinds decidable on this phantom.

Method (optimal experimental design on the diagnosis's own signatures, in the spirit of a
D-/A-optimal design on the Fisher information of each kind's size; Pukelsheim 2006):

1. **Candidate moves** within the limits (:class:`PlanLimits`; :mod:`core.diagnosis.moves`):
   on the box, presses into the top at a grid of points, slides across the top along x
   and along y, presses into the middle of each side face; on any other shape, presses at
   the seen surface's patches reachable from above and slides along the surface. Every
   move starts and ends at a safe height above the phantom, presses along the surface's
   inward normal no deeper than ``max_depth``, keeps its contact points inside the
   margins and moves no faster than ``speed`` in contact.
2. **Expected evidence of each move** for each kind: the move is replayed with the base
   model of the diagnosis and with the kind at its reference size (its
   :meth:`~core.simulation.effects.Effect.assumptions`); the change of the weighted
   residual, with the base model's nuisance directions projected out
   (:mod:`core.diagnosis.nuisance`), gives the non-centrality ``q`` per unit strength
   squared: a kind of strength ``s`` is expected to add ``s^2 q`` to the held-out chi-square.
   The surface is seen as the session's camera saw it (its bins, at its mean point
   counts); the force with the session's force noise, or 10 mN when it recorded none.
3. **Choice**: for each target kind the move with the largest ``q`` (the smallest size it
   would show), then moves for the rest while the time budget lasts; moves are
   independent, so their ``q`` add up. The predicted ``min_size`` of every kind is the
   strength whose ``s^2 q`` reaches the critical value of a 1-parameter held-out test at
   ``alpha`` over the number of kinds (chi-square with one degree of freedom).
4. **Held to the model-form gap**, as the diagnosis states its sizes: on the chosen path,
   each kind's change of the data is simulated in every model-form world (the base model
   with the neo-Hookean law, Poisson's ratio 0.38 or 0.485, damping 0.05 or 0.3 s, a
   softer or stiffer contact) and the test fits it along the replay's signature; the
   least ``q`` of the replay and the worlds gives the prediction (:func:`_world_q`), as a
   claim must still explain its critical value in each world that explains part of the
   residual (:func:`core.diagnosis.model_form.beyond_model_form`). What the plan cannot
   predict is the model-form gap of the data it will record: the prediction is the
   noise's and the worlds' floor, and the diagnosis of the recorded session states the
   size that holds.

The plan's path is written in the robot frame (the session's calibration), as a
``kinematics.csv`` of the session format that a dVRK script can replay, with a
plain-language description; the virtual lab can record it (``generate_session(paths=...)``).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from core.diagnosis.config import DiagnosisConfig
from core.diagnosis.evidence import Evidence, Spec
from core.diagnosis.moves import Move, PlanError, PlanLimits, candidate_moves, move_path, surface_moves, within_duration
from core.diagnosis.patches import field_layout
from core.diagnosis.model_form import mesh_world, model_form_worlds
from core.diagnosis.nuisance import nuisance_columns
from core.errors import TissueTwinError
from core.identification.execution import Executor, SerialExecutor
from core.simulation.effects import EFFECT_KINDS, PhantomContext
from core.preparation.probe import ProbePath
from core.preparation import PreparedSequence, PreparedSession

__all__ = ["PlanLimits", "PlanError", "Move", "Plan", "candidate_moves", "plan_inputs", "plan_experiment", "write_plan",
           "NOMINAL_FORCE_NOISE", "surface_moves"]

NOMINAL_FORCE_NOISE = 0.01
"""Force noise per axis assumed for a session that recorded no force, N (a dVRK force estimate)."""

Callback = Callable[[float, str], None]


@dataclass(frozen=True)
class Plan:
    """A palpation protocol that would make the target kinds decidable.

    Attributes:
        moves: the chosen moves, in order. path_t: (K,) s. path_phantom: (K, 3) sphere
            centres, m, phantom frame. path_robot: (K, 3) the same in the robot frame.
        quaternion: (4,) tool orientation written to kinematics.csv (x, y, z, w).
        targets: the kinds the plan was made for, and why.
        predicted: {kind: predicted min_size of the session recorded with this plan (m,
            s, ... in the kind's size unit), or None: still cannot tell}.
        current: {kind: the diagnosed session's min_size}.
        record_force: whether the plan asks for force to be recorded.
        limits: the limits the plan keeps.
        description: plain-language lines.
        predicted_world: {kind: the model-form world whose phantom set its predicted
            size} where a world, not the replay's own physics, set it.
    """

    moves: tuple
    path_t: np.ndarray
    path_phantom: np.ndarray
    path_robot: np.ndarray
    quaternion: np.ndarray
    targets: dict
    predicted: dict
    current: dict
    record_force: bool
    limits: PlanLimits
    description: tuple = field(default_factory=tuple)
    predicted_world: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        return {
            "format": "tissue-plan/1",
            "targets": self.targets,
            "moves": [{"name": m.name, "description": m.description, "face": m.face, "duration_s": m.duration}
                      for m in self.moves],
            "description": list(self.description),
            "record_force": self.record_force,
            "predicted_min_size": self.predicted,
            "predicted_model_form_world": self.predicted_world,
            "current_min_size": self.current,
            "limits": {k: getattr(self.limits, k) for k in self.limits.__dataclass_fields__},
            "path_phantom": {"t": self.path_t.tolist(), "centres": self.path_phantom.tolist()},
            "duration_s": float(self.path_t[-1]),
        }


def _virtual_session(prepared: PreparedSession, path: ProbePath, rate: float, layout) -> PreparedSession:
    """A session whose sequences follow ``path`` and whose "clouds" are one point at every
    bin centre (the signatures are differences of models; counts are set by the caller)."""
    t = np.arange(0.0, float(path.t[-1]) + 1e-9, 1.0 / rate)
    pts = layout.centres3() - 1e-5 * layout.normals3()  # just inside, so the binning finds each face
    clouds = tuple(pts for _ in t)
    zeros = np.zeros((path.t.size, 3))
    seqs = {f"plan-{role}": PreparedSequence(f"plan-{role}", role, t, path, clouds, force=zeros)
            for role in ("train", "validation", "test")}
    return replace(prepared, sequences=seqs)


def _mean_counts(ev: Evidence) -> np.ndarray:
    """(B,) the session's mean points per bin over the frames that saw it (noise-weighted)."""
    tot = np.zeros(ev.layout.n_bins)
    seen = np.zeros(ev.layout.n_bins)
    for n in ev.names["train"] + ev.names["validation"]:
        c = ev.raw_counts[n]
        tot += c.sum(axis=0)
        seen += (c > 0).sum(axis=0)
    return np.where(seen > 0, tot / np.maximum(seen, 1), 0.0)


def _critical(alpha: float, n_kinds: int) -> float:
    from scipy.stats import chi2

    return float(chi2.isf(alpha / max(n_kinds, 1), 1))


def plan_inputs(diagnosis, config: DiagnosisConfig | None = None) -> tuple[dict, list[dict], float]:
    """What :func:`plan_experiment` takes from a diagnosis: every kind's detectability
    (with its answer), the claimed causes, and the E they were fitted with on the replay
    grid.

    Args:
        diagnosis: a ``core.diagnosis.Diagnosis`` or its ``diagnosis.json`` dict.
        config: where the default E comes from when the diagnosis reports none.

    Returns:
        (detectability {kind: Detectability or its JSON with "answer"}, claimed effect
        dicts, E in Pa).

    Raises:
        PlanError: a dict without a ``detectability`` object.
    """
    E0 = (config or DiagnosisConfig()).youngs_modulus
    if isinstance(diagnosis, dict):
        det = diagnosis.get("detectability")
        if not isinstance(det, dict):
            raise PlanError("the diagnosis has no detectability object")
        answers = diagnosis.get("answers") or {}
        detect = {k: {**d, "answer": answers.get(k, d.get("answer"))} for k, d in det.items()}
        fixed = list((diagnosis.get("extended") or {}).get("effects") or [])
        return detect, fixed, float((diagnosis.get("youngs_modulus") or {}).get("replay_grid_value_used") or E0)
    return diagnosis.detectability, list(diagnosis.extended_effects), float(diagnosis.youngs.get("replay_grid_value_used") or E0)


def plan_experiment(
    prepared: PreparedSession,
    detectability: dict,
    config: DiagnosisConfig | None = None,
    *,
    fixed: Sequence[dict] = (),
    youngs_modulus: float | None = None,
    kinds: Sequence[str] | None = None,
    limits: PlanLimits | None = None,
    executor: Executor | None = None,
    callback: Callback | None = None,
) -> Plan:
    """The palpation that would make the undetectable or confounded kinds decidable.

    Args:
        prepared: the diagnosed session (calibration, noise, camera coverage).
        detectability: {kind: Detectability or its JSON} of the session's diagnosis.
        config: the diagnosis's settings (alpha, nuisances, grid).
        fixed: the causes the diagnosis claimed (effect dicts). youngs_modulus: its E, Pa.
        kinds: the kinds to make decidable (default: every kind that could not be told,
            was confounded, or would need more than its reference size to show).
        limits: what the plan may ask of the robot.
        executor: where the replays run.
        callback: ``callback(fraction, message)``.

    Returns:
        A :class:`Plan`.

    Raises:
        PlanError: no move fits the phantom within the limits (depth, margins, duration).
    """
    cfg = config or DiagnosisConfig()
    lim = limits or PlanLimits(camera_rate=_camera_rate(prepared))
    say = callback or (lambda f, m: None)
    executor = executor or SerialExecutor()
    E = float(youngs_modulus or cfg.youngs_modulus)

    def entry(k):
        d = detectability.get(k)
        if d is None:
            return None, None
        return (d.min_size, getattr(d, "answer", None)) if hasattr(d, "min_size") else (d.get("min_size"), d.get("answer"))

    all_kinds = [k for k in cfg.kinds if k in EFFECT_KINDS]
    if kinds is None:
        targets = {}
        for k in all_kinds:
            size, answer = entry(k)
            cls = EFFECT_KINDS[k]
            if size is None:
                targets[k] = "cannot tell from this data"
            elif answer == "confounded":
                targets[k] = "confounded with another kind"
            elif size > cls.reference_size:
                targets[k] = f"shows only above {size:.3g} {cls.size_unit}"
    else:
        unknown = [k for k in kinds if k not in EFFECT_KINDS]
        if unknown:
            raise TissueTwinError(f"unknown effect kind(s) {unknown}; expected some of {sorted(EFFECT_KINDS)}")
        targets = {k: "asked for" for k in kinds}
    size = np.asarray(prepared.size, dtype=np.float64)
    radius = float(prepared.probe_radius)
    shape = prepared.shape
    session_cfg = replace(cfg, fine_grid=None)
    layout = field_layout(prepared, cfg)
    if shape.is_box:
        moves = candidate_moves(size, radius, lim)
    else:  # presses at the seen surface's patches
        moves = surface_moves(shape, radius, (layout.centres3(), layout.normals3()), lim)
    moves = within_duration(moves, lim)

    # the session's camera coverage and noise
    ev0 = Evidence(prepared, session_cfg, executor, layout)
    base_runs = ev0.runs([[]], "train")[0] + ev0.runs([[]], "validation")[0]
    ss = np.sum([r.ss for r in base_runs], axis=0)
    dof = np.sum([r.dof for r in base_runs], axis=0)
    face_sigma2 = np.where(dof > 0, ss / np.maximum(dof, 1), 0.0)
    sigma2 = float(face_sigma2[0]) if dof[0] > 0 else float(ss.sum() / max(dof.sum(), 1))
    ev0.weigh_faces(face_sigma2, sigma2)
    counts = _mean_counts(ev0)
    force_sigma = ev0.force_sigma if ev0.use_force else np.full(3, NOMINAL_FORCE_NOISE)
    record_force = not ev0.use_force
    if shape.is_box:
        ctx = PhantomContext(size, radius, np.array([[m.knots_p[2][0], m.knots_p[2][1]] for m in moves if m.face == "+z"]))
    else:  # under each press: its contact point (approach minus the radius and clearance along the normal)
        presses = [m for m in moves if m.name.startswith("press-")]
        normals = np.array([(m.knots_p[1] - m.knots_p[2]) / np.linalg.norm(m.knots_p[1] - m.knots_p[2]) for m in presses])
        points = np.array([m.knots_p[2] - normals[i] * (radius - lim.max_depth) for i, m in enumerate(presses)])
        ctx = PhantomContext(size, radius, points.reshape(-1, 3), normals.reshape(-1, 3), shape)
    crit = _critical(cfg.alpha, len(all_kinds))

    def evidence_for(move_list, fine=False):
        """The virtual session of ``move_list`` with the session's coverage and noise; with
        ``fine``, the fine grid is kept for the fine-mesh world (:func:`_world_q`; the coarse
        runs step at the simulator's own dt as without it, and nothing is shifted)."""
        t, c = move_path(move_list, size, radius, lim)
        path = ProbePath(t, c)
        virt = _virtual_session(prepared, path, lim.camera_rate, layout)
        vcfg = replace(cfg, coarse_dt=None) if fine else session_cfg
        ev = Evidence(virt, replace(vcfg, use_force=False), executor, layout)
        for n in ev.counts:
            ev.counts[n] = np.where(ev.counts[n] > 0, counts[None, :], 0.0)
            ev.raw_counts[n] = ev.counts[n]
        ev.sigma2 = sigma2
        ev.force = {n: np.zeros((virt.sequences[n].frame_times.size, 3)) for n in virt.sequences}
        ev.force_sigma = np.asarray(force_sigma, dtype=np.float64)
        return ev

    def q_of(ev, kind_list, worlds=False):
        """{kind: (q per unit strength^2, assumption, the model-form world that set q or "")}
        on the virtual sequence; with ``worlds``, q is held to the model-form worlds
        (:func:`_world_q`) at the chosen assumption."""
        N, _ = nuisance_columns(ev, "validation", list(fixed), E, cfg.nuisances)
        v0 = ev.vector(ev.runs([Spec(tuple(fixed), E)], "validation")[0])

        def project(X):
            return X - N @ np.linalg.lstsq(N, X, rcond=None)[0] if N.shape[1] else X

        out = {}
        for k in kind_list:
            cls = EFFECT_KINDS[k]
            best = None
            for a in cls.assumptions(ctx):
                eff = cls.sized(cls.reference_size, ctx, **a).to_dict()
                v = ev.vector(ev.runs([Spec(tuple(fixed) + (eff,), E)], "validation")[0])
                st = cls.strength(cls.reference_size)
                if not np.all(np.isfinite(v)) or st == 0:
                    continue
                D = project((v - v0) / st)
                q = float(D @ D) / sigma2
                pick = (best is None or (q > best[0] if cls.assume == "most_detectable" else q < best[0]))
                if pick:
                    best = (q, a, eff, D, st)
            if best is None:
                out[k] = (0.0, {}, "")
                continue
            q, a, eff, D, st = best
            world = ""
            if worlds and q > 0:
                q, world = _world_q(ev, tuple(fixed), E, eff, D, st, project, sigma2, q)
            out[k] = (q, a, world)
        return out

    # expected evidence of every move for every target kind
    per_move = {}
    for i, mv in enumerate(moves):
        say(0.05 + 0.6 * i / len(moves), f"expected evidence of {mv.name}")
        per_move[mv.name] = q_of(evidence_for([mv]), list(targets) or all_kinds[:1])
    chosen: list[Move] = []
    for k in targets:
        ranked = sorted(moves, key=lambda m: -per_move[m.name][k][0])
        if ranked and per_move[ranked[0].name][k][0] > 0 and ranked[0] not in chosen:
            chosen.append(ranked[0])
    total = sum(m.duration for m in chosen)
    while total > lim.duration and len(chosen) > 1:
        total -= chosen.pop().duration
    if not chosen:
        chosen = [moves[0]]
    say(0.7, "predicting what the plan would show, in every model-form world")
    ev = evidence_for(chosen, fine=True)
    q_all = q_of(ev, all_kinds, worlds=True)
    predicted, current, set_by = {}, {}, {}
    for k in all_kinds:
        cls = EFFECT_KINDS[k]
        q = q_all[k][0]
        s = math.sqrt(crit / q) if q > 0 else math.inf
        size_k = cls.size_at(s) if math.isfinite(s) else math.inf
        predicted[k] = None if not math.isfinite(size_k) or size_k > cls.max_size else float(size_k)
        current[k] = entry(k)[0]
        if q_all[k][2]:
            set_by[k] = q_all[k][2]
    t, c = move_path(chosen, size, radius, lim)
    T = np.asarray(prepared.calibration.T_phantom_robot, dtype=np.float64)
    Tinv = np.linalg.inv(T)
    robot = c @ Tinv[:3, :3].T + Tinv[:3, 3]
    from scipy.spatial.transform import Rotation

    q_tool = Rotation.from_matrix(Tinv[:3, :3]).as_quat()
    lines = [f"{i + 1}. {m.description}" for i, m in enumerate(chosen)]
    if record_force:
        lines.append("record the probe force (fx, fy, fz in kinematics.csv): without it a press cannot tell a "
                     "stiffer spot, friction or a larger probe from the gel's own stiffness")
    lines.append("repeat the whole path at least three times (train, validation and test sequences)")
    say(1.0, "done")
    return Plan(tuple(chosen), t, c, robot, q_tool, targets, predicted, current, record_force, lim, tuple(lines),
                predicted_world=set_by)


def _world_q(ev: Evidence, fixed: tuple, E: float, effect: dict, D: np.ndarray, strength: float,
             project: Callable[[np.ndarray], np.ndarray], sigma2: float, q: float) -> tuple[float, str]:
    """(q, the world that set it or ""): the expected evidence per unit strength squared of
    ``effect`` when the phantom is any model-form world, not only the replay's physics.

    As the diagnosis states a kind's size (:func:`core.diagnosis.sizing.world_min_size`),
    the kind's change of the data is simulated in each model-form world ``W``
    (:func:`core.diagnosis.model_form.model_form_worlds`, and the fine mesh,
    :func:`core.diagnosis.model_form.mesh_world`, when ``ev`` keeps a fine grid) as
    ``X_W = run(W + effect) - run(W)``,
    per unit strength, with the nuisance directions projected out; the test fits the kind
    along its replay signature ``D`` (nuisances projected out too), which explains
    ``(X_W . D)^2 / |D|^2`` of it. The least of that and the replay's own ``q`` is kept.

    Args:
        ev: the plan's virtual evidence (validation role). fixed, E: the diagnosed model.
        effect: the kind at its reference size. D: (L,) its projected replay signature per
            unit strength. strength: the effect's strength. project: removes the nuisance
            directions. sigma2: the field's noise variance. q: the replay's own q.
    """
    worlds = model_form_worlds(ev)
    changes = []  # (world, its change of the data per unit strength)
    if worlds:
        specs = [Spec(fixed, E, **f) for _, f in worlds] + [Spec(fixed + (effect,), E, **f) for _, f in worlds]
        vec = [ev.vector(r) for r in ev.runs(specs, "validation")]
        changes += [(name, (vec[len(worlds) + i] - vec[i]) / strength) for i, (name, _) in enumerate(worlds)]
    mesh = mesh_world(ev)
    if mesh is not None:
        name, f = mesh
        base, with_effect = (ev.vector(r, shifted=False)
                             for r in ev.runs([Spec(fixed, E, **f), Spec(fixed + (effect,), E, **f)], "validation", fine=True))
        changes.append((name, (with_effect - base) / strength))
    dd = float(D @ D)
    best, label = q, ""
    for name, X in changes:
        if not (np.all(np.isfinite(X)) and dd > 0):
            continue
        q_w = float(project(X) @ D) ** 2 / dd / sigma2
        if q_w < best:
            best, label = q_w, name
    return best, label


def _camera_rate(prepared: PreparedSession) -> float:
    rates = [1.0 / float(np.median(np.diff(s.frame_times))) for s in prepared.sequences.values() if s.frame_times.size > 2]
    return float(np.median(rates)) if rates else 15.0


def write_plan(plan: Plan, out: str | Path) -> Path:
    """Write ``kinematics.csv`` (the session format, robot frame), ``plan.json`` and ``plan.md``.

    Raises:
        OSError: the folder cannot be written.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rows = ["t,x,y,z,qx,qy,qz,qw"]
    qx, qy, qz, qw = (float(v) for v in plan.quaternion)
    for t, p in zip(plan.path_t, plan.path_robot):
        rows.append(f"{t:.4f},{p[0]:.7f},{p[1]:.7f},{p[2]:.7f},{qx:.7f},{qy:.7f},{qz:.7f},{qw:.7f}")
    (out / "kinematics.csv").write_text("\n".join(rows) + "\n")
    (out / "plan.json").write_text(json.dumps(plan.to_json(), indent=2))
    lines = ["# Palpation plan", "", "Made for: " + "; ".join(f"{k} ({why})" for k, why in plan.targets.items()) if plan.targets
             else "Made for: nothing was undecidable; a general protocol.", "", "## What to do", ""]
    lines += list(plan.description)
    lines += ["", f"Probe path: {plan.path_t[-1]:.1f} s, `kinematics.csv` (robot frame, the session's calibration), "
              f"at most {plan.limits.max_depth * 1e3:.0f} mm deep and {plan.limits.speed * 1e3:.0f} mm/s in contact.", "",
              "## What it would show", "", "| kind | smallest size now | predicted with this plan |", "|---|---|---|"]
    for k in plan.predicted:
        unit = EFFECT_KINDS[k].size_unit
        now = plan.current.get(k)
        pred = plan.predicted[k]
        world = plan.predicted_world.get(k)
        lines.append(f"| {k} | {'cannot tell' if now is None else f'{now:.3g} {unit}'} | "
                     f"{'cannot tell' if pred is None else f'{pred:.3g} {unit}'}"
                     f"{f' (for a phantom with {world})' if world else ''} |")
    lines += ["", "Predicted sizes hold in the replay's physics and in every model-form world (another law, "
              "Poisson's ratio, damping or contact within the plausible range, or the finer mesh); the diagnosis of the recorded "
              "session also asks a claim to beat the model-form gap its data show, so it may state more."]
    (out / "plan.md").write_text("\n".join(lines) + "\n")
    return out
