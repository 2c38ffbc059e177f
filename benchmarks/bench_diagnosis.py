"""Diagnosis benchmark on the randomised lab: hide each effect kind (or none) and score the diagnosis.

Every case is a session of the ``field`` preset (:data:`core.lab.PRESETS`: the small
preset's 4 sequences, validation, test and two train, with the truth's law, E, Poisson's
ratio, mesh, contact, damping and noise levels drawn per seed by
:class:`core.lab.LabVariation`) and its default random palpation (no scenario-specific
probing), ``--duration`` s per sequence. A hidden kind's effect is its class's example,
``EFFECT_KINDS[kind].example(ctx, numpy.random.default_rng([seed, 99]))``; "none" sessions
hide nothing and use their own seeds (``--none-seeds``, ten by default). With ``--force
both`` every case is generated and diagnosed twice: with force columns
(``use_force=True``) and without them (a session of the same seed generated without
force columns, ``use_force=False``). Every effect kind is a candidate of every diagnosis.

    .venv/bin/python -m benchmarks.bench_diagnosis [--seeds 0 1 2] [--none-seeds 100 ... 109]
        [--kinds gravity none ...] [--force {yes,no,both}] [--duration 6] [--workers 2]
        [--sessions DIR] [--json OUT] [--no-youngs] [--learned] [--method {exact,fd,both}]

``--method both`` diagnoses every case twice, in the same run: with the exact
sensitivities of the replay as the fits' Jacobians (``exact``, the default,
``DiagnosisConfig.sensitivities=True``) and with one forward-difference replay per
parameter (``fd``, the former method, kept for this comparison); the summary then
compares their answers, wall times and simulations case by case. (Both use the compiled
time loop; the Python step is compared with it in ``bench_replay``.)

``--sessions DIR`` keeps the generated sessions there and reuses them on the next run;
``--json OUT`` writes every finished case (hidden effect, lab E, sizes, wall time and the
whole diagnosis.json) as it goes.

Per case it prints one line as it finishes; at the end, separately with and without force:
the confusion matrix (hidden kind x named kinds, "none" and "confounded"), the
false-claim rate on no-effect sessions, the share of effects at or above the stated
``min_size`` that were named exactly, the share of misses that were honest (the stated
``min_size`` above the hidden size, or None, or the hidden kind confounded; for an
inclusion, the size stated at the placement nearest it, :func:`applicable_min_size`, and
a count of those no stated placement covers), spurious
extra claims beside the hidden kind, the mean relative parameter error of exact correct
claims per kind, the coverage of the lab's E by the reported E interval (sessions with
force), and the wall time and simulations per diagnosis.

Targets (issue 16): no false claim on any no-effect session; at least 90 % of effects
above their stated ``min_size`` named exactly; every miss honest; the E interval contains
the lab's E in at least 90 % of the sessions with force. The benchmark prints how far it
is from each of them and asserts nothing.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
import traceback
from pathlib import Path

import numpy as np

from core.diagnosis import KINDS, DiagnosisConfig, diagnose
from core.identification import executor
from core.io import read_truth
from core.lab import PHANTOM_SIZE, PRESETS, LabConfig, generate_session
from core.simulation.effects import EFFECT_KINDS, PhantomContext

LABELS = (*KINDS, "none")
"""Rows of the confusion matrix: every effect kind and "none"."""
COLUMNS = (*KINDS, "none", "confounded")
"""Columns of the confusion matrix: every named kind, "none" (nothing claimed, nothing
confounded) and "confounded" (a group of kinds reported as confounded)."""


def relative_error(truth: dict, found: dict) -> float:
    """Largest relative error over an effect's parameters (vectors by norm)."""
    errs = []
    for k, v in truth.items():
        if k == "kind":
            continue
        a, b = np.asarray(v, dtype=float), np.asarray(found.get(k, np.nan), dtype=float)
        errs.append(float(np.linalg.norm(b - a) / max(np.linalg.norm(a), 1e-12)))
    return max(errs) if errs else 0.0


def learned_gain(session: Path, youngs: float, cfg: DiagnosisConfig) -> tuple[float, float]:
    """A narrow 2D correction network (widths 16/32/64, at most 6 epochs) trained on
    ``session``'s train sequences over the diagnosis's base model: ``youngs`` Pa, and
    ``cfg``'s Poisson's ratio, law and fine grid (the grid its errors are measured on).

    Returns:
        (test error of the base replay in m, the network's in-loop test gain as a fraction),
        on the paper's point-to-mesh error over the session's test sequences.
    """
    from core.learning import NetworkConfig, TrainConfig, train_and_test
    from core.preparation import prepare_session
    from core.simulation.replay import ReplayConfig
    config = ReplayConfig(youngs_modulus=youngs, poisson_ratio=cfg.poisson_ratio, law=cfg.law,
                          grid=cfg.fine_grid or cfg.grid)
    prepared = prepare_session(session, config)
    report = train_and_test(prepared, config, NetworkConfig(kind="2d", widths=(16, 32, 64)), TrainConfig(max_epochs=6, threads=1))
    te = report.test_error
    return float(te["no_network"]), float(1.0 - te["corrected"] / te["no_network"])


def lab_config(duration: float) -> LabConfig:
    """The ``field`` preset with every sequence ``duration`` s long."""
    return PRESETS["field"].with_duration(duration)


def phantom_context(cfg: LabConfig) -> PhantomContext:
    """The phantom of the lab's sessions as the effect classes see it (box size, nominal
    probe radius, no presses)."""
    return PhantomContext(size=np.asarray(PHANTOM_SIZE, dtype=float), probe_radius=float(cfg.probe_radius))


def hidden_effect(kind: str, seed: int, ctx: PhantomContext) -> tuple[list[dict], float | None]:
    """The effects hidden for ``kind`` and ``seed`` and the hidden effect's size.

    Returns:
        (effect dicts for :func:`core.lab.generate_session`, the kind's size measure of
        SESSION_FORMAT.md's detectability table): ``kind``'s example drawn with
        ``numpy.random.default_rng([seed, 99])``; ``([], None)`` for "none".
    """
    if kind == "none":
        return [], None
    effect = EFFECT_KINDS[kind].example(ctx, np.random.default_rng([int(seed), 99]))
    return [effect.to_dict()], float(effect.size(ctx))


def case_session(root: Path, cfg: LabConfig, kind: str, seed: int, effects: list[dict], force: bool,
                 duration: float) -> tuple[Path, float | None]:
    """The session of one case under ``root``, generated unless it is there already.

    Returns:
        (session folder, generation wall time in s, or None when an existing session was reused).
    """
    path = root / f"field-{kind}-{seed}-{duration:g}s-{'force' if force else 'noforce'}"
    if (path / "session.json").exists() and (path / "truth.json").exists():
        return path, None
    t0 = time.perf_counter()
    generate_session(path, preset=cfg, seed=seed, effects=effects, with_force=force, overwrite=True)
    return path, time.perf_counter() - t0


PLACEMENT_TOLERANCE = 0.005
"""m: a hidden inclusion within this of a stated placement's centre is judged by that
placement's min_size (the presses are merged at 5 mm, the same scale)."""


RADIUS_TOLERANCE = 0.0005
"""m: a hidden inclusion this much smaller than the statements' sphere is not judged by them."""


def applicable_min_size(det, hidden: dict) -> tuple[float | None, bool, str]:
    """The stated size that applies to the ``hidden`` effect, whether any does, and which.

    A placed kind (an inclusion) states a min_size under each press and one
    ``beside_distance`` to the side of the best-placed one (``parameters["placements"]``,
    ``parameters["beside"]``): a hidden inclusion is judged by the placement within
    :data:`PLACEMENT_TOLERANCE` of its centre, else by the "beside" statement when it lies
    that far (within the tolerance) from the best placement; otherwise no statement covers
    it ``(None, False, "")``: "not found" said nothing about it. The statements are for a sphere
    of their ``radius``: a smaller hidden one (by more than :data:`RADIUS_TOLERANCE`) shows
    less at the same stiffness ratio, and none covers it either. The third item names the
    statement ("its placement", "beside the best placement"; "" for other kinds). Other
    kinds: ``(min_size, True, "")``.
    """
    places = det.parameters.get("placements") if isinstance(det.parameters, dict) else None
    if not places or "center" not in hidden:
        return det.min_size, True, ""
    stated_radius = min(float(p["radius"]) for p in places)
    if float(hidden.get("radius", stated_radius)) < stated_radius - RADIUS_TOLERANCE:
        return None, False, ""
    c = np.asarray(hidden["center"], dtype=float)
    dist = [float(np.linalg.norm(np.asarray(p["center"], dtype=float) - c)) for p in places]
    i = int(np.argmin(dist))
    if dist[i] <= PLACEMENT_TOLERANCE:
        return places[i]["min_size"], True, "its placement"
    beside = det.parameters.get("beside")
    best = det.parameters.get("center")
    if beside and best is not None:
        r = float(np.linalg.norm(np.asarray(best, dtype=float) - c))
        if abs(r - float(beside["distance"])) <= PLACEMENT_TOLERANCE:
            return beside["min_size"], True, f"{1e3 * float(beside['distance']):.0f} mm beside the best placement"
    return None, False, ""


def _fmt(v: float | None, unit: str = "") -> str:
    return "-" if v is None else f"{v:.3g}{' ' + unit if unit else ''}"


def run_case(root: Path, cfg: LabConfig, ctx: PhantomContext, kind: str, seed: int, force: bool,
             args: argparse.Namespace, ex, method: str = "exact") -> dict:
    """Generate (or reuse) one case's session, diagnose it and print its line.

    Returns:
        the case's record: kind, seed, force, hidden effects and size, the lab's E, the
        named and confounded kinds, the hidden kind's stated min_size and answer, the
        reported E, parameter error of an exact claim, wall time, simulations and the
        whole diagnosis.json (``"diagnosis"``); on a failure, ``"error"`` instead.
    """
    effects, size = hidden_effect(kind, seed, ctx)
    rec: dict = {"kind": kind, "seed": int(seed), "force": bool(force), "hidden": effects, "hidden_size": size,
                 "method": method}
    try:
        path, gen_s = case_session(root, cfg, kind, seed, effects, force, args.duration)
        rec["session"], rec["generation_s"] = str(path), gen_s
        truth = read_truth(path) or {}
        rec["lab_youngs"] = E_lab = float(truth["youngs_modulus"]) if "youngs_modulus" in truth else None
        rec["lab_variation"] = truth.get("lab_variation")
        dcfg = DiagnosisConfig(use_force=force, fit_youngs=not args.no_youngs, sensitivities=method == "exact",
                               null_residual=args.null)
        t0 = time.perf_counter()
        d = diagnose(path, dcfg, executor=ex)
        rec["wall_time_s"] = dt = time.perf_counter() - t0
    except Exception as exc:  # a benchmark reports a failed case and goes on
        rec["error"] = f"{type(exc).__name__}: {exc}"
        print(f"{kind:17s} seed {seed:3d} force {'yes' if force else 'no ':3s}: FAILED {rec['error']}", flush=True)
        traceback.print_exc()
        return rec

    named = [c.kind for c in d.causes]
    rec["named"] = named
    rec["confounded"] = [list(g) for g in d.confounded]
    rec["simulations"] = int(d.simulations)
    rec["youngs"] = {k: d.youngs.get(k) for k in ("value", "interval", "identifiable")}
    rec["answers"] = d.answers()
    det = (d.detectability or {}).get(kind) if kind != "none" else None
    rec["stated_min_size"] = det.min_size if det is not None else None
    rec["min_size"], rec["covered"], rec["statement"] = applicable_min_size(det, effects[0]) if det is not None else (None, True, "")
    rec["answer"] = det.answer if det is not None else None
    rec["parameter_error"] = None
    if kind != "none" and named == [kind]:
        rec["parameter_error"] = relative_error(effects[0], d.causes[0].parameters)
    rec["extended_gain"] = float(d.extended_gain)
    rec["force_gain"] = float(d.force["gain"]) if d.force else None

    line = f"{kind:17s} seed {seed:3d} force {'yes' if force else 'no ':3s} [{method}]: named {named or ['none']}"
    if rec["confounded"]:
        line += f", confounded {rec['confounded']}"
    if kind != "none":
        unit = EFFECT_KINDS[kind].size_unit
        line += (f"; hidden {_fmt(size, unit)}, min_size {_fmt(rec['stated_min_size'], unit)}"
                 + (f" ({rec['statement']}: {_fmt(rec['min_size'], unit)})" if rec["statement"] and rec["min_size"] != rec["stated_min_size"] else "")
                 + ("" if rec["covered"] else " (no statement covers it: its placement or radius)") + f", answer {rec['answer']}")
        if rec["parameter_error"] is not None:
            line += f", parameter error {100 * rec['parameter_error']:.0f} %"
    y = rec["youngs"]
    iv = y.get("interval")
    line += (f"; E {_fmt(y.get('value'), 'Pa')} [{_fmt(iv[0]) if iv else '-'}, {_fmt(iv[1]) if iv else '-'}]"
             f"{'' if y.get('identifiable') else ' (not identifiable)'} vs lab {_fmt(E_lab, 'Pa')}")
    line += f"; {dt:.0f} s, {d.simulations} sims"
    if gen_s is not None:
        line += f" (generated in {gen_s:.0f} s)"
    if args.learned:
        # the network corrects the base model, the one the diagnosis's gain is measured against
        E = d.force["base_youngs_modulus"] if d.force else dcfg.youngs_modulus
        base_err, rec["learned_gain"] = learned_gain(path, E, dcfg)
        line += (f"; gain: diagnosis {100 * d.extended_gain:.1f} %, 2D network {100 * rec['learned_gain']:.1f} % "
                 f"(its base {1e3 * base_err:.3f} mm, the diagnosis's {1e3 * d.baseline_test_error:.3f} mm)")
    rec["diagnosis"] = d.to_json()
    print(line, flush=True)
    return rec


def _share(n: int, total: int) -> str:
    return f"{n}/{total}" + (f" ({100 * n / total:.0f} %)" if total else "")


def _contains(rec: dict) -> bool:
    y, E = rec["youngs"], rec.get("lab_youngs")
    iv = y.get("interval")
    return bool(y.get("identifiable") and iv and E is not None and iv[0] <= E <= iv[1])


def print_summary(records: list[dict], kinds: list[str], workers: int) -> None:
    """Print the benchmark's tables over the finished ``records`` of :func:`run_case`,
    separately for the cases with and without force columns."""
    done = [r for r in records if "error" not in r]
    failed = [r for r in records if "error" in r]
    if failed:
        print(f"\n{len(failed)} case(s) failed: " + ", ".join(f"{r['kind']}-{r['seed']}-{'force' if r['force'] else 'noforce'}"
                                                          for r in failed))
    for force in (True, False):
        rs = [r for r in done if r["force"] is force]
        if not rs:
            continue
        tag = "WITH force columns" if force else "WITHOUT force columns"
        print(f"\n===== {tag}: {len(rs)} diagnoses =====")

        # 1. confusion matrix
        print("\n1. confusion matrix (rows: hidden; columns: named; a case naming two kinds counts in both; "
              "'none': nothing claimed or confounded; 'confounded': a confounded group reported)")
        print(" " * 18 + " ".join(f"{c[:8]:>8s}" for c in COLUMNS) + "   exactly  cases")
        for k in [k for k in LABELS if k in kinds]:
            rows = [r for r in rs if r["kind"] == k]
            if not rows:
                continue
            counts = dict.fromkeys(COLUMNS, 0)
            for r in rows:
                for n in r["named"]:
                    counts[n] += 1
                if r["confounded"]:
                    counts["confounded"] += 1
                if not r["named"] and not r["confounded"]:
                    counts["none"] += 1
            exact = sum(r["named"] == ([] if k == "none" else [k]) for r in rows)
            print(f"{k:18s}" + " ".join(f"{counts[c]:8d}" for c in COLUMNS) + f"   {exact:7d}  {len(rows):5d}")

        # 2. false claims on no-effect sessions
        nones = [r for r in rs if r["kind"] == "none"]
        if nones:
            claims = [r for r in nones if r["named"]]
            conf = [r for r in nones if r["confounded"] and not r["named"]]
            print(f"\n2. false-claim rate on no-effect sessions: {_share(len(claims), len(nones))} with a claim "
                  f"(target: none){'; seeds ' + str([r['seed'] for r in claims]) if claims else ''}; "
                  f"{len(conf)} more reported only a confounded group")

        # 3. detection, honest misses, spurious claims
        hidden = [r for r in rs if r["kind"] != "none"]
        if hidden:
            det = [r for r in hidden if r["min_size"] is not None and r["hidden_size"] >= r["min_size"]]
            exact = [r for r in det if r["named"] == [r["kind"]]]
            misses = [r for r in hidden if r["kind"] not in r["named"]]
            honest = [r for r in misses if r["min_size"] is None or r["min_size"] > r["hidden_size"]
                      or any(r["kind"] in g for g in r["confounded"])]
            uncovered = [r for r in misses if not r.get("covered", True)]
            extra = [r for r in hidden if any(n != r["kind"] for n in r["named"])]
            n_extra = sum(sum(n != r["kind"] for n in r["named"]) for r in hidden)
            print(f"\n3. hidden effects: {len(hidden)} cases, {len(det)} at or above their stated min_size")
            print(f"   named exactly, of those at or above min_size: {_share(len(exact), len(det))} (target >= 90 %)")
            print(f"   named exactly, of all: {_share(sum(r['named'] == [r['kind']] for r in hidden), len(hidden))}")
            print(f"   misses (hidden kind not named): {len(misses)}; honest: {_share(len(honest), len(misses))} "
                  f"(target: all)")
            if uncovered:
                print(f"   of the honest misses, {len(uncovered)} no statement covered (away from every stated placement, or smaller than the stated sphere): "
                      + ", ".join(f"{r['kind']} seed {r['seed']}" for r in uncovered))
            honest_ids = {id(r) for r in honest}
            dishonest = [r for r in misses if id(r) not in honest_ids]
            if dishonest:
                print("   dishonest misses: " + ", ".join(
                    f"{r['kind']} seed {r['seed']} (hidden {_fmt(r['hidden_size'])}, min_size {_fmt(r['min_size'])})"
                    for r in dishonest))
            print(f"   cases with a spurious claim beside (or instead of) the hidden kind: {_share(len(extra), len(hidden))}, "
                  f"{n_extra} spurious claims in all")
            print(f"   {'kind':17s} {'cases':>5s} {'>=min':>5s} {'exact':>5s} {'misses':>6s} {'honest':>6s} {'extra':>5s}   "
                  "hidden size / stated min_sizes")
            for k in [k for k in KINDS if k in kinds]:
                kr = [r for r in hidden if r["kind"] == k]
                if not kr:
                    continue
                kd = [r for r in kr if r["min_size"] is not None and r["hidden_size"] >= r["min_size"]]
                km = [r for r in kr if k not in r["named"]]
                kh = [r for r in km if id(r) in honest_ids]
                ke = [r for r in kr if any(n != k for n in r["named"])]
                unit = EFFECT_KINDS[k].size_unit
                mins = ", ".join(_fmt(r["min_size"]) for r in kr)
                print(f"   {k:17s} {len(kr):5d} {len(kd):5d} {sum(r['named'] == [k] for r in kr):5d} {len(km):6d} "
                      f"{len(kh):6d} {len(ke):5d}   {_fmt(kr[0]['hidden_size'])} / {mins} {unit}")

            # 4. parameter errors
            print("\n4. relative parameter error of exact correct claims (largest over the parameters), mean per kind")
            any_err = False
            for k in [k for k in KINDS if k in kinds]:
                errs = [r["parameter_error"] for r in hidden if r["kind"] == k and r["parameter_error"] is not None]
                if errs:
                    any_err = True
                    print(f"   {k:17s} {100 * np.mean(errs):5.0f} % over {len(errs)} (max {100 * np.max(errs):.0f} %)")
            if not any_err:
                print("   (no exact correct claim)")

        # 5. E coverage
        ys = [r for r in rs if r.get("lab_youngs") is not None]
        if ys:
            cover = [r for r in ys if _contains(r)]
            ident = [r for r in ys if r["youngs"].get("identifiable")]
            ratios = [r["youngs"]["value"] / r["lab_youngs"] for r in ys if r["youngs"].get("value") is not None]
            stated = [r for r in ys if r["youngs"].get("interval")]
            held = [r for r in stated if r["youngs"]["interval"][0] <= r["lab_youngs"] <= r["youngs"]["interval"][1]]
            target = " (target >= 90 %)" if force else " (no target without force)"
            print(f"\n5. E: interval identifiable and containing the lab's E in {_share(len(cover), len(ys))}{target}; "
                  f"identifiable in {_share(len(ident), len(ys))}, of those containing it {_share(len(cover), len(ident))}; "
                  f"any stated interval (identifiable or not) containing it {_share(len(held), len(stated))}; value / lab E: median "
                  f"{np.median(ratios) if ratios else float('nan'):.3f}"
                  + (f" (range {np.min(ratios):.3f}-{np.max(ratios):.3f})" if ratios else ""))

        # 6. cost
        times = [r["wall_time_s"] for r in rs]
        sims = [r["simulations"] for r in rs]
        print(f"\n6. wall time per diagnosis: mean {np.mean(times):.0f} s, max {np.max(times):.0f} s "
              f"({workers} workers); simulations: mean {np.mean(sims):.0f}")
        nets = [(r["extended_gain"], r["learned_gain"]) for r in rs if "learned_gain" in r]
        if nets:
            a = np.array(nets)
            print(f"   mean test gain: diagnosis {100 * a[:, 0].mean():.1f} %, 2D network {100 * a[:, 1].mean():.1f} % "
                  "(same test sequences)")


def print_methods(records: list[dict]) -> None:
    """Print the exact-sensitivity and finite-difference diagnoses of the same cases side by
    side: named kinds, E, wall time and simulations."""
    by = {}
    for r in records:
        if "error" not in r:
            by.setdefault((r["kind"], r["seed"], r["force"]), {})[r["method"]] = r
    pairs = [(k, v) for k, v in by.items() if {"exact", "fd"} <= set(v)]
    if not pairs:
        return
    print("\n===== exact sensitivities vs forward differences (same cases, same run) =====")
    for (kind, seed, force), v in pairs:
        a, b = v["exact"], v["fd"]
        same = a["named"] == b["named"] and a["confounded"] == b["confounded"]
        print(f"{kind} seed {seed} force {'yes' if force else 'no'}: exact {a['named'] or ['none']} "
              f"{a['wall_time_s']:.0f} s {a['simulations']} sims, E {_fmt(a['youngs'].get('value'), 'Pa')}; "
              f"fd {b['named'] or ['none']} {b['wall_time_s']:.0f} s {b['simulations']} sims, "
              f"E {_fmt(b['youngs'].get('value'), 'Pa')}; {'same answer' if same else 'DIFFERENT answers'}; "
              f"speed-up {b['wall_time_s'] / a['wall_time_s']:.2f}x")


def _jsonable(o):
    if hasattr(o, "tolist"):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    return float(o)


def main() -> None:
    """Parse the command line, run every case (printing a line each) and print the summary."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="seeds of the hidden-kind cases")
    ap.add_argument("--none-seeds", type=int, nargs="+", default=list(range(100, 110)),
                    help="seeds of the no-effect cases (default 100-109)")
    ap.add_argument("--kinds", nargs="+", default=list(LABELS), choices=LABELS,
                    help="hidden kinds (default: every effect kind and none)")
    ap.add_argument("--force", choices=("yes", "no", "both"), default="both",
                    help="sessions with force columns, without, or both (default)")
    ap.add_argument("--duration", type=float, default=6.0, help="length of each sequence, s")
    ap.add_argument("--workers", type=int, default=2, help="Dask worker processes")
    ap.add_argument("--sessions", type=Path, help="keep (and reuse) the generated sessions in this folder")
    ap.add_argument("--json", type=Path, help="write every finished case (with its diagnosis.json) into this file")
    ap.add_argument("--no-youngs", action="store_true", help="without force: skip the E fit (faster)")
    ap.add_argument("--learned", action="store_true", help="also train a small 2D network per session and compare gains")
    ap.add_argument("--method", choices=("exact", "fd", "both"), default="exact",
                    help="the fits' Jacobians: exact sensitivities (default), forward differences (the former "
                         "method), or both on every case")
    ap.add_argument("--null", choices=("round", "candidate"), default=DiagnosisConfig().null_residual,
                    help="what the held-out test's bootstrap resamples: each candidate's own fitted residual "
                         "(the default) or the round's (DiagnosisConfig.null_residual)")
    args = ap.parse_args()
    methods = ("exact", "fd") if args.method == "both" else (args.method,)

    cfg = lab_config(args.duration)
    ctx = phantom_context(cfg)
    forces = {"yes": (True,), "no": (False,), "both": (True, False)}[args.force]
    print("lab: the 'field' preset, default random palpation, "
          f"{len(cfg.sequence_roles)} x {args.duration:g} s ({', '.join(cfg.sequence_roles)}); "
          "truth drawn per seed from LabVariation:")
    for k, v in cfg.variation.to_dict().items():
        print(f"  {k}: {v}")
    print(f"candidate kinds: {', '.join(KINDS)}; alpha {DiagnosisConfig().alpha} per selection round")
    print(f"hidden effects (each kind's example, default_rng([seed, 99]); seed {args.seeds[0]} shown):")
    for k in [k for k in KINDS if k in args.kinds]:
        effects, size = hidden_effect(k, args.seeds[0], ctx)
        print(f"  {k:17s} size {_fmt(size, EFFECT_KINDS[k].size_unit)}: {json.dumps(effects[0])}")
    print(flush=True)

    cases = []
    n = max(len(args.seeds), len(args.none_seeds))
    for i in range(n):
        for kind in args.kinds:
            seeds = args.none_seeds if kind == "none" else args.seeds
            if i < len(seeds):
                cases.extend((kind, seeds[i], f) for f in forces)

    records: list[dict] = []
    results: dict[str, dict] = {}
    with tempfile.TemporaryDirectory() as tmp, executor(workers=args.workers) as ex:
        root = args.sessions or Path(tmp)
        root.mkdir(parents=True, exist_ok=True)
        for kind, seed, force in cases:
            for method in methods:
                rec = run_case(root, cfg, ctx, kind, seed, force, args, ex, method)
                records.append(rec)
                results[f"{kind}-{seed}-{'force' if force else 'noforce'}-{method}"] = rec
                if args.json:
                    args.json.write_text(json.dumps(results, indent=1, default=_jsonable))
    for method in methods:
        if len(methods) > 1:
            print(f"\n########## method: {method} ##########")
        print_summary([r for r in records if r["method"] == method], list(args.kinds), args.workers)
    print_methods(records)


if __name__ == "__main__":
    main()
