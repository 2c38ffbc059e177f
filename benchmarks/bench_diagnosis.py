"""Diagnosis benchmark: hide each effect kind (or none) in generated sessions and score the diagnosis.

Prints the confusion matrix (true kind x named kinds), the mean relative parameter
error of correctly named causes, the mean test gain and the wall time per diagnosis.

    .venv/bin/python benchmarks/bench_diagnosis.py [--seeds 0 1 2] [--kinds gravity none ...]
        [--duration 10] [--workers 2] [--sessions DIR] [--json OUT]

``--sessions DIR`` keeps the generated sessions there and reuses them on the next run
(generation is half the time); ``--json OUT`` writes every case's diagnosis.json.

Sessions are the `small` preset (4 sequences: train x 2, validation, test) with
``--duration`` s per sequence; magnitudes are those of ``HIDDEN`` below, with the
inclusion's centre moved by the seed.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from core.diagnosis import KINDS, DiagnosisConfig, diagnose
from core.identification import executor
from core.lab import generate_session
from core.lab.generate import PHANTOM_SIZE, PRESETS


def hidden(kind: str, seed: int) -> list[dict]:
    """The effect hidden for ``kind`` (empty for "none"), at a detectable magnitude."""
    rng = np.random.default_rng(1000 + seed)
    sx, sy, sz = PHANTOM_SIZE
    table = {
        "gravity": {"g": [0.0, 0.0, -9.81]},
        "inclusion": {"center": [float(rng.uniform(0.3, 0.7) * sx), float(rng.uniform(0.35, 0.65) * sy), sz - 0.011],
                      "radius": 0.009, "stiffness_ratio": 6.0},
        "viscoelasticity": {"relaxation_time": 0.5, "stiffness_ratio": 2.0},
        "friction": {"mu": 0.8},
        "base_compliance": {"stiffness": 5e4},
        "probe_radius": {"radius": 0.0075},
        "time_offset": {"offset": 0.15},
        "kinematic_offset": {"offset": [0.0015, -0.001, -0.0015]},
    }
    return [] if kind == "none" else [{"kind": kind, **table[kind]}]


def relative_error(kind: str, truth: dict, found: dict) -> float:
    """Largest relative error over the kind's parameters (vectors by norm)."""
    errs = []
    for k, v in truth.items():
        if k == "kind":
            continue
        a, b = np.asarray(v, dtype=float), np.asarray(found.get(k, np.nan), dtype=float)
        errs.append(float(np.linalg.norm(b - a) / max(np.linalg.norm(a), 1e-12)))
    return max(errs) if errs else 0.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--kinds", nargs="+", default=list(KINDS) + ["none"])
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--no-youngs", action="store_true", help="skip the E fit (faster)")
    ap.add_argument("--sessions", type=Path, help="keep (and reuse) the generated sessions in this folder")
    ap.add_argument("--json", type=Path, help="write every case's diagnosis.json into this file")
    args = ap.parse_args()
    labels = list(KINDS) + ["none"]
    confusion = {k: {j: 0 for j in labels} for k in args.kinds}
    perr, gains, times = [], [], []
    lab = replace(PRESETS["small"], sequence_durations=(args.duration,) * 4)
    results = {}
    with tempfile.TemporaryDirectory() as tmp, executor(workers=args.workers) as ex:
        root = args.sessions or Path(tmp)
        for kind in args.kinds:
            for seed in args.seeds:
                effects = hidden(kind, seed)
                path = root / f"{kind}-{seed}-{args.duration:g}s"
                if not (path / "session.json").exists():
                    generate_session(path, preset=lab, seed=seed, effects=effects, overwrite=True)
                t0 = time.perf_counter()
                d = diagnose(path, DiagnosisConfig(fit_youngs=not args.no_youngs, refine_mesh=False), executor=ex)
                dt = time.perf_counter() - t0
                times.append(dt)
                results[f"{kind}-{seed}"] = {"hidden": effects, "wall_time_s": dt, "diagnosis": d.to_json()}
                if args.json:
                    args.json.write_text(json.dumps(results, indent=1, default=float))
                named = [c.kind for c in d.causes] or ["none"]
                for n in named:
                    confusion[kind][n] += 1
                line = f"{kind:17s} seed {seed}: named {named}, gain {100 * d.extended_gain:5.1f} %, {dt:5.0f} s, {d.simulations} sims"
                if kind != "none" and kind in named:
                    c = next(c for c in d.causes if c.kind == kind)
                    e = relative_error(kind, effects[0], c.parameters)
                    perr.append(e)
                    gains.append(d.extended_gain)
                    line += f", parameter error {100 * e:.0f} % ({json.dumps(c.parameters)})"
                print(line, flush=True)
    print("\nconfusion matrix (rows: hidden, columns: named)")
    print(" " * 18 + " ".join(f"{j[:8]:>8s}" for j in labels))
    for k in args.kinds:
        print(f"{k:18s}" + " ".join(f"{confusion[k][j]:8d}" for j in labels))
    if perr:
        print(f"\nmean relative parameter error of correct claims: {100 * np.mean(perr):.0f} %")
        print(f"mean test gain of correct claims: {100 * np.mean(gains):.1f} %")
    print(f"wall time per diagnosis: mean {np.mean(times):.0f} s, max {np.max(times):.0f} s ({args.workers} workers)")


if __name__ == "__main__":
    main()
