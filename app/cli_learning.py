"""``tissuetwin train`` and ``tissuetwin evaluate``: the learned correction (Wu et al. 2020,
Sec. 3.3 and Table 3) from the command line.

torch and the FEM are imported inside the commands so that ``tissuetwin --help`` stays fast.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from core.errors import TissueTwinError


def _network_config(args, kind: str):
    from core.learning import NetworkConfig

    return NetworkConfig(kind=kind, widths=tuple(args.widths), pose=args.pose)


def _train_config(args):
    from core.learning import TrainConfig

    return TrainConfig(
        max_epochs=args.epochs, patience=args.patience, batch_size=args.batch_size, learning_rate=args.lr,
        max_points=args.max_points, seed=args.seed, threads=args.threads,
    )


def _prepare(args):
    from app.cli import _progress
    from core.io import read_session
    from core.preparation import prepare_session
    from core.simulation.replay import ReplayConfig
    session = read_session(args.session)
    names = tuple(args.sequences) if args.sequences else None
    with _progress("calibrating and cleaning") as cb:
        prepared = prepare_session(session, ReplayConfig(grid=tuple(args.grid), sequences=names), callback=cb)
    roles = {s.role for s in prepared.sequences.values()}
    missing = {"train", "validation", "test"} - roles
    if missing:
        raise TissueTwinError(f"{Path(args.session) / 'session.json'}: the learned correction needs train, validation "
                              f"and test sequences; missing role(s) {sorted(missing)}")
    return session, prepared


def _mm(v) -> str:
    return "N/A" if v is None or not math.isfinite(v) else f"{v * 1e3:.4f}"


def _smm(v) -> str:
    return "N/A" if v is None or not math.isfinite(v) else f"{v * 1e3:+.3f}"


def _pct(v) -> str:
    return "N/A" if v is None or not math.isfinite(v) else f"{v * 100:.1f}%"


def cmd_train(args) -> int:
    from rich.console import Console
    from rich.table import Table

    from app.cli import _progress, _replay_config
    from core.learning import save_checkpoint, train_and_test

    session, prepared = _prepare(args)
    config = _replay_config(args)
    out = Path(args.out)
    with _progress(f"{args.model} network at E = {config.youngs_modulus:g} Pa") as cb:
        report = train_and_test(prepared, config, _network_config(args, args.model), _train_config(args),
                                session=session, callback=cb)
    out.mkdir(parents=True, exist_ok=True)
    ck_path = save_checkpoint(out / "checkpoint.pt", report.checkpoint.network, session=prepared.path,
                              replay_config=config, extra={"train": report.training.to_json()})
    traj = out / "trajectories"
    traj.mkdir(exist_ok=True)
    for name in report.in_loop:
        report.in_loop[name].save(traj / f"{name}_in_loop.npz")
        report.offline[name].save(traj / f"{name}_offline.npz")
    data = report.to_json()
    data["checkpoint"] = str(ck_path)
    (out / "train.json").write_text(json.dumps(data, indent=2))

    table = Table(title=f"{args.session}: {args.model.upper()} network, E = {config.youngs_modulus:g} Pa "
                        f"(mean distance cloud -> mesh, mm; cf. Wu et al. 2020 Table 3)")
    for col in ("sequence", "no network", "in-loop", "improvement", "offline", "improvement "):
        table.add_column(col, justify="left" if col == "sequence" else "right")
    signed = Table(title="signed: mean vertical residual over the top face's interior, measured minus mesh, mm "
                         "(negative: the mesh sits too high, which the unsigned error rewards)")
    for col in ("sequence", "no network", "in-loop", "offline"):
        signed.add_column(col, justify="left" if col == "sequence" else "right")
    for name, s in data["sequences"].items():
        table.add_row(name, _mm(s["no_network"]), _mm(s["corrected"]), _pct(_gain(s["no_network"], s["corrected"])),
                      _mm(s["corrected_offline"]), _pct(_gain(s["no_network"], s["corrected_offline"])))
        sg = s["signed_residual"]
        signed.add_row(name, _smm(sg["no_network"]), _smm(sg["corrected"]), _smm(sg["corrected_offline"]))
    te, ts = data["test_error"], data["test_signed_residual"]
    table.add_row("all test", _mm(te["no_network"]), _mm(te["corrected"]), _pct(data["improvement"]),
                  _mm(te["corrected_offline"]), _pct(data["improvement_offline"]))
    signed.add_row("all test", _smm(ts["no_network"]), _smm(ts["corrected"]), _smm(ts["corrected_offline"]))
    console = Console()
    console.print(table)
    console.print(signed)
    console.print(f"in the loop the nodes the network does not set stayed within {_mm(data['max_unobserved_offset'])} mm "
                  "of the plain replay")
    console.print(f"best epoch {data['best_epoch']} of {len(data['losses'])}; "
                  f"{data['timings']['per_epoch']:.2f} s per epoch on {data['frames']['train']} train frames")
    print(f"wrote {out}/train.json, {ck_path.name} and trajectories/")
    return 0


def _gain(before, after):
    if before is None or after is None or not before:
        return float("nan")
    return 1.0 - after / before


def cmd_evaluate(args) -> int:
    from app.cli import _base_trial, _progress, _replay_config
    from core.learning import evaluate_networks, write_evaluation

    session, prepared = _prepare(args)
    if args.identified is not None:
        E_id = float(args.identified)
        identification = {"method": "given (--identified)", "youngs_modulus": E_id}
    else:
        from core.identification import fit_youngs_modulus

        with _progress("identifying E on the train sequences") as cb:
            fit = fit_youngs_modulus(prepared, base=_base_trial(args), refine_mesh=False,
                                     progress=lambda n, msg: cb(min(n / 25.0, 0.99), msg))
        E_id = float(fit.coarse_value)
        identification = {"method": "fit_youngs_modulus on the replay grid (core.identification)",
                          "youngs_modulus": E_id, "identifiable": fit.identifiable, "reason": fit.reason,
                          "interval": list(fit.interval) if fit.interval else None}
        print(f"identified E = {E_id:.4g} Pa on the {'x'.join(map(str, args.grid))} grid"
              + ("" if fit.identifiable else f" (not identifiable: {fit.reason}; using the argmin)"))
    values = [("identified", E_id), ("too stiff", E_id * args.stiff_factor), ("10 Pa", 10.0)]
    args.youngs = E_id
    base = _replay_config(args)
    kinds = tuple(args.models)
    with _progress("Table 3: training and testing") as cb:
        result = evaluate_networks(prepared, values, base, kinds=kinds, network_config=_network_config(args, kinds[0]),
                                   train_config=_train_config(args), identification=identification, session=session,
                                   callback=cb)
    out = write_evaluation(result, args.out)
    print(result.to_markdown())
    print(f"wrote {out}/evaluation.json and {out}/evaluation.md")
    return 0


def _add_training_options(p) -> None:
    p.add_argument("--epochs", type=int, default=40, help="maximum epochs (default 40; early stopping on validation)")
    p.add_argument("--patience", type=int, default=5, help="epochs without a better validation loss before stopping (default 5)")
    p.add_argument("--batch-size", type=int, default=16, help="frames per Adam step (default 16)")
    p.add_argument("--lr", type=float, default=1e-3, help="Adam learning rate (default 1e-3)")
    p.add_argument("--max-points", type=int, default=1024, help="measured points per frame in the loss (default 1024)")
    p.add_argument("--widths", type=int, nargs=3, default=(64, 128, 256), metavar=("W1", "W2", "W3"),
                   help="features of the 3 encoder blocks (default: the paper's 64 128 256)")
    p.add_argument("--pose", choices=("position_quaternion", "position"), default="position_quaternion",
                   help="robot pose fed at the bottleneck (default: probe centre and tool quaternion)")
    p.add_argument("--seed", type=int, default=0, help="seed of initialisation, batches and point subsets (default 0)")
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")


def register(subparsers) -> None:
    """Add the ``train`` and ``evaluate`` subcommands to ``tissuetwin``'s subparsers."""
    from app.cli import _add_model_options

    p = subparsers.add_parser("train", help="train the 2D or 3D correction network and test it (Wu et al. 2020, Sec. 3.3)")
    p.add_argument("session")
    p.add_argument("--model", choices=("2d", "3d"), required=True, help="2D UNet on the top layer or 3D UNet on the grid")
    p.add_argument("--out", required=True, help="folder for train.json, checkpoint.pt and trajectories/")
    _add_model_options(p)
    _add_training_options(p)
    p.set_defaults(func=cmd_train)

    p = subparsers.add_parser("evaluate", help="Table 3: both networks at the identified E, a too-stiff E and 10 Pa")
    p.add_argument("session")
    p.add_argument("--out", required=True, help="folder for evaluation.json and evaluation.md")
    p.add_argument("--identified", type=float, default=None,
                   help="use this E (Pa) as the identified value instead of fitting it")
    p.add_argument("--stiff-factor", type=float, default=2.0,
                   help="too-stiff E = factor x identified E (default 2, the paper's 1e4 vs 5e3 Pa)")
    p.add_argument("--models", nargs="+", choices=("2d", "3d"), default=("2d", "3d"), help="networks (default both)")
    _add_model_options(p, youngs=False)
    _add_training_options(p)
    p.set_defaults(func=cmd_evaluate)
