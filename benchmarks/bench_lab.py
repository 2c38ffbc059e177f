"""Virtual-lab generation time per preset (prints; asserts nothing).

    .venv/bin/python -m benchmarks.bench_lab [--presets small demo] [--out /tmp/bench-lab]
"""

from __future__ import annotations

import argparse
import shutil
import time
from pathlib import Path

from core.io import read_session


def main() -> None:
    from core.lab import generate_session

    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--presets", nargs="*", default=["small", "demo"])
    parser.add_argument("--out", default="/tmp/tissuetwin-bench-lab")
    args = parser.parse_args()
    for preset in args.presets:
        out = Path(args.out) / preset
        shutil.rmtree(out, ignore_errors=True)
        t0 = time.perf_counter()
        generate_session(out, preset=preset, seed=0)
        seconds = time.perf_counter() - t0
        s = read_session(out)
        frames = sum(len(q) for q in s.sequences.values())
        first = next(iter(s.sequences.values()))
        points = sum(len(first.cloud(i)) for i in range(0, len(first), 10)) / len(range(0, len(first), 10))
        size = sum(f.stat().st_size for f in out.rglob("*") if f.is_file()) / 1e6
        print(f"{preset}: {seconds:.1f} s, {len(s.sequences)} sequences, {frames} frames, "
              f"~{points:.0f} raw points per frame, {size:.0f} MB")


if __name__ == "__main__":
    main()
