"""Discovery: name what the base model lacks, extend it, and measure the gain.

Method (nested model comparison on held-out data, with the model-form gap as a nuisance):

1. **Base model with nuisances.** The paper's model (corotational, no effects) is
   replayed on every sequence; with force data its Young's modulus is fitted to the force
   first. The noise variance of a point's signed normal residual is the pooled scatter
   of points within a bin and frame (:mod:`core.diagnosis.fields`). Every real session
   also differs from the replay by a model-form gap that no effect kind describes; the
   base model carries it as nuisance directions (E, a finer mesh, another material law,
   Poisson's ratio, damping, contact stiffness: :mod:`core.diagnosis.nuisance`) whose
   coefficients are fitted on train and carried over to validation.
2. **Candidate fits.** Each effect kind's parameters (:meth:`core.simulation.effects.Effect.fit_space`)
   are fitted on the ``train`` sequences by Levenberg-Marquardt on the weighted residual
   (field and force) beside the nuisances (:mod:`core.diagnosis.fitting`).
3. **Claims with a stated false-claim rate.** A candidate's evidence is the drop of the
   validation chi-square it brings, judged against its null distribution from a wild
   block bootstrap of the session's own residuals, with Holm's procedure across the
   kinds of a round at the family-wise rate ``alpha`` (:mod:`core.diagnosis.inference`).
   Two checks guard against the model-form gap, which the bootstrap treats as noise
   but which repeats in every block: the change the fit itself makes must be worth the
   critical value (``S = |change|^2 / sigma^2 >= critical``: an effect of the fitted size
   would be claimed; a drop far above ``S`` means validation asks for several times what
   train fitted, a residual of the kind's shape that does not reproduce), and no channel
   of the held-out data (top face, side faces, force) may get significantly worse
   (:func:`core.diagnosis.claims.claim_check`). Measured on randomised field-lab
   sessions (before the rule): the spurious claims' fitted changes were worth 0.13-0.78
   of their critical values (six of seven; a friction claim on one no-effect session,
   3.4 times, is kept), the true gravity and compliant-base claims' 1.30 and 1.46 times.
   A third check runs in the model-form worlds (the base model at the ends of its
   plausible range, one property at a time or all at once: damping, Poisson's ratio,
   contact, law; :func:`core.diagnosis.model_form.model_form_drops`), which the linear,
   bounded nuisance directions can miss: added to each world that explains part of the
   residual, the fitted cause must still explain its critical value of the held-out data
   (the nested test, :func:`core.diagnosis.model_form.beyond_model_form`). A residual one of
   them explains leaves it nothing there; a residual of another shape does not go away.
   The significant kind with the largest drop is claimed and the others are refitted on
   top of it (greedy forward selection), unless a rival explains as much or a larger,
   unconfirmed explanation shadows it; then the kinds are reported as confounded and
   neither is claimed (:func:`core.diagnosis.selection.choose`).
4. **Detectability.** For every kind, the smallest size these data would have claimed
   (its signature simulated and scaled; the session's own noise replicates): "not found
   above this size", or "cannot tell" when even a large effect would not show
   (:func:`detectability`).
5. **Extension and gain.** The claimed causes are refitted jointly on train, then on the
   fine grid; the paper's error on the ``test`` sequences (and, with force data, the RMS
   force error) is compared with the base model's, with a frame-block bootstrap interval.

The force is read on the robot's clock, as the kinematics are: a clock-offset hypothesis
reads it shifted with them. Without force data the field hardly depends on E; where an
effect's signature scales with 1/E (gravity: sag ~ rho g H^2 / E), the fit measures g / E,
and E is then fitted with gravity at its physical value
(:func:`core.identification.fit_youngs_modulus`, which says when it cannot be identified).
"""

from __future__ import annotations

import gc
import math
import time
from dataclasses import replace
from typing import Callable

import numpy as np

from core.diagnosis.candidates import phantom_context
from core.diagnosis.config import DiagnosisConfig
from core.diagnosis.detectability import (detectability, held_by_inversion, undersized_claims, unobservable,
                                         with_dependents, withdraw)
from core.diagnosis.evidence import Evidence, Request
from core.diagnosis.fields import NOISE_GROUPS
from core.diagnosis.fitting import Fit, fit_candidate
from core.diagnosis.inference import holm, holm_adjusted
from core.diagnosis.patches import field_layout
from core.diagnosis.results import CauseReport, Detectability, Diagnosis
from core.diagnosis.rounds import CandidateEvidence, Round, assess_all, beyond_verdict, channel_masks, model_form_json
from core.diagnosis.selection import choose
from core.diagnosis.summary import fit_fields, gain_interval, palpation, summary, test_error, unconfirmed_on_test
from core.diagnosis.trials import drop_binned_points
from core.diagnosis.worlds import absence_within, with_intervals
from core.diagnosis.youngs import unexcluded_effects, with_untold_kinds, youngs_of_extended
from core.errors import TissueTwinError
from core.identification.execution import Executor, SerialExecutor
from core.simulation.effects import EFFECT_KINDS, FitSpace
from core.preparation import PreparedSession
from core.preparation.segments import informative_session
from core.simulation.replay import noise_floor
__all__ = ["DiagnosisConfig", "CauseReport", "Detectability", "Diagnosis", "diagnose_prepared", "detectability"]

Callback = Callable[[float, str], None]


def _floor_mesh(prepared: PreparedSession, cfg: DiagnosisConfig, ev: Evidence):
    """The mesh of the reported noise floor: None for a box (the grid's), the fine mesh
    of any phantom."""
    if prepared.stl_path is None:
        return None
    from core.simulation.replay import replay_mesh

    return replay_mesh(prepared, cfg.grid, ev.fine_element_size if cfg.fine_grid else cfg.element_size)


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
        config: settings (defaults: the paper's base model, alpha 0.01).
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
    if cfg.segments:
        prepared = informative_session(prepared, int(cfg.segments))
    say = callback or (lambda f, m: None)
    layout = field_layout(prepared, cfg)
    ev = Evidence(prepared, cfg, executor, layout)
    for role, names in ev.names.items():
        if not names:
            raise TissueTwinError(f"{prepared.path}: the diagnosis needs a '{role}' sequence (session.json roles)")

    seen = ev.names["train"] + ev.names["validation"]
    ctx_fit = phantom_context(prepared, ev.names["train"])
    ctx_all = phantom_context(prepared, seen)
    cands = {k: EFFECT_KINDS[k].fit_space(ctx_fit) for k in cfg.kinds}
    rng = np.random.default_rng(cfg.seed)
    joint = ev.use_force
    timings: dict[str, float] = {}
    stage_sims: dict[str, int] = {}
    clock = [time.perf_counter(), ev.simulations]

    def lap(name: str) -> None:
        now = time.perf_counter()
        timings[name] = timings.get(name, 0.0) + now - clock[0]
        stage_sims[name] = stage_sims.get(name, 0) + ev.simulations - clock[1]
        clock[0], clock[1] = now, ev.simulations

    say(0.02, "replaying the base model")
    notes: list[str] = []
    failed = ev.discrepancy(("train", "validation"))
    if failed:
        # the finer mesh can fail where the replay's own does not (a deep press inverting
        # its small elements under the probe): carry on with the replay's mesh alone, and
        # say so, rather than give no answer
        notes.append(f"the fine-mesh reference diverged on {', '.join(failed)}: the diagnosis ran without it "
                     "(no mesh nuisance, no fine-mesh discrepancy, noise from the replay's own mesh)")
        cfg = ev.drop_fine_reference()
    base = {role: ev.runs([[]], role)[0] for role in ("train", "validation")}
    all_base = base["train"] + base["validation"]
    if not all(r.ok for r in all_base):
        raise TissueTwinError(f"{prepared.path}: the base model diverged at E = {cfg.youngs_modulus:g} Pa")
    notes += inversion_notes(all_base, cfg.law)
    noise_runs = (ev.runs([[]], "train", fine=True)[0] + ev.runs([[]], "validation", fine=True)[0]) if cfg.fine_grid else all_base
    ss = np.sum([r.ss for r in noise_runs], axis=0)
    dof = np.sum([r.dof for r in noise_runs], axis=0)
    face_sigma2 = np.where(dof > 0, ss / np.maximum(dof, 1), 0.0)
    sigma2 = float(face_sigma2[0]) if dof[0] > 0 else float(ss.sum() / max(dof.sum(), 1))
    ev.weigh_faces(face_sigma2, sigma2)
    channels_v = channel_masks(ev, "validation")
    palp = palpation(prepared, seen)

    E_base = cfg.youngs_modulus
    base_fit = None
    if joint:
        say(0.04, "fitting Young's modulus of the base model to the force")
        base_fit = fit_candidate(ev, None, [], E=E_base, fit_youngs=True)
        E_base = base_fit.youngs_modulus
    E_cur, e_fit = E_base, base_fit
    lap("base")

    fixed: list[dict] = []
    claimed: list[tuple[FitSpace, Fit, CauseReport]] = []
    reports: list[CauseReport] = []
    confounded: list[list[str]] = []
    # kinds these presses cannot show at any size (friction without slides): not fitted
    blind = unobservable(cfg.kinds, palpation(prepared, ev.names["train"]), palpation(prepared, ev.names["validation"]))
    refused: dict[str, str] = dict(blind)  # kinds significant but refused by channel_worsening, or blind: why
    small: dict[str, str] = {}  # kinds significant whose fitted change is below a claim: why
    active = [k for k in cands if k not in blind]
    last: Round | None = None
    last_evidence: dict[str, CandidateEvidence] = {}
    last_fits: dict[str, Fit] = {}
    for rnd_i in range(cfg.max_causes + 1):
        if joint and rnd_i > 0:
            # the round's reference model at its own optimum in E: otherwise any candidate
            # gains by moving E further
            e_fit = fit_candidate(ev, None, fixed, E=E_cur, fit_youngs=True)
            E_cur = e_fit.youngs_modulus
        say(0.05 + 0.6 * rnd_i / (cfg.max_causes + 1), f"round {rnd_i}: the model's nuisances and null")
        rnd = Round.build(ev, fixed, E_cur, cfg, cfg.seed + rnd_i)
        last, last_evidence = rnd, {}
        if rnd_i == cfg.max_causes or not active:
            break
        # a later round starts each kind from its fit of the round before (the model
        # gained a cause; the kind's optimum moves, its basin rarely does)
        evid = assess_all(
            ev, {k: cands[k] for k in active}, rnd, cfg, len(active), channels_v,
            starts={k: f.x[: len(cands[k].names)] for k, f in last_fits.items()},
            progress=lambda i, kind: say(0.05 + 0.6 * (rnd_i + (i + 1) / (len(active) + 1)) / (cfg.max_causes + 1),
                                         f"round {rnd_i}: fitting {kind}"))
        last_fits.update({k: e.fit for k, e in evid.items()})
        last_evidence = evid
        pvals = {k: e.p_value for k, e in evid.items()}
        # a kind is claimed when Holm's procedure rejects its absence and it passes
        # rounds.beyond_verdict (its fitted change reproduces, no channel made worse, and it
        # still explains held-out data in each model-form world that explains part of it)
        significant, nested = set(), {}
        rejected = set(holm(pvals, cfg.alpha))
        for k in rejected:
            verdict, nested[k] = beyond_verdict(rnd, ev, evid[k], cands[k])
            refused.pop(k, None)
            small.pop(k, None)
            if verdict is None:
                significant.add(k)
            elif verdict[0] == "not_reproduced":
                small[k] = verdict[1]
            else:
                refused[k] = verdict[1]
        adjusted = holm_adjusted(pvals)
        round_reports = {}
        for k in active:
            e = evid[k]
            round_reports[k] = CauseReport(
                kind=k, **fit_fields(cands[k], e.fit), delta_chi2=e.statistic,
                explained=float(e.statistic / rnd.chi2) if rnd.chi2 > 0 else 0.0,
                confidence=float(1.0 - adjusted[k]), round=rnd_i, delta_chi2_field=e.by_channel[0],
                delta_chi2_force=e.by_channel[1], p_value=e.p_value, critical=e.critical,
                score=float(e.statistic / e.critical) if e.critical > 0 and math.isfinite(e.critical) else None,
                significant=k in significant, channels=e.channels,
                reproduction=e.reproduction,
                model_form_bar=rnd.model_form(ev)[1] if rnd._model_form is not None else None,
                model_form_nested=nested.get(k))
        lap(f"round {rnd_i}")
        if not significant:
            reports += list(round_reports.values())
            break

        def change(k):
            parts = [(a.field - b.field).ravel() for a, b in zip(rnd.validation, evid[k].validation)]
            if joint:
                parts += [(ev.force_residual(a) - ev.force_residual(b)).ravel() for a, b in zip(rnd.validation, evid[k].validation)]
            return np.concatenate(parts)

        def adds(kind: str, given: str) -> bool:
            g = evid[given].fit
            sub = Round.build(ev, fixed + g.effects, E_cur, cfg, cfg.seed + 100 + rnd_i)
            e = assess_all(ev, {kind: cands[kind]}, sub, cfg, len(active), channels_v)[kind]
            return e.p_value <= cfg.alpha / max(len(active), 1)

        best, group = choose(sorted(significant), [k for k in rejected if k in small],
                             {k: evid[k].statistic for k in evid}, change, adds)
        if best is None:
            # the largest residual has two explanations: claim neither, and stop, since
            # the other candidates would be fitted against a residual it dominates
            confounded.append(group)
            reports += list(round_reports.values())
            break
        round_reports[best] = replace(round_reports[best], claimed=True)
        reports += list(round_reports.values())
        claimed.append((cands[best], evid[best].fit, round_reports[best]))
        fixed = fixed + evid[best].fit.effects
        active = [k for k in active if k != best]

    nv = {c.kind: len(c.names) for c, _, _ in claimed}
    # joint refit of the claimed causes (each refitted with the others fixed)
    if len(claimed) > 1:
        say(0.7, "refitting the claimed causes jointly")
        for i, (c, f, rep) in enumerate(list(claimed)):
            others = [e for j, (_, g, _) in enumerate(claimed) if j != i for e in g.effects]
            g = fit_candidate(ev, c, others, E=E_cur, start=f.x[: nv[c.kind]], nuisance=last.nuisance,
                              discrepancy=last.discrepancy)
            claimed[i] = (c, g, replace(rep, **fit_fields(c, g)))
    # final refit on the fine grid: the coarse signatures of local causes (a dent's
    # shift, a clock offset) are blurred by 6 x 10 mm elements (measured: a 0.15 s offset
    # fitted at 0.074 s, a lateral probe offset at about half, gravity 8 % high)
    if claimed and cfg.fine_grid and cfg.fine_refit_iterations > 0:
        say(0.72, "refitting the claimed causes on the fine grid")
        for i, (c, f, rep) in enumerate(list(claimed)):
            others = [e for j, (_, g, _) in enumerate(claimed) if j != i for e in g.effects]
            g = fit_candidate(ev, c, others, E=E_cur, start=f.x[: nv[c.kind]], fine=True,
                              iterations=cfg.fine_refit_iterations)
            claimed[i] = (c, g, replace(rep, **fit_fields(c, g)))
    lap("refits")

    det, gone = None, []
    if cfg.detectability and last is not None:
        say(0.8, "how large each kind would have to be to show")
        det = detectability(ev, last, ctx_all, cfg, cands, last_evidence, palp,
                            claimed=[c.kind for c, _, _ in claimed], confounded=confounded, refused=refused,
                            small=small, progress=lambda i, kind: say(0.8 + 0.1 * i / len(cfg.kinds),
                                                                      f"how large each kind would have to be to show: {kind}"),
                            without=lambda kind: Round.build(ev, [e for e in fixed if e.get("kind") != kind], E_cur, cfg,
                                                             cfg.seed + 200),
                            claimed_critical={c.kind: rep.critical for c, _, rep in claimed if rep.critical is not None})
        det = held_by_inversion(det, [r.sequence for r in all_base if r.inverted])
        lap("detectability")
        # E is refitted without them, and their fits go beside it as unclaimed causes
        claimed, reports, det, gone, said = withdraw(
            claimed, reports, det,
            with_dependents(claimed, undersized_claims({c.kind: f.effect for c, f, _ in claimed}, det, ctx_all)),
            "claimed, then withdrawn as below its own detectability")
        if said:
            notes += said
            e_fit = e_fit if claimed else base_fit

    # E with the claimed causes, under the model-form variants and beside the unclaimed
    # causes the held-out data leaned towards (core.diagnosis.youngs); a claim that,
    # refitted in the model-form worlds, cannot be told from no effect
    # (worlds.absence_within) is withdrawn, and E is fitted again without it
    while True:
        unexcluded = unexcluded_effects({k: (e.fit, e.statistic, e.reproduction.get("expected", 0.0), e.critical)
                                         for k, e in last_evidence.items()},
                                        [c.kind for c, _, _ in claimed]) + gone
        youngs, E_ext, ext_effects, refits, worlds = youngs_of_extended(
            prepared, ev, cfg, executor, joint=joint, claimed=[(c, f) for c, f, _ in claimed],
            youngs_modulus=E_cur, e_fit=e_fit, unexcluded=unexcluded, say=say)
        # the claimed causes as refitted with E, their intervals holding their model-form worlds
        claimed = [(c, g, with_intervals(replace(rep, **fit_fields(c, g)) if g is not f else rep, c, g, worlds))
                   for (c, f, rep), (_, g) in zip(claimed, refits)]
        gap = {c.kind: why for c, g, _ in claimed if (why := absence_within(c, g, worlds))}
        if not gap:
            break
        gap = with_dependents(claimed, gap)
        claimed, reports, det, more, said = withdraw(
            claimed, reports, det, gap, "claimed, then withdrawn: no effect within its model-form interval",
            stated={k: f"cannot tell from this data: a claim of it was {why}" for k, why in gap.items()})
        gone, notes = gone + more, notes + said
        e_fit = e_fit if claimed else base_fit
    if det:
        youngs = with_untold_kinds(youngs, {k: d.answer for k, d in det.items()})
    lap("youngs")

    # the fields the report shows on train and validation (the fine grid's runs of the
    # refits), taken now: the runs cache is then emptied, since the test stage replays
    # only test sequences (a paper-size diagnosis held 0.5 GiB of runs through it)
    base_spec = ev.spec([], E_base)
    ext_spec = ev.spec(ext_effects, E_ext)
    # shown on train and validation: the fine grid at the fits' step (the E fit's last
    # train run of the extended model is one of them); the test errors below step at the
    # simulator's own
    step = cfg.fine_step
    shown = [replace(m, simulation=step) for m in (base_spec, ext_spec if claimed else base_spec)]
    (base_train,), (base_val,), (ext_train,), (ext_val,) = ev.runs_together(
        [Request([m], role, fine=True) for m in shown for role in ("train", "validation")])
    ev.cache.clear()
    # what the report needs of the selection rounds, kept; the rounds' nuisances, nulls and
    # runs freed, and the workers' binned train and validation points with them
    nuisance_names = tuple(dict.fromkeys(last.nuisance.names)) if last else ()
    model_form = model_form_json(last, ev)
    last = rnd = last_evidence = last_fits = base_fit = e_fit = noise_runs = base = None
    evid = {}
    gc.collect()
    executor.run_everywhere(drop_binned_points)

    # test errors: base, each cause alone, extended
    say(0.96, "measuring the gain on the test sequences")
    test_blocks = ev.frame_blocks("test")
    # the base, the extended model and each cause alone on test, in one map
    base_test, ext_runs, *cause_runs = ev.runs_together(
        [Request([base_spec, ext_spec] + [ev.spec(f.effects, E_ext) for _, f, _ in claimed], "test",
                 paper=True, fine=True)])[0]
    b_err, b_s, b_c = test_error(base_test)
    e_err, e_s, _ = test_error(ext_runs)
    gain = 1.0 - e_err / b_err if b_err > 0 else 0.0
    gain_iv = gain_interval((b_s, b_c), (e_s, b_c), test_blocks, cfg.n_boot, rng) if claimed else (0.0, 0.0)
    force = None
    if joint:
        fb, fe = ev.force_rms(base_test), ev.force_rms(ext_runs)
        force = {"noise_N": ev.force_sigma.tolist(), "base_youngs_modulus": E_base,
                 "baseline_test_rms_N": fb, "extended_test_rms_N": fe, "gain": 1.0 - fe / fb if fb > 0 else 0.0}
    said = unconfirmed_on_test([c.kind for c, _, _ in claimed], gain, gain_iv, force["gain"] if force else None)
    notes += [said] if said else []
    causes = []
    for (c, f, rep), runs_c in zip(claimed, cause_runs):
        err, _, _ = test_error(runs_c)
        extra = {}
        if joint:
            fc = ev.force_rms(runs_c)
            extra = {"force_test_rms": fc, "force_gain": 1.0 - fc / force["baseline_test_rms_N"]}
        causes.append(replace(rep, test_error=err, gain=1.0 - err / b_err if b_err > 0 else 0.0, **extra))
    causes.sort(key=lambda c: -(c.gain or 0.0) - (c.force_gain or 0.0))
    reports = [next((c for c in causes if c.kind == r.kind and r.claimed), r) for r in reports]

    lap("test")
    timings["total"] = time.perf_counter() - t0
    say(1.0, "done")
    return Diagnosis(
        session=prepared.path, config=cfg, noise_sigma=math.sqrt(sigma2),
        noise_floor=float(noise_floor(prepared, cfg.fine_grid or cfg.grid, mesh=_floor_mesh(prepared, cfg, ev))), youngs=youngs, baseline_test_error=b_err,
        causes=causes, candidates=reports, confounded=confounded,
        extended_kinds=[c.kind for c in causes], extended_effects=ext_effects,
        extended_test_error=e_err, extended_gain=gain, gain_interval=gain_iv,
        summary=dict(summary(ev, all_base, sigma2, prepared),
                     validation_bin_frames=int(sum((ev.counts[n][:, :layout.top_bins] > 0).sum() for n in ev.names["validation"])),
                     noise_by_face_m={f: math.sqrt(face_sigma2[NOISE_GROUPS.index(f)]) for f in layout.faces()}),
        base_fields={r.sequence: r for r in base_train + base_val + base_test},
        extended_fields={r.sequence: r for r in ext_train + ext_val + ext_runs},
        layout=layout, timings=timings, simulations=ev.simulations, simulations_by_stage=stage_sims,
        simulations_repeated=ev.repeated,
        force=force, force_note=ev.force_note, detectability=det, palpation=palp, nuisances=nuisance_names,
        notes=tuple(notes), model_form=model_form,
    )


def inversion_notes(runs, law: str) -> list[str]:
    """What to tell when the base model's replay turned elements inside out: ``runs`` its
    :class:`core.diagnosis.trials.FieldRun` of the train and validation sequences."""
    bad = [f"{r.sequence} (at most {r.inverted} at once)" for r in runs if r.inverted]
    if not bad:
        return []
    if law == "corotational":  # no resistance to inversion
        why = "the corotational law's stress and probe force there are not physical"
        fix = "replay with the stable neo-Hookean law (--law stable_neo_hookean), which resists inversion, or press less deep"
    else:
        why = "the replay's mesh is too coarse for these presses"
        fix = "mesh finer (--element-size; --grid for a box) or press less deep"
    return [f"the replay turned tetrahedra inside out under the probe on {', '.join(bad)}: {why}, and E and "
            f"the causes fitted to them carry that; {fix}"]
