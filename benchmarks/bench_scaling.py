"""How each stage's cost grows with the length of the data (issue 17).

For every length (``--minutes``, default 1 2 4 8 minutes of probing in all) the virtual
lab writes a session of the ``small`` preset's four sequences (validation, test, two
train), each ``minutes * 60 / 4`` s long, with force columns and a hidden gravity (so E
is identifiable and the diagnosis has something to name). Each stage then runs as a user
runs it, through the ``tissuetwin`` command line in a fresh process:

- ``replay`` (calibrate, clean, cache, simulate, error; the cache is emptied first),
- ``fit`` (E with its interval; force columns),
- ``diagnose`` (``--segments N`` unless ``--segments 0``; every effect kind a candidate).

Per stage it prints the wall time, the peak resident memory of the whole process tree
(the command and its Dask workers, sampled every 0.2 s with psutil, so a short peak can
be missed) and, from the second length on, the growth exponent against the first length
(log time ratio / log length ratio: 1 is linear).

    .venv/bin/python -m benchmarks.bench_scaling [--minutes 1 2 4 8] [--stages replay fit diagnose]
        [--segments 8] [--workers 2] [--root DIR] [--preset small]

Sessions are kept (and reused) under ``--root``. Asserts nothing.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import psutil

CLI = [sys.executable, "-m", "app.cli"]


def tree_rss(proc: psutil.Process) -> int:
    """Resident memory in bytes of ``proc`` and all its descendants (0 for those gone)."""
    total = 0
    try:
        procs = [proc, *proc.children(recursive=True)]
    except psutil.Error:
        return 0
    for p in procs:
        try:
            total += p.memory_info().rss
        except psutil.Error:
            pass
    return total


def run_measured(cmd: list[str], env: dict, log: Path) -> tuple[float, int, int]:
    """Run ``cmd`` and sample its process tree's resident memory.

    Returns:
        (wall time in s, peak resident bytes of the tree, exit code); the output goes to ``log``.
    """
    with open(log, "w") as out:
        t0 = time.perf_counter()
        popen = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, env=env)
        proc = psutil.Process(popen.pid)
        peak = [0]
        stop = threading.Event()

        def sample():
            while not stop.is_set():
                peak[0] = max(peak[0], tree_rss(proc))
                stop.wait(0.2)

        th = threading.Thread(target=sample, daemon=True)
        th.start()
        code = popen.wait()
        stop.set()
        th.join()
        return time.perf_counter() - t0, peak[0], code


def main() -> None:
    """Generate (or reuse) each length's session, run the stages and print the table."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, nargs="+", default=[1.0, 2.0, 4.0, 8.0])
    ap.add_argument("--stages", nargs="+", default=["replay", "fit", "diagnose"], choices=("replay", "fit", "diagnose"))
    ap.add_argument("--segments", type=int, default=8, help="diagnose --segments N (0: whole sequences)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--preset", default="small")
    ap.add_argument("--root", type=Path, help="keep (and reuse) sessions and outputs here")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    root = args.root or Path(tempfile.mkdtemp(prefix="tt-scaling-"))
    root.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, TISSUETWIN_CACHE_DIR=str(root / "cache"))
    gravity = json.dumps([{"kind": "gravity", "g": [0.0, 0.0, -9.81]}])
    rows: dict[str, list[tuple[float, float, int, int]]] = {s: [] for s in args.stages}
    print(f"preset {args.preset}, 4 sequences, hidden gravity, force columns; {args.workers} workers; "
          f"diagnose --segments {args.segments}", flush=True)
    for minutes in args.minutes:
        seq_s = minutes * 60.0 / 4.0
        session = root / f"{args.preset}-{minutes:g}min"
        if not (session / "truth.json").exists():
            t, peak, code = run_measured([*CLI, "generate", "--preset", args.preset, "--duration", f"{seq_s:g}",
                                          "--seed", str(args.seed), "--force", "--effects", gravity, "--overwrite",
                                          "--out", str(session)], env, root / f"generate-{minutes:g}.log")
            print(f"{minutes:g} min: generated in {t:.0f} s (peak {peak / 2**30:.2f} GiB), exit {code}", flush=True)
            if code:
                continue
        shutil.rmtree(root / "cache", ignore_errors=True)  # the first stage pays for cleaning
        for stage in args.stages:
            out = root / f"{stage}-{minutes:g}min"
            cmd = [*CLI, stage, str(session), "--out", str(out), "--workers", str(args.workers)]
            if stage == "replay":
                cmd = [*CLI, "replay", str(session), "--out", str(out)]
            if stage == "diagnose" and args.segments:
                cmd += ["--segments", str(args.segments)]
            t, peak, code = run_measured(cmd, env, root / f"{stage}-{minutes:g}.log")
            rows[stage].append((minutes, t, peak, code))
            print(f"{minutes:g} min: {stage:8s} {t:7.1f} s, peak {peak / 2**30:.2f} GiB, exit {code}", flush=True)

    print("\nstage     minutes   wall s   peak GiB   growth exponent vs the first length (1 = linear)")
    for stage, rs in rows.items():
        for m, t, peak, code in rs:
            m0, t0 = rs[0][0], rs[0][1]
            k = math.log(t / t0) / math.log(m / m0) if m != m0 and t0 > 0 else float("nan")
            flag = "" if code == 0 else f"  (exit {code})"
            print(f"{stage:9s} {m:7g} {t:8.1f} {peak / 2**30:10.2f}   {k:5.2f}{flag}")


if __name__ == "__main__":
    main()
