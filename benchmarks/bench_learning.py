"""Learned correction (Wu et al. 2020, Sec. 3.3, Table 3): CPU training and inference
speed at the paper's size, and a Table 3 reproduction on a virtual-lab session.

Prints its measurements; asserts nothing.

1. Training time per epoch at the paper's size: 15872 samples (the paper's 9 min of
   train video) on the 13x5x5 grid with the paper's widths 64/128/256, from synthetic
   inputs of that size (random deformations, 1024 cloud points per frame). A fixed
   number of Adam steps is timed and scaled to a full epoch (said in the output).
2. Inference time per frame: in-loop (one frame per call, as the replay's frame hook
   does) and offline (batches of 256 frames).
3. Table 3: ``evaluate`` on a generated session (identified E, a too-stiff E, 10 Pa;
   2D and 3D networks).

    .venv/bin/python -m benchmarks.bench_learning [--steps 20] [--table3 demo|paper|none]
        [--widths 64 128 256] [--effects '[{"kind": "gravity"}]'] [--identified E]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

SIZE = np.array([0.0687, 0.0393, 0.0358])  # the paper's phantom, m
GRID = (13, 5, 5)
PAPER_SAMPLES = 15872  # "9 min of the captured video samples, or 15872 samples"


def _synthetic(n_frames: int, points: int, seed: int = 0):
    """Random but plausible inputs: rest mesh plus 1 mm noise, poses over the top, clouds
    on the top face; float32 straight away (the paper-size set is ~200 MB)."""
    import torch

    from core.simulation.mesh import box_mesh

    rng = np.random.default_rng(seed)
    rest = box_mesh(SIZE, GRID).nodes.astype(np.float32)
    pos = rest[None] + rng.normal(scale=1e-3, size=(n_frames, rest.shape[0], 3)).astype(np.float32)
    q = rng.normal(size=(n_frames, 4)).astype(np.float32)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    poses = np.concatenate([rng.uniform([0, 0, SIZE[2]], [SIZE[0], SIZE[1], SIZE[2] + 0.01], (n_frames, 3)).astype(np.float32), q], 1)
    pts = rng.uniform([0, 0, SIZE[2] - 0.002], [SIZE[0], SIZE[1], SIZE[2] + 0.002], (n_frames, points, 3)).astype(np.float32)
    return torch.from_numpy(pos), torch.from_numpy(poses), torch.from_numpy(pts)


def bench_training(widths, steps: int, batch: int, threads: int) -> dict:
    """Seconds per Adam step (and per paper-size epoch, scaled) for both networks."""
    import torch

    from core.learning import NetworkConfig, build_network, chamfer_loss
    from core.learning.train import _LossModel

    torch.set_num_threads(threads)
    pos, poses, pts = _synthetic(batch * (steps + 2), 1024)
    mask = torch.ones(pts.shape[:2], dtype=torch.bool)
    lm = _LossModel(GRID, 3)
    out = {}
    for kind in ("2d", "3d"):
        torch.manual_seed(0)
        net = build_network(NetworkConfig(kind=kind, widths=tuple(widths)), GRID, SIZE)
        opt = torch.optim.Adam(net.parameters(), lr=1e-3)
        times = []
        for s in range(steps + 2):
            sl = slice(s * batch, (s + 1) * batch)
            t0 = time.perf_counter()
            loss = chamfer_loss(pts[sl], mask[sl], lm.surface(pos[sl], net(pos[sl], poses[sl])))
            opt.zero_grad()
            loss.backward()
            opt.step()
            times.append(time.perf_counter() - t0)
        per_step = float(np.median(times[2:]))  # two warm-up steps
        out[kind] = {
            "parameters": int(sum(p.numel() for p in net.parameters())),
            "seconds_per_step": per_step,
            "seconds_per_epoch_scaled": per_step * PAPER_SAMPLES / batch,
            "batch": batch,
            "steps_timed": steps,
        }
        print(f"  {kind.upper()} UNet {tuple(widths)}: {out[kind]['parameters']:,} parameters; "
              f"{per_step * 1e3:.0f} ms per step of {batch} frames -> {out[kind]['seconds_per_epoch_scaled'] / 60:.1f} min "
              f"per epoch of {PAPER_SAMPLES} samples (scaled from {steps} timed steps)")
    return out


def bench_inference(widths, threads: int, frames: int = 512) -> dict:
    """Seconds per frame: one frame per call (in-loop) and batches of 256 (offline)."""
    import torch

    from core.learning import NetworkConfig, build_network
    from core.learning.apply import _field

    torch.set_num_threads(threads)
    pos, poses, _ = _synthetic(frames, 1)
    pos64, poses64 = pos.double().numpy(), poses.double().numpy()
    out = {}
    for kind in ("2d", "3d"):
        torch.manual_seed(0)
        net = build_network(NetworkConfig(kind=kind, widths=tuple(widths)), GRID, SIZE).eval()
        n_loop = 100
        with torch.no_grad():
            net(pos[:1], poses[:1])
            t0 = time.perf_counter()
            for j in range(n_loop):  # what the frame hook does: numpy -> tensor -> numpy
                net(torch.tensor(pos64[j : j + 1], dtype=torch.float32), torch.tensor(poses64[j : j + 1], dtype=torch.float32)).double().numpy()
            in_loop = (time.perf_counter() - t0) / n_loop
        t0 = time.perf_counter()
        _field(net, pos64, poses64, batch=256)
        offline = (time.perf_counter() - t0) / frames
        out[kind] = {"in_loop_seconds_per_frame": in_loop, "offline_seconds_per_frame": offline}
        print(f"  {kind.upper()}: in-loop {in_loop * 1e3:.2f} ms per frame, offline {offline * 1e3:.3f} ms per frame")
    return out


def bench_table3(preset: str, out: Path, widths, effects, identified, epochs: int, threads: int, seed: int) -> dict:
    """Generate (once) a session of ``preset`` and run the Table 3 evaluation on it."""
    from core.identification import Trial, fit_youngs_modulus
    from core.lab import generate_session
    from core.learning import NetworkConfig, TrainConfig, evaluate_networks, write_evaluation
    from core.simulation.replay import ReplayConfig, prepare_session

    session = out / f"{preset}-session"
    t0 = time.perf_counter()
    if not (session / "session.json").exists():
        generate_session(session, preset=preset, seed=seed, effects=effects, overwrite=True)
    t_gen = time.perf_counter() - t0
    t0 = time.perf_counter()
    prepared = prepare_session(session, ReplayConfig())
    t_prep = time.perf_counter() - t0
    t0 = time.perf_counter()
    if identified is None:
        fit = fit_youngs_modulus(prepared, base=Trial(sequence="", youngs_modulus=1.0), refine_mesh=False)
        E = float(fit.coarse_value)
        ident = {"method": "fit_youngs_modulus, replay grid", "youngs_modulus": E, "identifiable": fit.identifiable,
                 "reason": fit.reason}
    else:
        E = float(identified)
        ident = {"method": "given", "youngs_modulus": E}
    t_fit = time.perf_counter() - t0
    print(f"  session {session} ({t_gen:.0f} s to generate, {t_prep:.0f} s to prepare); identified E = {E:.4g} Pa "
          f"({t_fit:.0f} s)")
    values = [("identified", E), ("too stiff", 2.0 * E), ("10 Pa", 10.0)]
    result = evaluate_networks(
        prepared, values, ReplayConfig(), network_config=NetworkConfig(widths=tuple(widths)),
        train_config=TrainConfig(max_epochs=epochs, patience=3, threads=threads, seed=0), identification=ident,
    )
    write_evaluation(result, out / f"table3-{preset}")
    print(result.to_markdown())
    for (label, kind), rep in result.reports.items():
        tr = rep.training
        print(f"  {label} {kind}: {len(tr.history)} epochs (best {tr.best_epoch}), {tr.timings['per_epoch']:.1f} s per epoch "
              f"on {tr.n_frames['train']} frames")
    return {"session": str(session), "generate_seconds": t_gen, "identification": ident,
            "evaluation": str(out / f"table3-{preset}"), "total_seconds": result.timings["total"]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=20, help="Adam steps timed per network (default 20)")
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--widths", type=int, nargs=3, default=(64, 128, 256), help="widths of the timing runs (paper's)")
    ap.add_argument("--table3", choices=("demo", "paper", "small", "none"), default="demo",
                    help="preset of the Table 3 session (paper: about an hour to generate; default demo)")
    ap.add_argument("--table3-widths", type=int, nargs=3, default=(64, 128, 256))
    ap.add_argument("--table3-epochs", type=int, default=20)
    ap.add_argument("--effects", default='[{"kind": "gravity"}]',
                    help="truth effects of the generated session (JSON; default gravity, which the base model lacks)")
    ap.add_argument("--identified", type=float, default=None, help="skip the fit and use this E, Pa")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="data/bench-learning")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = {}
    print(f"training speed, paper size (13x5x5 grid, widths {tuple(args.widths)}, {args.threads} threads):")
    results["training"] = bench_training(args.widths, args.steps, args.batch, args.threads)
    print("inference speed:")
    results["inference"] = bench_inference(args.widths, args.threads)
    if args.table3 != "none":
        print(f"Table 3 on a '{args.table3}' session (widths {tuple(args.table3_widths)}):")
        results["table3"] = bench_table3(args.table3, out, args.table3_widths, json.loads(args.effects), args.identified,
                                         args.table3_epochs, args.threads, args.seed)
    (out / "bench_learning.json").write_text(json.dumps(results, indent=2))
    print(f"wrote {out}/bench_learning.json")
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
