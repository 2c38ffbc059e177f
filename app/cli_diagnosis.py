"""``tissuetwin diagnose``: what the simulation gets wrong, why, and what the fix is worth."""

from __future__ import annotations

from pathlib import Path


def cmd_diagnose(args) -> int:
    from rich.console import Console

    from app.cli import _progress
    from core.diagnosis import DiagnosisConfig, diagnose, write_diagnosis
    from core.identification import executor

    config = DiagnosisConfig(grid=tuple(args.grid), fit_youngs=not args.no_youngs, refine_mesh=not args.no_mesh_refinement,
                             use_force=False if args.no_force else None, segments=args.segments,
                             element_size=args.element_size, law=args.law)
    with executor(args.scheduler, workers=args.workers, serial=args.serial) as ex, _progress(f"diagnosing {Path(args.session).name}") as cb:
        if args.network:
            diag = _diagnose_with_network(args, config, ex, cb)
        else:
            diag = diagnose(args.session, config, executor=ex, callback=cb)
    from core.diagnosis.youngs import gravity_at_reported_youngs

    out = write_diagnosis(diag, args.out)
    console = Console()
    if diag.causes:
        for c in diag.causes:
            fg = "" if c.force_gain is None else f", force gain {100 * c.force_gain:.1f} %"
            console.print(f"cause: [bold]{c.kind}[/bold] {c.parameters} (confidence {c.confidence:.2f}, test gain {100 * (c.gain or 0):.1f} %{fg})")
            if c.kind == "gravity" and (g := gravity_at_reported_youngs(c.parameters["g"], diag.youngs)) is not None:
                console.print(f"  (|g| {g:.2f} m/s^2 at the reported E {diag.youngs['value']:.4g} Pa: fitted on the "
                              f"replay grid at {diag.youngs['replay_grid_value_used']:.4g} Pa, and the sag is set by rho g / E)")
    else:
        console.print("[bold]no effect found[/bold] beyond noise and model-form error")
    if diag.learned_correction:
        lc = diag.learned_correction
        shares = ", ".join(f"{c['kind']} {100 * c['share']:.0f} %" for c in lc["causes"][:3])
        console.print(f"learned correction ({lc['correction_rms_m'] * 1e3:.3f} mm RMS): best matched by {shares}"
                      + (f"; the claimed causes account for {100 * lc['claimed_share']:.0f} %" if lc["claimed_share"] is not None else ""))
    for group in diag.confounded:
        console.print(f"confounded, not picked: {' / '.join(group)}")
    for kind, d in (diag.detectability or {}).items():
        size = "no size would show" if d.min_size is None else f"min size {d.min_size:.3g} {d.unit}".rstrip()
        console.print(f"  {kind:<17} {d.answer.replace('_', ' '):<11} ({size})")
    lo, hi = diag.gain_interval
    console.print(
        f"test error: base {diag.baseline_test_error * 1e3:.3f} mm, extended {diag.extended_test_error * 1e3:.3f} mm "
        f"(gain {100 * diag.extended_gain:.1f} %, 95 % interval {100 * lo:.1f} to {100 * hi:.1f} %); noise floor {diag.noise_floor * 1e3:.3f} mm"
    )
    if diag.force:
        fz = diag.force
        console.print(f"probe force on test: RMS error base {fz['baseline_test_rms_N'] * 1e3:.1f} mN (E {fz['base_youngs_modulus']:.4g} Pa), "
                      f"extended {fz['extended_test_rms_N'] * 1e3:.1f} mN (gain {100 * fz['gain']:.1f} %)")
    else:
        console.print(f"probe force: {diag.force_note}")
    for note in diag.notes:
        console.print(f"note: {note}")
    repeated = f" ({diag.simulations_repeated} of runs the cache had dropped)" if diag.simulations_repeated else ""
    print(f"{diag.simulations} simulations{repeated} in {diag.timings['total']:.0f} s; "
          f"wrote {out}/diagnosis.json and {out}/report.md")
    return 0


def cmd_plan(args) -> int:
    """``tissuetwin plan``: the palpation that would make undecidable kinds decidable."""
    import json

    from rich.console import Console

    from app.cli import _progress
    from core.diagnosis import DiagnosisConfig, diagnose_prepared
    from core.diagnosis.planner import PlanError, PlanLimits, plan_experiment, plan_inputs, write_plan
    from core.errors import TissueTwinError
    from core.identification import executor
    from core.preparation import prepare_session
    from core.simulation.replay import ReplayConfig
    config = DiagnosisConfig(use_force=False if args.no_force else None)
    limits = PlanLimits(max_depth=args.max_depth, speed=args.speed, duration=args.duration)
    with executor(args.scheduler, workers=args.workers, serial=args.serial) as ex, _progress(f"planning {Path(args.session).name}") as cb:
        prepared = prepare_session(args.session, ReplayConfig(grid=config.grid), callback=lambda f, m: cb(0.05 * f, m))
        if args.diagnosis:
            path = Path(args.diagnosis)
            path = path / "diagnosis.json" if path.is_dir() else path
            try:
                detect, fixed, E = plan_inputs(json.loads(path.read_text()), config)
            except (OSError, ValueError, PlanError) as exc:
                raise TissueTwinError(f"{path}: not a diagnosis.json with detectability ({exc})") from exc
        else:
            diag = diagnose_prepared(prepared, config, executor=ex, callback=lambda f, m: cb(0.05 + 0.6 * f, m))
            detect, fixed, E = plan_inputs(diag, config)
        plan = plan_experiment(prepared, detect, config, fixed=fixed, youngs_modulus=E,
                               kinds=args.kinds or None, limits=limits, executor=ex,
                               callback=lambda f, m: cb(0.65 + 0.35 * f, m))
    out = write_plan(plan, args.out)
    console = Console()
    console.print("[bold]plan[/bold] for " + (", ".join(f"{k} ({w})" for k, w in plan.targets.items()) or "a general protocol"))
    for line in plan.description:
        console.print("  " + line)
    for k, v in plan.predicted.items():
        now = plan.current.get(k)
        console.print(f"  {k}: now {'cannot tell' if now is None else f'{now:.3g}'} -> {'cannot tell' if v is None else f'{v:.3g}'}")
    print(f"wrote {out}/kinematics.csv, {out}/plan.json and {out}/plan.md")
    return 0


def _diagnose_with_network(args, config, ex, cb):
    """Diagnose, then explain the checkpoint's correction field on the test sequences."""
    from core.diagnosis import diagnose_prepared
    from core.diagnosis.explain import explain_diagnosis
    from core.learning import build_frames, correction_field, load_checkpoint
    from core.preparation import prepare_session
    from core.simulation.replay import ReplayConfig
    ck = load_checkpoint(args.network)  # first: a bad checkpoint fails before minutes of work
    prepared = prepare_session(args.session, ReplayConfig(grid=config.grid), callback=lambda f, m: cb(0.05 * f, m))
    diag = diagnose_prepared(prepared, config, executor=ex, callback=lambda f, m: cb(0.05 + 0.85 * f, m))
    cb(0.9, "explaining the learned correction")
    replay = ck.replay_config()
    tests = [n for n, s in prepared.sequences.items() if s.role == "test"]
    frames = build_frames(prepared, replay, names=tests)
    correction = {n: correction_field(ck, frames[n]) for n in tests}
    diag = explain_diagnosis(diag, prepared, correction, replay, executor=ex)
    cb(1.0, "done")
    return diag


def register(sub) -> None:
    """Add the ``diagnose`` subcommand to the ``tissuetwin`` parser's subparsers."""
    from app.cli import _add_execution_options
    from core.simulation.model import LAWS

    p = sub.add_parser("diagnose", help="name what the simulation lacks, extend the model, measure the gain")
    p.add_argument("session")
    p.add_argument("--out", required=True)
    p.add_argument("--grid", type=int, nargs=3, default=(13, 5, 5), metavar=("NX", "NY", "NZ"),
                   help="replay grid of a box phantom (default 13 5 5)")
    p.add_argument("--element-size", type=float, default=None, metavar="M",
                   help="target element size of a phantom given by phantom.stl, m (default: about the paper's 325 "
                        "nodes; the fine mesh halves it)")
    p.add_argument("--law", choices=LAWS, default="corotational",
                   help="material law of the replay (default the paper's corotational linear; stable_neo_hookean "
                        "resists the element inversion of deep presses)")
    p.add_argument("--no-youngs", action="store_true", help="keep E at 5e3 Pa instead of fitting it with the claimed causes")
    p.add_argument("--no-mesh-refinement", action="store_true", help="fit E on the replay grid only")
    p.add_argument("--no-force", action="store_true",
                   help="leave the force columns out of the evidence (by default they are used when every sequence has them)")
    p.add_argument("--network", metavar="CHECKPOINT",
                   help="a trained correction network (tissuetwin train): report how much of its correction each cause accounts for")
    p.add_argument("--segments", type=int, default=None, metavar="N",
                   help="fit on at most N pokes (cut at rest) of the train sequences and N of the validation ones, "
                        "chosen to cover the palpation: long recordings cost no more than N pokes")
    _add_execution_options(p)
    p.set_defaults(func=cmd_diagnose)

    from core.simulation.effects import EFFECT_KINDS

    p = sub.add_parser("plan", help="the palpation protocol that would make the undetectable or confounded kinds decidable")
    p.add_argument("session")
    p.add_argument("--out", required=True)
    p.add_argument("--diagnosis", metavar="DIAGNOSIS", help="a diagnosis folder or diagnosis.json of this session "
                   "(default: diagnose it first)")
    p.add_argument("--kinds", nargs="*", choices=sorted(EFFECT_KINDS), help="the kinds to make decidable "
                   "(default: those that could not be told, were confounded, or show only above their reference size)")
    p.add_argument("--max-depth", type=float, default=0.008, help="deepest press, m (default 0.008)")
    p.add_argument("--speed", type=float, default=0.010, help="fastest probe speed in contact, m/s (default 0.010)")
    p.add_argument("--duration", type=float, default=20.0, help="most seconds of probing (default 20)")
    p.add_argument("--no-force", action="store_true", help="diagnose without the force columns")
    _add_execution_options(p)
    p.set_defaults(func=cmd_plan)
