"""Diagnosis benchmark: hide each effect kind (or none) in generated sessions and score the diagnosis.

Prints the confusion matrix (true kind x named kinds), the mean relative parameter
error of correctly named causes, the mean test gains (the paper's point-to-mesh error
and, with force data, the RMS force error) and the wall time per diagnosis; with
``--learned``, the test gain of a small 2D correction network trained on the same
session, on the same test sequences.

    .venv/bin/python -m benchmarks.bench_diagnosis [--seeds 0 1 2] [--kinds gravity none ...]
        [--duration 10] [--workers 2] [--no-force] [--sessions DIR] [--json OUT] [--learned]

``--sessions DIR`` keeps the generated sessions there and reuses them on the next run;
``--json OUT`` writes every case's diagnosis.json (and the network's gain) as it goes.

Sessions are :func:`core.lab.scenario`'s: the `small` preset (4 sequences: validation,
test, two train) with ``--duration`` s per sequence, the magnitudes of
:func:`core.lab.hidden_effects`, an inclusion whose centre moves with the seed and a
palpation over it, sliding pokes for friction, and force columns unless ``--no-force``.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from core.diagnosis import KINDS, DiagnosisConfig, diagnose
from core.identification import executor
from core.lab import SCENARIO_KINDS, generate_session, scenario


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
    from core.simulation.replay import ReplayConfig, prepare_session

    config = ReplayConfig(youngs_modulus=youngs, poisson_ratio=cfg.poisson_ratio, law=cfg.law,
                          grid=cfg.fine_grid or cfg.grid)
    prepared = prepare_session(session, config)
    report = train_and_test(prepared, config, NetworkConfig(kind="2d", widths=(16, 32, 64)), TrainConfig(max_epochs=6, threads=1))
    te = report.test_error
    return float(te["no_network"]), float(1.0 - te["corrected"] / te["no_network"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--kinds", nargs="+", default=list(SCENARIO_KINDS), choices=SCENARIO_KINDS)
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--no-force", action="store_true", help="sessions without force columns")
    ap.add_argument("--no-youngs", action="store_true", help="without force: skip the E fit (faster)")
    ap.add_argument("--sessions", type=Path, help="keep (and reuse) the generated sessions in this folder")
    ap.add_argument("--json", type=Path, help="write every case's diagnosis.json into this file")
    ap.add_argument("--learned", action="store_true", help="also train a small 2D network per session and compare gains")
    args = ap.parse_args()
    labels = list(KINDS) + ["none"]
    confusion = {k: {j: 0 for j in labels} for k in args.kinds}
    exact = {k: 0 for k in args.kinds}
    per_kind: dict[str, list[tuple[float, float, float | None]]] = {k: [] for k in args.kinds}
    perr, gains, fgains, times, nets = [], [], [], [], []
    results = {}
    force = not args.no_force
    with tempfile.TemporaryDirectory() as tmp, executor(workers=args.workers) as ex:
        root = args.sessions or Path(tmp)
        for kind in args.kinds:
            for seed in args.seeds:
                lab, effects = scenario(kind, seed, args.duration)
                path = root / f"{kind}-{seed}-{args.duration:g}s{'-force' if force else ''}"
                if not (path / "session.json").exists():
                    generate_session(path, preset=lab, seed=seed, effects=effects, with_force=force, overwrite=True)
                t0 = time.perf_counter()
                cfg = DiagnosisConfig(fit_youngs=not args.no_youngs, refine_mesh=False)
                d = diagnose(path, cfg, executor=ex)
                dt = time.perf_counter() - t0
                times.append(dt)
                case = {"hidden": effects, "wall_time_s": dt, "diagnosis": d.to_json()}
                named = [c.kind for c in d.causes] or ["none"]
                for n in named:
                    confusion[kind][n] += 1
                exact[kind] += named == [kind]
                fg = f", force gain {100 * d.force['gain']:5.1f} %" if d.force else ""
                line = (f"{kind:17s} seed {seed}: named {named}, gain {100 * d.extended_gain:5.1f} %{fg}, "
                        f"{dt:5.0f} s, {d.simulations} sims")
                if kind != "none" and kind in named:
                    c = next(c for c in d.causes if c.kind == kind)
                    e = relative_error(effects[0], c.parameters)
                    perr.append(e)
                    gains.append(d.extended_gain)
                    if d.force:
                        fgains.append(d.force["gain"])
                    per_kind[kind].append((e, d.extended_gain, d.force["gain"] if d.force else None))
                    line += f", parameter error {100 * e:.0f} % ({json.dumps(c.parameters)})"
                if args.learned:
                    # the network corrects the base model, the one the diagnosis's gain is measured against
                    E = d.force["base_youngs_modulus"] if d.force else cfg.youngs_modulus
                    base_err, case["learned_gain"] = learned_gain(path, E, cfg)
                    nets.append((d.extended_gain, case["learned_gain"]))
                    line += (f"; 2D network gain {100 * case['learned_gain']:.1f} % (its base {1e3 * base_err:.3f} mm, "
                             f"the diagnosis's {1e3 * d.baseline_test_error:.3f} mm)")
                results[f"{kind}-{seed}"] = case
                if args.json:
                    args.json.write_text(json.dumps(results, indent=1, default=float))
                print(line, flush=True)
    print("\nconfusion matrix (rows: hidden, columns: named; a case naming two kinds counts in both)")
    print(" " * 18 + " ".join(f"{j[:8]:>8s}" for j in labels) + "   exactly")
    for k in args.kinds:
        print(f"{k:18s}" + " ".join(f"{confusion[k][j]:8d}" for j in labels) + f"   {exact[k]} of {len(args.seeds)}")
    print("\nper hidden kind, over the cases that named it: mean relative parameter error, mean test gain (surface / force)")
    for k, rows in per_kind.items():
        if rows:
            a = np.array([(e, g, np.nan if f is None else f) for e, g, f in rows])
            print(f"{k:18s} {len(rows)} named: parameter error {100 * a[:, 0].mean():4.0f} %, "
                  f"gain {100 * a[:, 1].mean():5.1f} % / {100 * np.nanmean(a[:, 2]) if np.isfinite(a[:, 2]).any() else float('nan'):5.1f} %")
    if perr:
        print(f"\nmean relative parameter error of correct claims: {100 * np.mean(perr):.0f} %")
        print(f"mean test gain of correct claims: {100 * np.mean(gains):.1f} % (paper's point-to-mesh error)")
    if fgains:
        print(f"mean force gain of correct claims: {100 * np.mean(fgains):.1f} % (RMS force error on test)")
    if nets:
        a = np.array(nets)
        print(f"mean test gain: diagnosis {100 * a[:, 0].mean():.1f} %, 2D network {100 * a[:, 1].mean():.1f} % (same test sequences)")
    print(f"wall time per diagnosis: mean {np.mean(times):.0f} s, max {np.max(times):.0f} s ({args.workers} workers)")


if __name__ == "__main__":
    main()
