"""How each stage's cost grows with the length of the data (issue 17).

For every length (``--minutes``, default 1 2 4 8 minutes of probing in all) the virtual
lab writes a session of the ``small`` preset's four sequences (validation, test, two
train), each ``minutes * 60 / 4`` s long, with force columns and a hidden gravity (so E
is identifiable and the diagnosis has something to name). Each stage then runs as a user
runs it, through the ``tissuetwin`` command line in a fresh process:

- ``replay`` (calibrate, clean, cache, simulate, error; the cache is emptied first),
- ``fit`` (E with its interval; force columns),
- ``diagnose`` (``--segments N`` unless ``--segments 0``; every effect kind a candidate).

Per stage it prints the wall time, the peak memory of the whole process tree (the
command and its Dask workers, sampled every 0.2 s, so a short peak can be missed):
resident, proportional (a page mapped by several processes, such as the memory-mapped
cleaned clouds, counted once) and anonymous (the private heap; see :func:`tree_memory`), and, from the second length on, the growth exponent against the first length
(log time ratio / log length ratio: 1 is linear).

    .venv/bin/python -m benchmarks.bench_scaling [--minutes 1 2 4 8] [--stages replay fit diagnose]
        [--segments 8] [--workers 2] [--root DIR] [--preset small]
    .venv/bin/python -m benchmarks.bench_scaling --session PAPER_SESSION --root DIR
        (the stages on an existing session, e.g. `tissuetwin generate --preset paper`'s)

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


def _smaps_rollup(pid: int) -> dict[str, int]:
    """Rss, Pss and Anonymous bytes of one process from ``/proc/PID/smaps_rollup`` (Linux)."""
    out = {}
    with open(f"/proc/{pid}/smaps_rollup") as f:
        for line in f:
            key, _, rest = line.partition(":")
            if key in ("Rss", "Pss", "Anonymous"):
                out[key] = int(rest.split()[0]) * 1024
    return out


def tree_memory(proc: psutil.Process) -> tuple[dict[str, int], dict[str, int]]:
    """Memory in bytes of ``proc`` and, apart, of all its descendants (those gone count 0),
    each process read once.

    Returns ``(command, descendants)``, each ``{"rss": resident, "pss": proportional,
    "anon": anonymous}``. Resident counts every mapped page in every process that maps
    it, so the cleaned clouds a command and its Dask workers all memory-map (read-only
    page cache, dropped under pressure) are counted once per process; the proportional set
    size counts a shared page once in all; anonymous memory is the private heap that
    cannot be dropped without swap. Without ``smaps_rollup`` (not Linux) pss and anon
    equal rss.
    """
    parts = ({"rss": 0, "pss": 0, "anon": 0}, {"rss": 0, "pss": 0, "anon": 0})
    try:
        procs = [proc, *proc.children(recursive=True)]
    except psutil.Error:
        return parts
    for i, p in enumerate(procs):
        total = parts[min(i, 1)]
        try:
            rss = p.memory_info().rss
            try:
                roll = _smaps_rollup(p.pid)
            except OSError:
                roll = {}
            total["rss"] += rss
            total["pss"] += roll.get("Pss", rss)
            total["anon"] += roll.get("Anonymous", rss)
        except psutil.Error:
            pass
    return parts


def run_measured(cmd: list[str], env: dict, log: Path, series: Path | None = None) -> tuple[float, dict[str, int], int]:
    """Run ``cmd`` and sample its process tree's memory every 0.2 s (:func:`tree_memory`);
    with ``series``, every second's sample of the command itself and of its workers apart
    goes to that CSV (``t_s, main_rss, main_pss, main_anon, workers_rss, workers_pss,
    workers_anon``, bytes), to line up with the command's timestamped log.

    Returns:
        (wall time in s, peak bytes of the tree ``{"rss", "pss", "anon"}`` (each its own
        peak), exit code); the output goes to ``log``.
    """
    with open(log, "w") as out:
        t0 = time.perf_counter()
        popen = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, env=env)
        proc = psutil.Process(popen.pid)
        peak = {"rss": 0, "pss": 0, "anon": 0}
        stop = threading.Event()
        rows = open(series, "w") if series else None
        if rows:
            rows.write("t_s,main_rss,main_pss,main_anon,workers_rss,workers_pss,workers_anon\n")

        def sample():
            last = -1.0
            while not stop.is_set():
                main, workers = tree_memory(proc)
                for k in peak:
                    peak[k] = max(peak[k], main[k] + workers[k])
                now = time.perf_counter() - t0
                if rows and now - last >= 1.0:
                    last = now
                    rows.write(f"{now:.1f}," + ",".join(str(main[k]) for k in ("rss", "pss", "anon")) + ","
                               + ",".join(str(workers[k]) for k in ("rss", "pss", "anon")) + "\n")
                    rows.flush()
                stop.wait(0.2)

        th = threading.Thread(target=sample, daemon=True)
        th.start()
        code = popen.wait()
        stop.set()
        th.join()
        if rows:
            rows.close()
        return time.perf_counter() - t0, peak, code


def _gib(peak: dict[str, int]) -> str:
    return (f"peak resident {peak['rss'] / 2**30:.2f} GiB, proportional {peak['pss'] / 2**30:.2f} GiB, "
            f"anonymous {peak['anon'] / 2**30:.2f} GiB")


def _stage_command(stage: str, session: Path, out: Path, workers: int, segments: int) -> list[str]:
    if stage == "replay":
        return [*CLI, "replay", str(session), "--out", str(out)]
    cmd = [*CLI, stage, str(session), "--out", str(out), "--workers", str(workers)]
    if stage == "diagnose" and segments:
        cmd += ["--segments", str(segments)]
    return cmd


def measure_session(session: Path, root: Path, stages, workers: int, segments: int, keep_cache: bool = False) -> None:
    """Run ``stages`` on one existing session (``--session``: the paper preset's) and print
    wall time and peak memory of each (each stage's memory every second in
    ``root/<stage>-<session>.memory.csv``) (the preparation cache under ``root`` is emptied
    first, so the first stage pays for cleaning, unless ``keep_cache``)."""
    env = dict(os.environ, TISSUETWIN_CACHE_DIR=str(root / "cache"))
    if not keep_cache:
        shutil.rmtree(root / "cache", ignore_errors=True)
    print(f"session {session}; {workers} workers; diagnose --segments {segments}", flush=True)
    for stage in stages:
        out = root / f"{stage}-{session.name}"
        t, peak, code = run_measured(_stage_command(stage, session, out, workers, segments), env,
                                     root / f"{stage}-{session.name}.log", root / f"{stage}-{session.name}.memory.csv")
        print(f"{stage:8s} {t:7.1f} s, {_gib(peak)}, exit {code}", flush=True)


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
    ap.add_argument("--session", type=Path, help="measure the stages on this existing session instead "
                    "(e.g. one written by `tissuetwin generate --preset paper`)")
    ap.add_argument("--keep-cache", action="store_true", help="with --session: keep the preparation cache of an "
                    "earlier run under --root (the stages then read the cleaned clouds instead of cleaning)")
    args = ap.parse_args()

    root = args.root or Path(tempfile.mkdtemp(prefix="tt-scaling-"))
    root.mkdir(parents=True, exist_ok=True)
    if args.session:
        measure_session(args.session, root, args.stages, args.workers, args.segments, args.keep_cache)
        return
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
            print(f"{minutes:g} min: generated in {t:.0f} s ({_gib(peak)}), exit {code}", flush=True)
            if code:
                continue
        shutil.rmtree(root / "cache", ignore_errors=True)  # the first stage pays for cleaning
        for stage in args.stages:
            out = root / f"{stage}-{minutes:g}min"
            cmd = _stage_command(stage, session, out, args.workers, args.segments)
            t, peak, code = run_measured(cmd, env, root / f"{stage}-{minutes:g}.log")
            rows[stage].append((minutes, t, peak, code))
            print(f"{minutes:g} min: {stage:8s} {t:7.1f} s, {_gib(peak)}, exit {code}", flush=True)

    print("\nstage     minutes   wall s   resident GiB  proportional GiB  anonymous GiB   growth exponent vs the first length (1 = linear)")
    for stage, rs in rows.items():
        for m, t, peak, code in rs:
            m0, t0 = rs[0][0], rs[0][1]
            k = math.log(t / t0) / math.log(m / m0) if m != m0 and t0 > 0 else float("nan")
            flag = "" if code == 0 else f"  (exit {code})"
            print(f"{stage:9s} {m:7g} {t:8.1f} {peak['rss'] / 2**30:12.2f} {peak['pss'] / 2**30:17.2f} "
                  f"{peak['anon'] / 2**30:14.2f}   {k:5.2f}{flag}")


if __name__ == "__main__":
    main()
