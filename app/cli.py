"""``tissuetwin`` command line: generate, replay and the demo.

Heavy modules (open3d, numba kernels, torch) are imported inside the commands so that
``tissuetwin --help`` starts fast. Domain errors print one clear line and exit 2.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from contextlib import contextmanager
from pathlib import Path

from core.errors import TissueTwinError

DEFAULT_DATA = Path(os.environ.get("TISSUETWIN_DATA", "data"))


class _LogLines:
    """Progress for a log file or pipe (no terminal, where a rich bar shows nothing until
    it ends): one timestamped line when the stage changes (the message with its numbers
    left out), another tenth of the work is done, or 30 s passed, so a long run's log says
    where its time goes without a line per frame."""

    def __init__(self, description: str, every: float = 30.0):
        import re
        import time

        self.description, self.time, self.every = description, time.perf_counter, every
        self.t0 = self.last_t = self.time()
        self.digits = re.compile(r"[0-9.]+")
        self.last = (None, -1)

    def __call__(self, fraction: float | None, message: str = "") -> None:
        tenth = -1 if fraction is None else int(min(max(fraction, 0.0), 1.0) * 10)
        stage = self.digits.sub("#", message)
        now = self.time()
        if stage == self.last[0] and tenth <= self.last[1] and now - self.last_t < self.every:
            return
        self.last, self.last_t = (stage, max(tenth, self.last[1] if stage == self.last[0] else -1)), now
        done = "" if fraction is None else f" {min(max(fraction, 0.0), 1.0):4.0%}"
        print(f"[{now - self.t0:8.1f} s] {self.description}{done} {message}".rstrip(), file=sys.stderr, flush=True)


@contextmanager
def _progress(description: str):
    """Yield a ``callback(fraction, message)`` that drives a rich progress bar (timestamped
    lines when stderr is not a terminal: :class:`_LogLines`)."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    if not sys.stderr.isatty():
        lines = _LogLines(description)
        yield lines
        lines(1.0, "done")
        return
    with Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        TextColumn("{task.percentage:>3.0f}%"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        TextColumn("{task.fields[msg]}"),
        transient=False,
    ) as progress:
        task = progress.add_task(description, total=1.0, msg="")

        def callback(fraction: float, message: str = "") -> None:
            progress.update(task, completed=min(max(fraction, 0.0), 1.0), msg=message)

        yield callback
        progress.update(task, completed=1.0)


def _parse_effects(text: str | None) -> list[dict]:
    if not text:
        return []
    try:
        value = json.loads(text)
    except json.JSONDecodeError as exc:
        raise TissueTwinError(f"--effects must be a JSON list of objects: {exc}") from exc
    if isinstance(value, dict):
        value = [value]
    if not isinstance(value, list) or not all(isinstance(v, dict) for v in value):
        raise TissueTwinError("--effects must be a JSON list of objects like [{\"kind\": \"gravity\"}]")
    return value


def _preset_names() -> tuple[str, ...]:
    from core.lab.generate import PRESETS

    return tuple(PRESETS)


def _plan_path(plan: str):
    """(t, centres) of a plan's probe path in the phantom frame (plan.json ``path_phantom``)."""
    import json

    import numpy as np

    p = Path(plan)
    p = p / "plan.json" if p.is_dir() else p
    try:
        data = json.loads(p.read_text())
        t = np.asarray(data["path_phantom"]["t"], dtype=np.float64)
        c = np.asarray(data["path_phantom"]["centres"], dtype=np.float64)
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise TissueTwinError(f"{p}: not a plan.json with a path_phantom ({exc})") from exc
    return t, c


def cmd_generate(args) -> int:

    from core.lab import generate_session
    from core.lab.generate import PRESETS

    effects = _parse_effects(args.effects)
    preset = PRESETS[args.preset]
    if args.duration is not None:
        preset = preset.with_duration(args.duration)
    paths = None
    if args.plan:
        paths = [_plan_path(args.plan)] * len(preset.sequence_roles)
    shape = "stl" if args.phantom_stl else args.shape
    with _progress(f"generating {args.preset} session ({shape} phantom)") as cb:
        path = generate_session(
            args.out, preset=preset, seed=args.seed, effects=effects, with_force=args.force,
            overwrite=args.overwrite, callback=cb, paths=paths, shape=args.shape, phantom_stl=args.phantom_stl,
        )
    print(f"session written to {path}")
    return 0


def _replay_config(args):
    from core.simulation import SimulationConfig, effect_from_dict
    from core.simulation.replay import ReplayConfig
    sim = SimulationConfig(dt=args.dt) if getattr(args, "dt", None) else SimulationConfig()
    effects = tuple(effect_from_dict(e) for e in _parse_effects(getattr(args, "effects", None)))
    return ReplayConfig(
        youngs_modulus=args.youngs,
        poisson_ratio=args.poisson,
        grid=tuple(args.grid),
        element_size=getattr(args, "element_size", None),
        simulation=sim,
        effects=effects,
        sequences=tuple(args.sequences) if args.sequences else None,
    )


def _print_replay(result, title: str) -> None:
    from rich.console import Console
    from rich.table import Table

    console = Console()
    table = Table(title=title)
    for col in ("sequence", "role", "frames", "status", "mean error (mm)", "sim time (s)"):
        table.add_column(col, justify="right" if col not in ("sequence", "role", "status") else "left")
    for name, s in result.sequences.items():
        err = f"{s.mean_error * 1e3:.3f}" if s.status == "ok" else "N/A"
        table.add_row(name, s.role, str(s.frame_times.size), s.status, err, f"{s.simulation.wall_time:.2f}")
    console.print(table)
    cal = result.calibration
    console.print(
        f"calibration: robot RMS {cal.robot_rms * 1e3:.2f} mm, camera ICP RMS {cal.camera_rms * 1e3:.2f} mm "
        f"(fitness {cal.camera_fitness:.2f})"
    )
    console.print(f"noise floor (rest frames to rest mesh): {result.noise_floor * 1e3:.3f} mm")
    console.print("timings (s): " + ", ".join(f"{k} {v:.2f}" for k, v in result.timings.items()))


def _run_replay(session: Path, out: Path, config, title: str):
    from core.simulation.replay import replay, write_replay
    with _progress(f"replaying {session.name}") as cb:
        result = replay(session, config, callback=cb)
    write_replay(result, out)
    _print_replay(result, title)
    print(f"results written to {out}/replay.json")
    return result


def cmd_replay(args) -> int:
    config = _replay_config(args)
    _run_replay(Path(args.session), Path(args.out), config, f"{args.session}  (E = {config.youngs_modulus:g} Pa)")
    return 0


def _demo_session_current(session: Path) -> bool:
    """Whether ``session`` is the demo session this release makes: its truth.json hides
    :data:`core.lab.DEMO_EFFECTS` and it has force columns (an older demo held no effect)."""
    from core.lab import DEMO_EFFECTS, complete_effects

    try:
        truth = json.loads((session / "truth.json").read_text())
        header = next((session / "sequences").glob("*/kinematics.csv")).open().readline()
    except (OSError, ValueError, StopIteration):
        return False
    return truth.get("effects") == complete_effects(DEMO_EFFECTS) and "fx" in header.split(",")


def cmd_demo(args) -> int:
    """Generate the demo session if absent (or made by an older release), replay the shared
    sample session; then, unless ``--no-serve``, open the workbench on them: the demo
    session's replay runs as the workbench's first job (the session is replayed and
    cleaned once), then the demo's analyses (``app.cli_serve.demo_analyses``: sweep,
    train, fit, diagnose) one after another. With ``--no-serve`` the demo session is
    replayed here instead.

    The demo session (``demo`` preset, seed 0, force columns) hides
    :data:`core.lab.DEMO_EFFECTS`: gravity and a robot calibration offset, which the
    demo's diagnosis names."""
    from core.io import read_session
    from core.lab import DEMO_EFFECTS, generate_session

    data = Path(args.data)
    session = data / "demo-session"
    if not _demo_session_current(session):
        what = ("regenerating the demo session (it was made without the demo's hidden effects)"
                if (session / "session.json").exists() else "generating the demo session (once)")
        with _progress(what) as cb:
            generate_session(session, preset="demo", seed=0, effects=list(DEMO_EFFECTS), with_force=True,
                             callback=cb, overwrite=True)
    else:
        read_session(session)  # validates what is there
    config = _replay_config(args)
    sample = Path(args.sample) if args.sample else None
    has_sample = sample is not None and (sample / "session.json").exists()
    if args.no_serve:
        _run_replay(session, data / "runs" / "demo-replay", config, f"demo session (E = {config.youngs_modulus:g} Pa)")
    if has_sample:
        _run_replay(sample, data / "runs" / "sample-replay", config, f"{sample} (E = {config.youngs_modulus:g} Pa)")
    if args.no_serve:
        return 0
    from app.cli_serve import serve_demo

    print("the demo session hides " + " and ".join(e["kind"] for e in DEMO_EFFECTS)
          + " (force columns recorded); the workbench replays it as its first job, then sweeps, trains, fits and "
            "diagnoses it", flush=True)
    params = {"youngs_modulus": args.youngs, "poisson_ratio": args.poisson, "grid": list(args.grid),
              "effects": _parse_effects(args.effects), "sequences": args.sequences or None}
    sessions = [(session, "demo-session")] + ([(sample, "sample-session")] if has_sample else [])
    return serve_demo(data, sessions, params, host=args.host, port=args.port)


@contextmanager
def _trial_progress(description: str):
    """A rich progress bar counting trials done: yields ``progress(done, total)``
    (timestamped lines when stderr is not a terminal: :class:`_LogLines`)."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    if not sys.stderr.isatty():
        lines = _LogLines(description)

        def progress(done: int, total) -> None:
            lines(None, f"{done}/{total}" if isinstance(total, int) else f"{done} {total or ''}")

        yield progress
        return
    with Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn()) as bar:
        task = bar.add_task(description, total=None)

        def progress(done: int, total) -> None:
            bar.update(task, completed=done, total=total if isinstance(total, int) else done)

        yield progress


def _base_trial(args):
    from core.identification import Trial
    from core.simulation import SimulationConfig, effect_from_dict

    effects = tuple(effect_from_dict(e).to_dict() for e in _parse_effects(getattr(args, "effects", None)))
    sim = SimulationConfig(dt=args.dt) if getattr(args, "dt", None) else SimulationConfig()
    return Trial(sequence="", youngs_modulus=1.0, poisson_ratio=args.poisson, grid=tuple(args.grid), effects=effects,
                 simulation=sim, element_size=getattr(args, "element_size", None))


def _parse_youngs(text: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError as exc:
        raise TissueTwinError(f"--youngs must be comma-separated numbers in Pa, got {text!r}") from exc
    if not values or any(v <= 0 for v in values):
        raise TissueTwinError(f"--youngs must be positive values in Pa, got {text!r}")
    return values


def cmd_precompile(args) -> int:
    from core.simulation.precompile import compile_kernels

    print(f"simulation kernels compiled and cached in {compile_kernels():.1f} s")
    return 0


def cmd_sweep(args) -> int:
    from rich.console import Console
    from rich.table import Table

    from core.identification import executor, sweep, write_sweep
    from core.preparation import prepare_session
    from core.simulation.replay import ReplayConfig
    youngs = _parse_youngs(args.youngs)
    with _progress("calibrating and cleaning") as cb:
        prepared = prepare_session(args.session, ReplayConfig(grid=tuple(args.grid)), callback=cb)
    with executor(args.scheduler, workers=args.workers, serial=args.serial) as ex, _trial_progress("sweep trials") as pr:
        result = sweep(prepared, youngs, sequences=args.sequences, base=_base_trial(args), refine=args.refine, executor=ex, progress=pr)
    out = write_sweep(result, args.out)
    table = Table(title="mean distance cloud -> mesh (mm), cf. Wu et al. 2020 Tables 1-2")
    table.add_column("E (Pa)", justify="right")
    table.add_column("mean error (mm)", justify="right")
    for E, e in result.table().items():
        table.add_row(f"{E:g}", f"{e * 1e3:.4f}" if e == e else "N/A (diverged)")
    Console().print(table)
    v = result.verdict or {}
    if v.get("identifiable"):
        lo, hi = v["interval"]
        print(f"E = {v['value']:.4g} Pa (95 % interval {lo:.4g}-{hi:.4g} Pa; {v['reason']})")
    else:
        print(f"E not identifiable from these data: {v.get('reason')}")
    print(f"wrote {out}/sweep.csv, {out}/sweep.json and {out}/sweep.png")
    return 0


def cmd_fit(args) -> int:
    from core.identification import executor, fit_youngs_modulus
    from core.preparation import prepare_session
    from core.simulation.replay import ReplayConfig
    with _progress("calibrating and cleaning") as cb:
        prepared = prepare_session(args.session, ReplayConfig(grid=tuple(args.grid)), callback=cb)
    with executor(args.scheduler, workers=args.workers, serial=args.serial) as ex, _trial_progress("fit: E values evaluated") as pr:
        result = fit_youngs_modulus(
            prepared, base=_base_trial(args), executor=ex, use_force=None if args.force == "auto" else args.force == "yes",
            refine_mesh=not args.no_mesh_refinement, progress=lambda n, msg: pr(n, msg),
        )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "fit.json").write_text(json.dumps(result.to_json(), indent=2))
    if result.identifiable:
        lo, hi = result.interval
        print(f"Young's modulus: {result.youngs_modulus:.4g} Pa (95 % interval {lo:.4g}-{hi:.4g} Pa), "
              f"on the {'x'.join(map(str, result.refined))} grid; {result.coarse_value:.4g} Pa on the "
              f"{'x'.join(map(str, result.grid))} replay grid (volumetric locking)")
    else:
        print(f"Young's modulus: not identifiable. {result.reason}")
    print("errors (mm): " + ", ".join(f"{k} {v * 1e3:.3f}" for k, v in result.errors.items()))
    print(f"{result.evaluations} sequence replays; wrote {out}/fit.json")
    return 0


def _add_execution_options(p) -> None:
    p.add_argument("--scheduler", default=None, help="existing Dask scheduler, e.g. tcp://host:8786 (default: a local cluster; env TISSUETWIN_SCHEDULER)")
    p.add_argument("--workers", type=int, default=2, help="worker processes of the local cluster (default 2)")
    p.add_argument("--serial", action="store_true", help="run trials in this process, without Dask")


def _add_model_options(p, *, youngs: bool = True) -> None:
    if youngs:
        p.add_argument("--youngs", type=float, default=5000.0, help="Young's modulus E in Pa (default 5e3, the paper's)")
    p.add_argument("--poisson", type=float, default=0.44, help="Poisson's ratio (default 0.44)")
    p.add_argument("--grid", type=int, nargs=3, default=(13, 5, 5), metavar=("NX", "NY", "NZ"),
                   help="node grid of a box phantom (default 13 5 5)")
    p.add_argument("--element-size", type=float, default=None, metavar="M",
                   help="target element size of a phantom given by phantom.stl, m (default: about the paper's 325 nodes)")
    p.add_argument("--dt", type=float, default=None, help="time step in s (default 1/120)")
    p.add_argument("--sequences", nargs="*", default=None, help="sequence names (default: all)")
    p.add_argument("--effects", default=None, help="JSON list of model extensions, e.g. '[{\"kind\": \"gravity\"}]'")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="tissuetwin", description="Tissue Twin: FEM replay, correction and diagnosis of palpation data.")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("generate", help="write a synthetic session with the virtual lab")
    p.add_argument("--preset", choices=_preset_names(), default="small",
                   help="lab preset (field: randomised physics and palpation, a lab that is not our replay)")
    p.add_argument("--duration", type=float, default=None, help="length of every sequence, s (default: the preset's)")
    p.add_argument("--plan", default=None, metavar="PLAN",
                   help="record a palpation plan (tissuetwin plan's folder or plan.json): every sequence follows its path")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--effects", default=None, help="JSON list of effects, e.g. '[{\"kind\": \"gravity\", \"g\": [0, 0, -9.81]}]'")
    p.add_argument("--force", action="store_true", help="write probe force columns fx, fy, fz")
    p.add_argument("--shape", choices=("box", "dome", "kidney"), default="box",
                   help="phantom shape: the paper's box (default), a dome (spherical cap on a flat base) or a "
                        "kidney-like body (an ellipsoid with a flattened base); other shapes are written as "
                        "phantom.stl and calibrated on landmarks")
    p.add_argument("--phantom-stl", default=None, metavar="FILE.stl",
                   help="use this watertight STL (metres, z up, resting on z = 0) as the phantom instead of --shape")
    p.add_argument("--overwrite", action="store_true", help="replace an existing session folder")
    p.add_argument("--out", required=True)
    p.set_defaults(func=cmd_generate)

    p = sub.add_parser("replay", help="replay a session and measure the paper's error")
    p.add_argument("session")
    p.add_argument("--out", required=True)
    _add_model_options(p)
    p.set_defaults(func=cmd_replay)

    p = sub.add_parser("sweep", help="the paper's grid search over Young's modulus (Tables 1-2)")
    p.add_argument("session")
    p.add_argument("--youngs", default="1e1,1e2,1e3,1e4,1e5,1e6", help="comma-separated E values in Pa")
    p.add_argument("--refine", action="store_true", help="add the paper's fine grid around the best coarse value")
    p.add_argument("--out", required=True)
    _add_model_options(p, youngs=False)
    _add_execution_options(p)
    p.set_defaults(func=cmd_sweep)

    p = sub.add_parser("fit", help="fit Young's modulus with a 95 %% interval, or say it cannot be identified")
    p.add_argument("session")
    p.add_argument("--out", required=True)
    p.add_argument("--force", choices=("auto", "yes", "no"), default="auto", help="use the force columns in the objective (default: when present)")
    p.add_argument("--no-mesh-refinement", action="store_true", help="skip the refined-grid refit (reports the replay-grid E)")
    _add_model_options(p, youngs=False)
    _add_execution_options(p)
    p.set_defaults(func=cmd_fit)

    p = sub.add_parser("demo", help="generate (once) the demo session (hidden gravity and robot offset, with force), "
                                    "replay the shared sample session, then open the workbench: it replays the demo "
                                    "session and runs the analyses, the diagnosis last")
    p.add_argument("--data", default=str(DEFAULT_DATA), help="data directory (default ./data)")
    p.add_argument("--sample", default=str(Path("..") / "shared" / "sample-session"), help="a session from another tool to replay too")
    p.add_argument("--no-serve", action="store_true", help="stop after the replays instead of opening the workbench")
    p.add_argument("--host", default="127.0.0.1", help="workbench bind address (default loopback)")
    p.add_argument("--port", type=int, default=None,
                   help="workbench port (default 8000 or TISSUETWIN_PORT); the 3D viewer uses PORT + 1")
    _add_model_options(p)
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("precompile", help="compile the simulation's kernels once (scripts/setup.sh runs it; "
                                          "otherwise a fresh install's first replay spends about 100 s compiling)")
    p.set_defaults(func=cmd_precompile)
    for register in _command_groups():
        register(sub)
    return parser


def _command_groups() -> list:
    """Subcommands that live in their own modules; each module exposes ``register(subparsers)``."""
    from app import cli_bag, cli_diagnosis, cli_export, cli_learning, cli_serve

    return [cli_diagnosis.register, cli_serve.register, cli_learning.register, cli_bag.register, cli_export.register]


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except TissueTwinError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except FileExistsError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
