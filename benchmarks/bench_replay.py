"""Replay speed: 60 s of 30 Hz kinematics on the paper's 13x5x5 grid and on 25x9x9,
beside two references measured in the same run.

- the compiled time loop (:mod:`core.simulation.stepper`, the default);
- the same algorithm stepped by the Python reference step (``SimulationConfig(compiled=False)``);
- a straightforward textbook solver (:mod:`benchmarks.reference_solver`: the sparse
  system assembled with the contact penalties and solved by ``spsolve`` every step,
  rotations by a batched SVD), on the first ``--reference-seconds`` of the path.

Prints wall time, steps per second, the speed-up over each reference and the largest
difference of the node positions from the textbook solver; asserts nothing (target of
issue 17: at least 5x the reference; the paper's SOFA replay took hours per minute).

    .venv/bin/python -m benchmarks.bench_replay [--session ../shared/sample-session]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from core.simulation import Material, ProbePath, SimulationConfig, build_model, box_mesh, simulate

SIZE = np.array([0.0687, 0.0393, 0.0358])  # the paper's phantom, m
MASS = 0.10401  # kg


def palpation_path(duration: float = 60.0, rate: float = 1000.0, seed: int = 0) -> ProbePath:
    """A minute of paper-like palpation at 1 kHz: pokes into the top with holds and slides, rests between."""
    rng = np.random.default_rng(seed)
    keys_t, keys_p = [0.0], [np.array([0.03, 0.02, SIZE[2] + 0.012])]
    t = 0.5
    while t < duration - 6.0:
        xy = rng.uniform([0.012, 0.01], [SIZE[0] - 0.012, SIZE[1] - 0.01])
        depth = rng.uniform(0.003, 0.009)
        above = np.array([*xy, SIZE[2] + 0.008])
        down = np.array([*xy, SIZE[2] + 0.005 - depth])
        slide = down + np.array([rng.uniform(-0.006, 0.006), rng.uniform(-0.004, 0.004), 0.0])
        for dt_, p in [(0.8, above), (1.2, down), (1.0, down), (1.2, slide), (1.0, slide), (0.8, above)]:
            t += dt_
            keys_t.append(t)
            keys_p.append(p)
        t += 0.5
    keys_t.append(duration)
    keys_p.append(keys_p[-1])
    ts = np.arange(0.0, duration, 1.0 / rate)
    kt, kp = np.array(keys_t), np.array(keys_p)
    return ProbePath(ts, np.stack([np.interp(ts, kt, kp[:, i]) for i in range(3)], axis=1))


def bench_grid(grid, path, frames, config, reference_seconds: float) -> None:
    from dataclasses import replace

    from benchmarks.reference_solver import simulate_reference

    mesh = box_mesh(SIZE, grid)
    t0 = time.perf_counter()
    model = build_model(mesh, MASS, Material(5000.0, 0.44), config)
    t_build = time.perf_counter() - t0
    simulate(model, ProbePath(path.t[:50], path.centres[:50]), 0.005, frames[:2])  # JIT warm-up (cached on disk)
    res = simulate(model, path, 0.005, frames)
    fast = res.steps / res.wall_time
    print(
        f"grid {grid[0]}x{grid[1]}x{grid[2]} ({mesh.n_nodes} nodes, {mesh.n_tets} tets): "
        f"{res.wall_time:.2f} s for {path.t[-1] - path.t[0]:.0f} s of interaction, "
        f"{res.steps} steps of {config.dt * 1e3:.2f} ms -> {fast:.0f} steps/s "
        f"(+{t_build:.2f} s model build), status {res.status}"
    )
    py = build_model(mesh, MASS, Material(5000.0, 0.44), replace(config, compiled=False))
    short = ProbePath(path.t[path.t <= reference_seconds], path.centres[path.t <= reference_seconds])
    f_short = frames[frames <= reference_seconds]
    r_py = simulate(py, short, 0.005, f_short)
    print(f"  Python reference step: {r_py.steps / r_py.wall_time:.0f} steps/s over {reference_seconds:g} s "
          f"-> compiled loop {fast / (r_py.steps / r_py.wall_time):.1f}x")
    pos, steps, wall = simulate_reference(model, short, 0.005, f_short)
    diff = float(np.nanmax(np.abs(pos - res.positions[: f_short.size])))
    print(f"  textbook solver (spsolve per step, SVD rotations): {steps / wall:.0f} steps/s over {reference_seconds:g} s "
          f"-> compiled loop {fast / (steps / wall):.1f}x; largest position difference {diff * 1e3:.3f} mm")


def bench_session(path: str) -> None:
    from core.simulation.replay import replay
    res = replay(path)
    frames = sum(s.frame_times.size for s in res.sequences.values())
    print(f"session {path}: {len(res.sequences)} sequences, {frames} frames; stage timings (s): "
          + ", ".join(f"{k} {v:.2f}" for k, v in res.timings.items()))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--session", default=None, help="also time the full pipeline on a session folder")
    parser.add_argument("--dt", type=float, default=SimulationConfig().dt)
    parser.add_argument("--reference-seconds", type=float, default=10.0,
                        help="length of the path the references replay, s (they are slow)")
    args = parser.parse_args()
    path = palpation_path()
    frames = np.arange(0.0, 60.0, 1.0 / 30.0)
    config = SimulationConfig(dt=args.dt)
    for grid in [(13, 5, 5), (25, 9, 9)]:
        bench_grid(grid, path, frames, config, args.reference_seconds)
    if args.session:
        bench_session(args.session)


if __name__ == "__main__":
    main()
