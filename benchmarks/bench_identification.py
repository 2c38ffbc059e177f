"""Identification cost: the paper's six-point coarse sweep on one 60 s sequence, serial
against a 2-worker local Dask cluster, and the wall time and simulation count of a fit.
Prints; asserts nothing.

    .venv/bin/python -m benchmarks.bench_identification [--work /tmp/tissuetwin-bench-id]
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

from core.identification import PAPER_COARSE, Trial, executor, fit_youngs_modulus, sweep
from core.preparation import prepare_session
def main() -> None:
    from core.lab import PRESETS, generate_session

    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--work", default="/tmp/tissuetwin-bench-id")
    parser.add_argument("--sweep-only", action="store_true", help="skip the fits")
    args = parser.parse_args()
    work = Path(args.work)
    minute = work / "one-minute"
    if not (minute / "session.json").exists():
        cfg = replace(PRESETS["small"], sequence_durations=(60.0,), sequence_roles=("train",), grid=(19, 7, 7))
        generate_session(minute, preset=cfg, seed=1, overwrite=True)
    prepared = prepare_session(minute)
    frames = sum(len(s.frame_times) for s in prepared.sequences.values())
    print(f"one 60 s sequence, {frames} frames at 15 Hz, replay grid 13x5x5, E in {PAPER_COARSE}")
    with executor(serial=True) as ex:
        t0 = time.perf_counter()
        sweep(prepared, PAPER_COARSE, executor=ex)
        print(f"  coarse sweep, serial:            {time.perf_counter() - t0:6.1f} s")
    t0 = time.perf_counter()
    with executor(workers=2) as ex:
        t1 = time.perf_counter()
        sweep(prepared, PAPER_COARSE, executor=ex)
        t2 = time.perf_counter()
    print(f"  coarse sweep, 2-worker cluster:  {t2 - t1:6.1f} s (+{t1 - t0:.1f} s cluster start)")
    if args.sweep_only:
        return

    force = work / "small-force"
    if not (force / "session.json").exists():
        generate_session(force, preset="small", seed=4, with_force=True, overwrite=True)
    prepared = prepare_session(force)
    for label, base in [("corotational", Trial("", 1.0)), ("stable neo-Hookean", Trial("", 1.0, law="stable_neo_hookean"))]:
        with executor(workers=2) as ex:
            t0 = time.perf_counter()
            fit = fit_youngs_modulus(prepared, base=base, executor=ex)
            dt = time.perf_counter() - t0
        iv = f"[{fit.interval[0]:.0f}, {fit.interval[1]:.0f}]" if fit.interval else "-"
        print(f"  fit ({label}, small session with force, truth 5000 Pa): {dt:.1f} s, "
              f"{fit.evaluations} sequence replays, E = {fit.youngs_modulus} Pa {iv} "
              f"(replay grid {fit.coarse_value:.0f} Pa)")


if __name__ == "__main__":
    main()
