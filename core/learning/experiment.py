"""Train-and-test runs of the correction networks, and the evaluation of Table 3
(Wu et al. 2020, Sec. 5.1): both networks at the identified E, a too-stiff E and 10 Pa.

The reported error is the paper's: the mean distance from every cleaned measured point
of the ``test`` sequences to the nearest vertex of the 3x super-sampled mesh (point
weighted over the sequences). "Corrected" is the in-loop replay, the paper's use; the
offline correction of the uncorrected replay is reported beside it.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Mapping

from core.learning.apply import CorrectedSequence, correct_offline, replay_in_loop, signed_residual
from core.learning.checkpoint import Checkpoint, replay_settings
from core.learning.config import LearningError, NetworkConfig, TrainConfig
from core.learning.data import SequenceFrames, build_frames
from core.learning.train import TrainResult, train_correction

__all__ = ["TrainReport", "train_and_test", "EvaluationResult", "evaluate_networks", "write_evaluation"]

Callback = Callable[[float, str], None]

IN_LOOP_MEANING = (
    "in-loop (Wu et al. 2020, Sec. 3.3): at the end of every camera frame the top layer is set to the plain "
    "replay's plus the network's correction of it, the other free nodes move by the model's static response to that "
    "change, and the FEM continues from there (anchored: corrections do not stack, the observed layer stays within "
    "the bound of the plain replay; core.learning.apply)"
)
OFFLINE_MEANING = "the plain replay corrected frame by frame; the simulation never sees the correction"
SIGNED_MEANING = (
    "mean signed vertical residual (m) of the measured points over the top face's interior, measured z minus the "
    "mesh's top-layer height there (core.identification.residuals.top_residuals; points >= 4 mm inside the edges): "
    "positive = the mesh sits below the measurement. The unsigned metric rewards a slightly high top, so a gain "
    "that drives this below zero is partly bias, not shape"
)
UNOBSERVED_MEANING = (
    "largest distance (m, any axis, any frame) of a node the network does not set from the plain replay, in the loop: "
    "how far the body followed the corrected top layer"
)


def _scaled(callback: Callback | None, lo: float, hi: float, prefix: str = "") -> Callback | None:
    if callback is None:
        return None
    return lambda f, msg: callback(lo + (hi - lo) * min(max(f, 0.0), 1.0), prefix + msg)


def _pooled(items: list[tuple[float, int]]) -> float:
    """Point-weighted mean of per-sequence means; NaN if any is NaN or nothing is given."""
    if not items or any(not math.isfinite(m) for m, _ in items):
        return float("nan")
    n = sum(k for _, k in items)
    return float(sum(m * k for m, k in items) / n) if n else float("nan")


def _improvement(before: float, after: float) -> float:
    if not (math.isfinite(before) and math.isfinite(after)) or before <= 0:
        return float("nan")
    return 1.0 - after / before


def _num(v: float):
    return None if v is None or not math.isfinite(v) else float(v)


@dataclass
class TrainReport:
    """One network trained at one E and tested.

    Attributes:
        kind: "2d" or "3d". youngs_modulus: E of the simulation, Pa.
        training: the :class:`TrainResult`.
        checkpoint: the :class:`Checkpoint` (network and what it was trained on).
        no_network: {test sequence: (mean error m, points)} of the plain replay.
        in_loop, offline: {test sequence: :class:`CorrectedSequence`}.
        timings: s.
        no_network_signed: {test sequence: (mean signed residual m, points)} of the
            plain replay (:func:`core.learning.apply.signed_residual`).
    """

    kind: str
    youngs_modulus: float
    training: TrainResult
    checkpoint: Checkpoint
    no_network: dict[str, tuple[float, int]]
    in_loop: dict[str, CorrectedSequence]
    offline: dict[str, CorrectedSequence]
    timings: dict[str, float] = field(default_factory=dict)
    no_network_signed: dict[str, tuple[float, int]] = field(default_factory=dict)

    @property
    def test_error(self) -> dict[str, float]:
        """Point-weighted test errors, m: ``no_network``, ``corrected`` (in-loop), ``corrected_offline``."""
        return {
            "no_network": _pooled(list(self.no_network.values())),
            "corrected": _pooled([(s.mean_error, s.n_points) for s in self.in_loop.values()]),
            "corrected_offline": _pooled([(s.mean_error, s.n_points) for s in self.offline.values()]),
        }

    @property
    def test_signed(self) -> dict[str, float]:
        """Point-weighted signed vertical residuals over the top face's interior, m, same keys
        as :attr:`test_error` (NaN where unknown)."""
        return {
            "no_network": _pooled([self.no_network_signed.get(n, (float("nan"), 0)) for n in self.no_network]),
            "corrected": _pooled([(s.signed_residual, s.n_signed) for s in self.in_loop.values()]),
            "corrected_offline": _pooled([(s.signed_residual, s.n_signed) for s in self.offline.values()]),
        }

    def to_json(self) -> dict:
        te = self.test_error
        return {
            "model": self.kind,
            "session": self.checkpoint.session,
            "youngs_modulus": self.youngs_modulus,
            "test_error": {k: _num(v) for k, v in te.items()},
            "improvement": _num(_improvement(te["no_network"], te["corrected"])),
            "improvement_offline": _num(_improvement(te["no_network"], te["corrected_offline"])),
            "test_signed_residual": {k: _num(v) for k, v in self.test_signed.items()},
            "max_unobserved_offset": _num(max((s.max_unobserved_offset for s in self.in_loop.values()), default=float("nan"))),
            "meaning": {"corrected": IN_LOOP_MEANING, "corrected_offline": OFFLINE_MEANING,
                        "test_signed_residual": SIGNED_MEANING, "max_unobserved_offset": UNOBSERVED_MEANING},
            "sequences": {
                name: {
                    "no_network": _num(self.no_network[name][0]),
                    "corrected": _num(self.in_loop[name].mean_error),
                    "corrected_offline": _num(self.offline[name].mean_error),
                    "status": self.in_loop[name].status,
                    "points": self.no_network[name][1],
                    "signed_residual": {
                        "no_network": _num(self.no_network_signed.get(name, (float("nan"), 0))[0]),
                        "corrected": _num(self.in_loop[name].signed_residual),
                        "corrected_offline": _num(self.offline[name].signed_residual),
                    },
                    "max_unobserved_offset": _num(self.in_loop[name].max_unobserved_offset),
                    "inference_seconds_per_frame": {
                        "in_loop": self.in_loop[name].inference_seconds / max(len(self.in_loop[name].frame_errors), 1),
                        "offline": self.offline[name].inference_seconds / max(len(self.offline[name].frame_errors), 1),
                    },
                }
                for name in self.no_network
            },
            **self.training.to_json(),
            "timings": {**self.training.timings, **self.timings},
        }


def train_and_test(
    prepared,
    replay_config,
    network_config: NetworkConfig,
    train_config: TrainConfig | None = None,
    *,
    frames: Mapping[str, SequenceFrames] | None = None,
    session=None,
    callback: Callback | None = None,
) -> TrainReport:
    """Replay (unless ``frames`` are given), train one network, test it in-loop and offline.

    Args:
        prepared: :class:`core.simulation.replay.PreparedSession` with train, validation
            and test sequences.
        replay_config: the simulation the network corrects (E, grid, effects, numerics).
        network_config, train_config: what to train and how.
        frames: per-frame arrays of ``replay_config`` (reuse them across networks).
        session: optional read :class:`core.io.Session` (tool orientations).
        callback: ``callback(fraction, message)``.

    Raises:
        LearningError: no train, validation or test sequence.
    """
    t0 = time.perf_counter()
    if not any(s.role == "test" for s in prepared.sequences.values()):
        raise LearningError(f"{prepared.path}: no 'test' sequence to report on (roles come from session.json)")
    if frames is None:
        frames = build_frames(prepared, replay_config, session=session, callback=_scaled(callback, 0.0, 0.2, "replay "))
    t_replay = time.perf_counter() - t0
    lo = 0.2 if t_replay > 0.01 else 0.0
    result = train_correction(frames, prepared.size, network_config, train_config,
                              callback=_scaled(callback, lo, 0.85, f"train {network_config.kind} "))
    ck = Checkpoint(network=result.network, session=str(prepared.path), replay=replay_settings(replay_config),
                    extra={"train": result.to_json()})
    tests = [n for n, s in frames.items() if s.role == "test"]
    no_net, no_net_signed, in_loop, offline = {}, {}, {}, {}
    t1 = time.perf_counter()
    for i, name in enumerate(tests):
        f = frames[name]
        no_net[name] = (f.mean_error, int(sum(c.shape[0] for c in f.clouds)))
        no_net_signed[name] = signed_residual(f.positions, f.clouds, f.mesh_or_grid, prepared.size)
        offline[name] = correct_offline(ck, f, factor=replay_config.supersample, size=prepared.size)
        in_loop[name] = replay_in_loop(ck, prepared, name, config=replay_config, session=session, reference=f,
                                       callback=_scaled(callback, 0.85 + 0.15 * i / len(tests), 0.85 + 0.15 * (i + 1) / len(tests), f"in-loop {name} "))
    return TrainReport(
        kind=network_config.kind, youngs_modulus=float(replay_config.youngs_modulus), training=result, checkpoint=ck,
        no_network=no_net, in_loop=in_loop, offline=offline, no_network_signed=no_net_signed,
        timings={"replay": t_replay, "test": time.perf_counter() - t1, "total": time.perf_counter() - t0},
    )


@dataclass
class EvaluationResult:
    """Table 3 of Wu et al. 2020: test errors without and with both networks for several E.

    Attributes:
        session: the session folder.
        values: [(label, E in Pa)], e.g. ("identified", 5100.0), ("too stiff", 51000.0), ("10 Pa", 10.0).
        reports: {(label, kind): :class:`TrainReport`}.
        identification: how the identified E was obtained (dict).
        no_network: {label: {test sequence: (mean error m or NaN, points)}} of the plain replays.
        failures: {(label, kind): why that network could not be trained (e.g. every train
            simulation diverged at 10 Pa); its cells read N/A}.
        timings: s.
        no_network_signed: {label: {test sequence: (mean signed residual m or NaN, points)}}
            of the plain replays (:func:`core.learning.apply.signed_residual`).
    """

    session: Path
    values: list[tuple[str, float]]
    reports: dict[tuple[str, str], TrainReport]
    identification: dict
    no_network: dict[str, dict[str, tuple[float, int]]] = field(default_factory=dict)
    failures: dict[tuple[str, str], str] = field(default_factory=dict)
    kinds: tuple[str, ...] = ("2d", "3d")
    timings: dict[str, float] = field(default_factory=dict)
    no_network_signed: dict[str, dict[str, tuple[float, int]]] = field(default_factory=dict)

    def rows(self) -> list[dict]:
        """One row per (E, test sequence) plus a pooled "all test" row per E; errors in m
        (NaN where a simulation diverged or a network could not be trained). Keys:
        ``no_network``, ``<kind>``, ``<kind>_offline``, their ``*_improvement``, and the
        signed residuals ``no_network_signed``, ``<kind>_signed``, ``<kind>_offline_signed``."""
        out = []
        for label, E in self.values:
            base = self.no_network[label]
            signed = self.no_network_signed.get(label, {})
            for name in list(base) + ["all test"]:
                row = {"label": label, "youngs_modulus": E, "sequence": name}
                row["no_network"] = _pooled(list(base.values())) if name == "all test" else base[name][0]
                row["no_network_signed"] = (_pooled([signed.get(n, (float("nan"), 0)) for n in base]) if name == "all test"
                                            else signed.get(name, (float("nan"), 0))[0])
                for k in self.kinds:
                    rep = self.reports.get((label, k))
                    if rep is None:
                        row[k] = row[k + "_offline"] = float("nan")
                        row[k + "_signed"] = row[k + "_offline_signed"] = float("nan")
                    elif name == "all test":
                        te, ts = rep.test_error, rep.test_signed
                        row[k], row[k + "_offline"] = te["corrected"], te["corrected_offline"]
                        row[k + "_signed"], row[k + "_offline_signed"] = ts["corrected"], ts["corrected_offline"]
                    else:
                        row[k], row[k + "_offline"] = rep.in_loop[name].mean_error, rep.offline[name].mean_error
                        row[k + "_signed"] = rep.in_loop[name].signed_residual
                        row[k + "_offline_signed"] = rep.offline[name].signed_residual
                    row[k + "_improvement"] = _improvement(row["no_network"], row[k])
                    row[k + "_offline_improvement"] = _improvement(row["no_network"], row[k + "_offline"])
                out.append(row)
        return out

    def to_json(self) -> dict:
        return {
            "format": "tissuetwin-evaluation/1",
            "session": str(self.session),
            "metric": "mean distance (m) from measured test points to the nearest vertex of the 3x super-sampled mesh",
            "corrected": IN_LOOP_MEANING + "; *_offline: " + OFFLINE_MEANING,
            "signed": "*_signed: " + SIGNED_MEANING,
            "identification": self.identification,
            "youngs_modulus": {label: E for label, E in self.values},
            "rows": [{k: (_num(v) if isinstance(v, float) else v) for k, v in r.items()} for r in self.rows()],
            "runs": {f"{label}/{kind}": rep.to_json() for (label, kind), rep in self.reports.items()},
            "failures": {f"{label}/{kind}": msg for (label, kind), msg in self.failures.items()},
            "timings": self.timings,
        }

    def to_markdown(self) -> str:
        """The Markdown table of Table 3 (errors in mm, in-loop correction), with the
        offline figures in a second table; both end with the signed residuals (mm)."""
        def mm(v):
            return "N/A" if v is None or not math.isfinite(v) else f"{v * 1e3:.4f}"

        def smm(v):
            return "N/A" if v is None or not math.isfinite(v) else f"{v * 1e3:+.3f}"

        def pct(v):
            return "N/A" if v is None or not math.isfinite(v) else f"{v * 100:.1f}%"

        lines = [
            "| E | sequence | no network | 2D | improvement | 3D | improvement | signed: no network | 2D | 3D |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
        ]
        off = list(lines)
        for r in self.rows():
            e = f"{r['youngs_modulus']:.3g} Pa ({r['label']})"
            sig = f"| {smm(r['no_network_signed'])} "
            lines.append(f"| {e} | {r['sequence']} | {mm(r['no_network'])} | {mm(r.get('2d'))} | {pct(r.get('2d_improvement'))} "
                         f"| {mm(r.get('3d'))} | {pct(r.get('3d_improvement'))} "
                         + sig + f"| {smm(r.get('2d_signed'))} | {smm(r.get('3d_signed'))} |")
            off.append(f"| {e} | {r['sequence']} | {mm(r['no_network'])} | {mm(r.get('2d_offline'))} | {pct(r.get('2d_offline_improvement'))} "
                       f"| {mm(r.get('3d_offline'))} | {pct(r.get('3d_offline_improvement'))} "
                       + sig + f"| {smm(r.get('2d_offline_signed'))} | {smm(r.get('3d_offline_signed'))} |")
        head = (f"# Learned correction, {self.session}\n\n"
                "Mean distance (mm) from the measured test points to the nearest vertex of the 3x super-sampled "
                "mesh (Wu et al. 2020, Table 3). The last three columns (signed) are the mean signed vertical "
                "residual (mm) of the points over the top face's interior, measured minus mesh: near 0 the top sits "
                "where the camera saw it, negative = the mesh sits too high (the unsigned metric rewards a slightly "
                "high top, so a gain that pushes this below 0 is partly bias, not shape).\n\n"
                "## In-loop correction (the paper's use)\n\n")
        notes = "".join(f"\n- {label}, {kind.upper()}: not trained: {msg}" for (label, kind), msg in self.failures.items())
        if notes:
            notes = "\nN/A: a simulation diverged (the paper's N/A) or the network could not be trained." + notes + "\n"
        return (head + "\n".join(lines) + "\n\n## Offline correction of the plain replay\n\n" + "\n".join(off) + "\n"
                + notes)


def evaluate_networks(
    prepared,
    values: list[tuple[str, float]],
    base_config,
    *,
    kinds: tuple[str, ...] = ("2d", "3d"),
    network_config: NetworkConfig | None = None,
    train_config: TrainConfig | None = None,
    identification: dict | None = None,
    session=None,
    callback: Callback | None = None,
    per_kind: Mapping[str, tuple[NetworkConfig | None, TrainConfig | None]] | None = None,
) -> EvaluationResult:
    """Train and test each network kind at each E (Table 3).

    Args:
        prepared: the prepared session (train/validation/test sequences).
        values: [(label, E Pa)] to replay at.
        base_config: :class:`ReplayConfig` whose E is replaced by each value.
        kinds: network kinds. network_config: template (its ``kind`` is replaced).
        train_config: schedule. identification: recorded as given.
        callback: ``callback(fraction, message)``.
        per_kind: {kind: (network config or None, train config or None)} overriding the
            template and schedule for that kind (e.g. a cheaper 3D run at paper size);
            what each run used is in its ``runs`` entry of ``evaluation.json``.
    """
    network_config = network_config or NetworkConfig()
    per_kind = dict(per_kind or {})
    t0 = time.perf_counter()
    reports, failures, baselines, baselines_signed = {}, {}, {}, {}
    n = len(values) * (len(kinds) + 1)
    step = 0
    for label, E in values:
        cfg = replace(base_config, youngs_modulus=float(E))
        frames = build_frames(prepared, cfg, session=session, callback=_scaled(callback, step / n, (step + 1) / n, f"E {E:g}: replay "))
        baselines[label] = {name: (f.mean_error, int(sum(c.shape[0] for c in f.clouds)))
                            for name, f in frames.items() if f.role == "test"}
        baselines_signed[label] = {name: signed_residual(f.positions, f.clouds, f.mesh_or_grid, prepared.size)
                                   for name, f in frames.items() if f.role == "test"}
        step += 1
        for kind in kinds:
            usable = {r: sum(int(f.finite.sum()) for f in frames.values() if f.role == r) for r in ("train", "validation")}
            if min(usable.values()) == 0:
                diverged = [f"{name}: {f.status}" for name, f in frames.items() if f.role in ("train", "validation")]
                failures[(label, kind)] = f"no usable train/validation frame at E = {E:g} Pa ({', '.join(diverged)})"
            else:
                net_k, train_k = per_kind.get(kind, (None, None))
                reports[(label, kind)] = train_and_test(
                    prepared, cfg, replace(net_k or network_config, kind=kind), train_k or train_config, frames=frames,
                    session=session,
                    callback=_scaled(callback, step / n, (step + 1) / n, f"E {E:g}: "),
                )
            step += 1
    return EvaluationResult(session=Path(prepared.path), values=list(values), reports=reports,
                            identification=identification or {}, no_network=baselines, failures=failures,
                            no_network_signed=baselines_signed,
                            kinds=tuple(kinds), timings={"total": time.perf_counter() - t0})


def write_evaluation(result: EvaluationResult, out) -> Path:
    """Write ``evaluation.json`` and ``evaluation.md`` into ``out``; returns the folder."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "evaluation.json").write_text(json.dumps(result.to_json(), indent=2))
    (out / "evaluation.md").write_text(result.to_markdown())
    return out
