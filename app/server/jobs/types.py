"""The job types the workbench runs: each is a parameter model and a function calling ``core``.

Functions run on a Dask worker with a :class:`JobContext`; they import ``core`` inside
(workers import this module once). Adding a type = one model, one function, one
:class:`JobType` in :func:`default_registry`.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from app.server.jobs.context import JobContext
from app.server.jobs.registry import JobType, Registry

__all__ = ["GenerateParams", "ReplayParams", "SweepParams", "FitParams", "DiagnoseParams", "TrainParams",
           "EvaluateParams", "default_registry"]

Grid = Annotated[list[Annotated[int, Field(ge=2, le=64)]], Field(min_length=3, max_length=3)]


def _check_effects(effects: list[dict]) -> list[dict]:
    from core.errors import TissueTwinError
    from core.simulation import effect_from_dict

    for e in effects:
        try:
            effect_from_dict(dict(e))
        except TissueTwinError as exc:  # pydantic turns ValueError into a 422 field error
            raise ValueError(str(exc)) from exc
    return effects


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class GenerateParams(_Strict):
    """Write a synthetic session with the virtual lab (``core.lab.generate_session``)."""

    name: str = Field("lab-session", pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$", description="name of the new session")
    preset: Literal["small", "demo", "paper", "field"] = "small"
    seed: int = Field(0, ge=0)
    effects: list[dict] = Field(default_factory=list, description='e.g. [{"kind": "gravity", "g": [0, 0, -9.81]}]')
    with_force: bool = False

    _effects = field_validator("effects")(_check_effects)


class _ModelParams(_Strict):
    session_id: int = Field(description="id of a registered session")
    poisson_ratio: float = Field(0.44, gt=0.0, lt=0.5)
    grid: Grid = Field(default_factory=lambda: [13, 5, 5], description="FEM node grid nx, ny, nz of a box phantom")
    element_size: float | None = Field(None, gt=0.0, le=1.0, description="target element size of a phantom given by "
                                       "phantom.stl, m (empty: about the paper's 325 nodes; unused for a box)")
    effects: list[dict] = Field(default_factory=list, description="model extensions (SESSION_FORMAT effect kinds)")
    sequences: list[str] | None = Field(None, description="sequence names (default: all, or train for sweeps)")

    _effects = field_validator("effects")(_check_effects)


class ReplayParams(_ModelParams):
    """Replay a session and measure the paper's error (``core.simulation.replay``)."""

    youngs_modulus: float = Field(5000.0, gt=0, le=1e9, description="E, Pa")


class SweepParams(_ModelParams):
    """The paper's grid search over E (Tables 1-2): explicit values, or a log range."""

    youngs: list[Annotated[float, Field(gt=0, le=1e9)]] | None = Field(None, description="E values, Pa")
    e_min: float = Field(1e1, gt=0, le=1e9, description="range start, Pa (when youngs is not given)")
    e_max: float = Field(1e6, gt=0, le=1e9, description="range end, Pa")
    per_decade: int = Field(1, ge=1, le=10, description="log-spaced values per decade")
    refine: bool = Field(False, description="add the paper's 2.5/5/7.5 fine grid around the best value")

    @model_validator(mode="after")
    def _range(self):
        if self.youngs is None and self.e_max < self.e_min:
            raise ValueError(f"e_max ({self.e_max:g} Pa) must be >= e_min ({self.e_min:g} Pa)")
        if len(self.values()) > 60:
            raise ValueError(f"at most 60 values of E per sweep, got {len(self.values())}")
        return self

    def values(self) -> list[float]:
        """The swept E values, Pa."""
        if self.youngs:
            return sorted({float(E) for E in self.youngs})
        n = max(int(round(math.log10(self.e_max / self.e_min) * self.per_decade)), 0)
        return [float(f"{self.e_min * 10 ** (i / self.per_decade):.6g}") for i in range(n + 1)]


class FitParams(_ModelParams):
    """Fit E with a 95 % interval, or report it is not identifiable (``fit_youngs_modulus``)."""

    use_force: Literal["auto", "yes", "no"] = "auto"
    refine_mesh: bool = True


class DiagnoseParams(_Strict):
    """Name what the base model lacks, extend it, measure the gain (``core.diagnosis``)."""

    session_id: int = Field(description="id of a registered session")
    grid: Grid = Field(default_factory=lambda: [13, 5, 5], description="grid of the signatures and fits")
    fit_youngs: bool = Field(True, description="fit E with the claimed causes")
    refine_mesh: bool = Field(True, description="fit E on the refined grid too")
    use_force: Literal["auto", "yes", "no"] = Field(
        "auto", description="probe force in the evidence, E fitted jointly with each cause (auto: when every sequence has force columns)")


class PlanParams(_Strict):
    """The palpation that would make the kinds a diagnosis could not tell decidable
    (``core.diagnosis.planner``): a probe path, its description and its kinematics.csv."""

    session_id: int = Field(description="id of a registered session")
    diagnose_job_id: int | None = Field(None, ge=1, description="a finished diagnose job of this session whose "
                                        "answers the plan starts from (empty: diagnose first, minutes)")
    kinds: list[str] | None = Field(None, max_length=8, description="kinds to make decidable (empty: every kind "
                                    "that could not be told or was confounded)")
    max_depth: float = Field(0.008, gt=0.0, le=0.02, description="deepest indentation, m")
    speed: float = Field(0.010, gt=0.0, le=0.05, description="fastest probe speed in contact, m/s")
    duration: float = Field(20.0, gt=1.0, le=600.0, description="most seconds of probing")

    @field_validator("kinds")
    @classmethod
    def _known(cls, v):
        from core.simulation.effects import EFFECT_KINDS

        bad = [k for k in v or [] if k not in EFFECT_KINDS]
        if bad:
            raise ValueError(f"unknown effect kind(s) {bad}; expected some of {sorted(EFFECT_KINDS)}")
        return v


class _LearningParams(_ModelParams):
    """How the correction network is shaped and trained (``core.learning.NetworkConfig`` /
    ``TrainConfig``; defaults are the paper's and the CLI's)."""

    widths: Annotated[list[Annotated[int, Field(ge=1, le=512)]], Field(min_length=3, max_length=3)] = Field(
        default_factory=lambda: [64, 128, 256], description="features of the 3 encoder blocks (paper: 64 128 256)")
    pose: Literal["position_quaternion", "position"] = "position_quaternion"
    epochs: int = Field(40, ge=1, le=1000, description="maximum epochs (early stopping on validation)")
    patience: int = Field(5, ge=1, le=1000, description="epochs without a better validation loss before stopping")
    batch_size: int = Field(16, ge=1, le=4096, description="frames per Adam step")
    learning_rate: float = Field(1e-3, gt=0, le=1.0, description="Adam step size")
    max_points: int = Field(1024, ge=1, le=1_000_000, description="measured points per frame in the loss")
    seed: int = Field(0, ge=0)
    threads: int = Field(1, ge=1, le=64, description="torch threads on the worker (one per worker process)")

    def network_config(self, kind: str):
        from core.learning import NetworkConfig

        return NetworkConfig(kind=kind, widths=tuple(self.widths), pose=self.pose)

    def train_config(self):
        from core.learning import TrainConfig

        return TrainConfig(max_epochs=self.epochs, patience=self.patience, batch_size=self.batch_size,
                           learning_rate=self.learning_rate, max_points=self.max_points, seed=self.seed,
                           threads=self.threads)


class TrainParams(_LearningParams):
    """Train the 2D or 3D correction network at one E and test it (Wu et al. 2020, Sec. 3.3)."""

    model: Literal["2d", "3d"] = Field("2d", description="2D UNet on the top layer or 3D UNet on the grid")
    youngs_modulus: float = Field(5000.0, gt=0, le=1e9, description="E of the simulation the network corrects, Pa")


class EvaluateParams(_LearningParams):
    """Table 3 of Wu et al. 2020: the networks at the identified E, a too-stiff E and 10 Pa."""

    identified: float | None = Field(None, gt=0, le=1e9, description="identified E, Pa (default: fit it on the train sequences)")
    stiff_factor: float = Field(2.0, gt=1.0, le=1e3, description="too-stiff E = factor x identified E")
    models: Annotated[list[Literal["2d", "3d"]], Field(min_length=1, max_length=2)] = Field(
        default_factory=lambda: ["2d", "3d"], description="networks to train at each E")


def _replay_config(p: _ModelParams, youngs: float = 5000.0):
    from core.simulation import effect_from_dict
    from core.simulation.replay import ReplayConfig
    return ReplayConfig(
        youngs_modulus=youngs, poisson_ratio=p.poisson_ratio, grid=tuple(p.grid), element_size=p.element_size,
        effects=tuple(effect_from_dict(dict(e)) for e in p.effects),
        sequences=tuple(p.sequences) if p.sequences else None,
    )


def _base_trial(p: _ModelParams):
    from core.identification import Trial

    return Trial(sequence="", youngs_modulus=1.0, poisson_ratio=p.poisson_ratio, grid=tuple(p.grid),
                 element_size=p.element_size, effects=tuple(dict(e) for e in p.effects))


def _prepare(p: _ModelParams, ctx: JobContext, lo: float, hi: float, youngs: float = 5000.0):
    from core.preparation import prepare_session
    return prepare_session(ctx.session_path, _replay_config(p, youngs), picked=ctx.picked, callback=ctx.scaled(lo, hi))


def run_generate(p: GenerateParams, ctx: JobContext) -> dict:
    from core.lab import generate_session

    out = ctx.artifact_dir / p.name
    generate_session(out, preset=p.preset, seed=p.seed, effects=p.effects, with_force=p.with_force,
                     callback=ctx.scaled(0.0, 1.0))
    return {"session": str(out), "register_session": {"path": str(out), "name": p.name}}


def run_replay(p: ReplayParams, ctx: JobContext) -> dict:
    from app.run_mesh import mesh_summary
    from app.viewer.data import write_viewer_arrays
    from core.simulation.replay import replay, write_replay
    prepared = _prepare(p, ctx, 0.0, 0.3, p.youngs_modulus)
    result = replay(prepared.path, _replay_config(p, p.youngs_modulus), prepared=prepared, callback=ctx.scaled(0.0, 0.9))
    write_replay(result, ctx.artifact_dir)
    ctx.progress(0.92, "per-vertex errors for the viewer")
    write_viewer_arrays(prepared, result, ctx.artifact_dir)
    summary = result.to_json()
    summary["mesh"] = {**mesh_summary(result.mesh), **(summary.get("mesh") or {})}  # the dashboard's mesh line
    summary["viewer"] = True
    return summary


def run_sweep(p: SweepParams, ctx: JobContext) -> dict:
    from core.identification import sweep, write_sweep

    prepared = _prepare(p, ctx, 0.0, 0.1)
    values = p.values()
    with ctx.executor() as ex:
        result = sweep(
            prepared, values, sequences=p.sequences, base=_base_trial(p), refine=p.refine, executor=ex,
            progress=lambda done, total: ctx.progress(0.1 + 0.85 * done / max(total, 1), f"{done}/{total} trials"),
        )
    write_sweep(result, ctx.artifact_dir)
    table = result.table()
    finite = {E: e for E, e in table.items() if math.isfinite(e)}
    return {
        "table": [{"youngs_modulus": E, "mean_error": (e if math.isfinite(e) else None)} for E, e in table.items()],
        "rows": [{"youngs_modulus": r.trial.youngs_modulus, "sequence": r.trial.sequence, "status": r.status,
                  "mean_error": r.mean_error if r.ok else None} for r in result.results],
        "best": min(finite, key=finite.get) if finite else None,  # the lowest error: an estimate only if identifiable
        "youngs_modulus": result.verdict,  # the fit's verdict on E (core.identification.verdict), as fit and diagnose report it
        "plot": "sweep.png",
    }


def run_fit(p: FitParams, ctx: JobContext) -> dict:
    from core.identification import fit_youngs_modulus

    prepared = _prepare(p, ctx, 0.0, 0.1)
    with ctx.executor() as ex:
        result = fit_youngs_modulus(
            prepared, base=_base_trial(p), executor=ex,
            use_force=None if p.use_force == "auto" else p.use_force == "yes", refine_mesh=p.refine_mesh,
            # about 65 replays for a fit with force data (README); the bar saturates at 95 %
            progress=lambda n, msg: ctx.progress(min(0.1 + 0.85 * n / 70.0, 0.95), f"{n} E values: {msg}"),
        )
    summary = result.to_json()
    (ctx.artifact_dir / "fit.json").write_text(json.dumps(summary, indent=2))
    return summary


def run_diagnose(p: DiagnoseParams, ctx: JobContext) -> dict:
    from core.diagnosis import DiagnosisConfig, diagnose_prepared
    from core.preparation import prepare_session
    from core.simulation.replay import ReplayConfig
    prepared = prepare_session(ctx.session_path, ReplayConfig(grid=tuple(p.grid)), picked=ctx.picked, callback=ctx.scaled(0.0, 0.1))
    config = DiagnosisConfig(grid=tuple(p.grid), fit_youngs=p.fit_youngs, refine_mesh=p.refine_mesh,
                             use_force=None if p.use_force == "auto" else p.use_force == "yes")
    with ctx.executor() as ex:
        diag = diagnose_prepared(prepared, config, executor=ex, callback=ctx.scaled(0.1, 0.98))
    return write_diagnose_artifacts(diag, prepared, ctx.artifact_dir, progress=ctx.progress)


def write_diagnose_artifacts(diag, prepared, out, progress=None) -> dict:
    """What a diagnose job leaves in its folder ``out``: ``diagnosis.json``, ``report.md``
    and its figures, and the viewer's run of the test sequences (``viewer_run/``): the base
    model, the model extended by the claimed causes as the corrected mesh, and the
    diagnosis layers (:mod:`app.viewer.diagnosis_data`).

    Args:
        diag: a ``core.diagnosis.Diagnosis``. prepared: the session it diagnosed.
        progress: ``progress(fraction, message)`` or None.

    Returns:
        the job's summary (the diagnosis's JSON, the first figure's name, the sequences
        with a corrected mesh, the diagnosis layers and ``"viewer": true``).
    """
    from app.viewer.diagnosis_data import write_diagnosis_run
    from core.diagnosis import write_diagnosis

    write_diagnosis(diag, out)
    summary = diag.to_json()
    summary["plot"] = "residual_maps.png"
    if progress is not None:
        progress(0.99, "the diagnosis in 3D: base and extended models, each cause's change")
    ym = summary.get("youngs_modulus") or {}
    E = ym.get("replay_grid_value_used") or ym.get("value") or 5000.0  # the E its causes were fitted with
    shown = write_diagnosis_run(prepared, summary, tuple(diag.config.grid), float(E), Path(out) / VIEWER_RUN)
    summary["corrected_shown"] = shown["corrected_shown"]
    summary["diagnosis_layers"] = shown["layers"]
    summary["viewer"] = True
    return summary


def _diagnosis_of(job_id: int, ctx: JobContext) -> dict:
    """The diagnosis.json of diagnose job ``job_id`` (its folder beside this job's)."""
    from core.errors import TissueTwinError

    path = ctx.artifact_dir.parent / str(job_id) / "diagnosis.json"
    try:
        data = json.loads(path.read_text())
        if not isinstance(data.get("detectability"), dict):
            raise ValueError("it has no detectability")
    except (OSError, ValueError) as exc:
        raise TissueTwinError(f"job {job_id}: no usable diagnosis ({path}: {exc}); give a finished diagnose job") from exc
    if Path(data.get("session", "")).resolve() != Path(ctx.session_path).resolve():
        raise TissueTwinError(f"job {job_id} diagnosed {data.get('session')}, not this plan's session {ctx.session_path}")
    return data


def run_plan(p: PlanParams, ctx: JobContext) -> dict:
    from app.viewer.plan_data import write_plan_view
    from core.diagnosis import DiagnosisConfig, diagnose_prepared
    from core.diagnosis.planner import PlanLimits, plan_experiment, plan_inputs, write_plan
    from core.preparation import prepare_session
    from core.simulation.replay import ReplayConfig

    config = DiagnosisConfig()
    prepared = prepare_session(ctx.session_path, ReplayConfig(grid=config.grid), picked=ctx.picked, callback=ctx.scaled(0.0, 0.05))
    limits = PlanLimits(max_depth=p.max_depth, speed=p.speed, duration=p.duration)
    with ctx.executor() as ex:
        diagnosis = (_diagnosis_of(p.diagnose_job_id, ctx) if p.diagnose_job_id is not None
                     else diagnose_prepared(prepared, config, executor=ex, callback=ctx.scaled(0.05, 0.6)))
        detect, fixed, E = plan_inputs(diagnosis, config)
        plan = plan_experiment(prepared, detect, config, fixed=fixed, youngs_modulus=E, kinds=p.kinds, limits=limits,
                               executor=ex, callback=ctx.scaled(0.6, 0.98))
    out = write_plan(plan, ctx.artifact_dir)
    write_plan_view(plan, prepared.size, prepared.probe_radius, out, stl=prepared.stl_path)
    summary = plan.to_json()
    summary.pop("path_phantom", None)  # in plan.json and plan_view.json; the job row stays small
    summary["plan_view"] = True
    return summary


def _prepare_learning(p: _LearningParams, ctx: JobContext, hi: float, youngs: float = 5000.0):
    """Read and prepare the session; the learned correction needs train, validation and test sequences."""
    from core.io import read_session
    from core.learning import LearningError
    from core.preparation import prepare_session
    session = read_session(ctx.session_path)
    prepared = prepare_session(session, _replay_config(p, youngs), picked=ctx.picked, callback=ctx.scaled(0.0, hi))
    missing = {"train", "validation", "test"} - {s.role for s in prepared.sequences.values()}
    if missing:
        raise LearningError(f"{ctx.session_path / 'session.json'}: the learned correction needs train, validation "
                            f"and test sequences; missing role(s) {sorted(missing)}")
    return session, prepared


def run_train(p: TrainParams, ctx: JobContext) -> dict:
    from core.learning import save_checkpoint, train_and_test

    session, prepared = _prepare_learning(p, ctx, 0.05, p.youngs_modulus)
    config = _replay_config(p, p.youngs_modulus)
    report = train_and_test(prepared, config, p.network_config(p.model), p.train_config(), session=session,
                            callback=ctx.scaled(0.05, 0.97))
    out = ctx.artifact_dir
    ck_path = save_checkpoint(out / "checkpoint.pt", report.checkpoint.network, session=prepared.path,
                              replay_config=config, extra={"train": report.training.to_json()})
    traj = out / "trajectories"
    traj.mkdir(exist_ok=True)
    for name in report.in_loop:  # the viewer's "corrected mesh" layer reads these
        report.in_loop[name].save(traj / f"{name}_in_loop.npz")
        report.offline[name].save(traj / f"{name}_offline.npz")
    summary = report.to_json()
    summary["checkpoint"] = ck_path.name
    (out / "train.json").write_text(json.dumps(summary, indent=2))
    ctx.progress(0.98, "corrected meshes for the viewer")
    summary["corrected_shown"], summary["mesh"] = _write_corrected_run(prepared, config, report, out / VIEWER_RUN)
    summary["viewer"] = True
    return summary


VIEWER_RUN = "viewer_run"
"""Folder of a train job holding a replay run of its test sequences with the network's
corrected meshes in ``corrected/`` (what :func:`app.viewer.data.load_run` reads)."""


def _write_corrected_run(prepared, config, report, folder) -> tuple[dict[str, str], dict]:
    """Replay the test sequences plainly (the raw FEM layer) and store the corrected
    trajectories beside them: in-loop (the paper's use) where it did not diverge, else
    offline. Returns ({sequence: "in_loop" | "offline"}, the replayed mesh's
    :func:`app.run_mesh.mesh_summary`)."""
    from dataclasses import replace

    import numpy as np

    from app.run_mesh import mesh_summary
    from app.viewer.data import vertex_errors, write_viewer_arrays
    from core.simulation.replay import replay, write_replay
    tests = list(report.in_loop)
    result = replay(prepared.path, replace(config, sequences=tuple(tests)), prepared=prepared)
    write_replay(result, folder)
    write_viewer_arrays(prepared, result, folder)
    (folder / "corrected").mkdir(exist_ok=True)
    shown = {}
    for name in tests:
        corrected = report.in_loop[name] if report.in_loop[name].status == "ok" else report.offline[name]
        positions = corrected.positions
        assert positions.shape == result.sequences[name].simulation.positions.shape, name  # same camera frames
        np.savez_compressed(folder / "corrected" / f"{name}.npz", positions=positions,
                            vertex_error=vertex_errors(positions, result.mesh, prepared.sequences[name].clouds, config.supersample),
                            mode=np.str_(corrected.mode))
        shown[name] = corrected.mode
    return shown, mesh_summary(result.mesh)


def run_evaluate(p: EvaluateParams, ctx: JobContext) -> dict:
    from core.learning import evaluate_networks, write_evaluation

    session, prepared = _prepare_learning(p, ctx, 0.05)
    if p.identified is not None:
        E_id = float(p.identified)
        identification = {"method": "given (identified)", "youngs_modulus": E_id}
        lo = 0.05
    else:
        from core.identification import fit_youngs_modulus

        with ctx.executor() as ex:
            fit = fit_youngs_modulus(prepared, base=_base_trial(p), executor=ex, refine_mesh=False,
                                     progress=lambda n, msg: ctx.progress(min(0.05 + 0.15 * n / 25.0, 0.2), f"{n} E values: {msg}"))
        E_id, lo = float(fit.coarse_value), 0.2
        identification = {"method": "fit_youngs_modulus on the replay grid (core.identification)",
                          "youngs_modulus": E_id, "identifiable": fit.identifiable, "reason": fit.reason,
                          "interval": list(fit.interval) if fit.interval else None}
        ctx.log(f"identified E = {E_id:.4g} Pa" + ("" if fit.identifiable else f" (not identifiable: {fit.reason})"))
    values = [("identified", E_id), ("too stiff", E_id * p.stiff_factor), ("10 Pa", 10.0)]
    kinds = tuple(p.models)
    result = evaluate_networks(prepared, values, _replay_config(p, E_id), kinds=kinds,
                               network_config=p.network_config(kinds[0]), train_config=p.train_config(),
                               identification=identification, session=session, callback=ctx.scaled(lo, 0.98))
    write_evaluation(result, ctx.artifact_dir)
    summary = result.to_json()
    summary["markdown"] = "evaluation.md"
    return summary


def default_registry() -> Registry:
    """The job types of this release: generate, replay, sweep, fit, diagnose, plan, train, evaluate."""
    return Registry([
        JobType("generate", GenerateParams, run_generate, "synthetic session from the virtual lab"),
        JobType("replay", ReplayParams, run_replay, "replay a session, paper's error, 3D view"),
        JobType("sweep", SweepParams, run_sweep, "grid search over Young's modulus (Tables 1-2)"),
        JobType("fit", FitParams, run_fit, "fit Young's modulus with a 95 % interval"),
        JobType("diagnose", DiagnoseParams, run_diagnose, "name what the simulation lacks and what fixing it gains"),
        JobType("plan", PlanParams, run_plan, "the palpation that would tell what the diagnosis could not"),
        JobType("train", TrainParams, run_train, "train the 2D/3D correction network and test it (Sec. 3.3)",
                ("core.learning",)),
        JobType("evaluate", EvaluateParams, run_evaluate, "Table 3: both networks at the identified E, too stiff, 10 Pa",
                ("core.learning",)),
    ])
