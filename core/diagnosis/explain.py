"""What a learned correction learned: its correction field projected onto the causes.

A correction network (Wu et al. 2020, Sec. 3.3; :mod:`core.learning`) moves the top
layer of the FEM replay towards the measured surface. Each candidate cause, fitted by
the diagnosis, also moves it: by the difference between the replay with the cause and
the replay without. When the network has learned a cause, its correction field lies
along that difference. This module measures how much, by linear least squares over
every top-layer node, axis and test frame:

- for one cause with field change ``d`` and correction ``c`` (both stacked into
  vectors), the scale ``a = <c, d> / <d, d>`` (1: the network moves the nodes exactly
  as the fitted cause does) and the share ``<c, d>^2 / (|c|^2 |d|^2)``, the fraction of
  the correction's sum of squares that the scaled cause reproduces (a squared cosine);
- for the claimed causes together, the same share of their joint field change (one
  replay with all of them, since effects interact), and what is left (``1 - share``):
  what the network learned that the claimed causes do not explain (model-form error,
  noise, or an effect the diagnosis missed).

The network's corrections are bounded to half a voxel, so a scale below 1 can mean a
cause larger than the network may correct, not a partial one.

``core.diagnosis`` does not import ``core.learning`` (they are sibling layers): the
caller computes the correction field (``core.learning.correction_field``) and passes
it in.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Mapping, Sequence

import numpy as np

from core.errors import TissueTwinError
from core.identification.execution import Executor, SerialExecutor
from core.simulation import effect_from_dict
from core.preparation import PreparedSession
from core.simulation.replay import ReplayConfig, build_replay_model
from core.simulation.solver import simulate

__all__ = ["CauseShare", "CorrectionExplanation", "explain_correction", "explain_diagnosis"]


@dataclass(frozen=True)
class CauseShare:
    """How much of a correction field one cause accounts for.

    Attributes:
        kind: effect kind. effect: the effect dict whose field change was used.
        share: fraction of the correction's sum of squares reproduced by the scaled
            cause field, [0, 1].
        scale: least-squares scale of the cause field (1: exactly the fitted cause).
        cause_rms: RMS of the cause's field change over the same nodes and frames, m.
    """

    kind: str
    effect: dict
    share: float
    scale: float
    cause_rms: float


@dataclass(frozen=True)
class CorrectionExplanation:
    """The projection of a learned correction field onto the causes.

    Attributes:
        sequences: the sequences used. frames: frames used (finite in every run).
        correction_rms: RMS of the correction over top-layer nodes, axes and frames, m.
        causes: one :class:`CauseShare` per cause, largest share first.
        claimed_share: share of the correction the claimed causes explain together
            (multiple regression); None when nothing was claimed.
        unexplained_share: ``1 - claimed_share`` (1 when nothing was claimed).
    """

    sequences: list[str]
    frames: int
    correction_rms: float
    causes: list[CauseShare]
    claimed_share: float | None
    unexplained_share: float

    def to_json(self) -> dict:
        return {
            "sequences": self.sequences,
            "frames": self.frames,
            "correction_rms_m": self.correction_rms,
            "causes": [{"kind": c.kind, "share": c.share, "scale": c.scale, "cause_rms_m": c.cause_rms,
                        "parameters": {k: v for k, v in c.effect.items() if k != "kind"}} for c in self.causes],
            "claimed_share": self.claimed_share,
            "unexplained_share": self.unexplained_share,
        }


def _top_nodes(grid) -> np.ndarray:
    nx, ny, nz = (int(g) for g in grid)
    return np.arange(nx * ny * nz).reshape(nx, ny, nz)[:, :, -1].ravel()


def _top_trajectory(prepared: PreparedSession, item: tuple[str, ReplayConfig]) -> np.ndarray:
    """(F, nx*ny, 3) top-layer node positions of one replay (Dask worker function)."""
    name, config = item
    seq = prepared.sequences[name]
    sim = simulate(build_replay_model(prepared, config), seq.probe, prepared.probe_radius, seq.frame_times)
    return np.asarray(sim.positions)[:, _top_nodes(config.grid)]


def explain_correction(
    prepared: PreparedSession,
    correction: Mapping[str, np.ndarray],
    config: ReplayConfig,
    causes: Sequence[dict],
    *,
    claimed: Sequence[dict] = (),
    executor: Executor | None = None,
) -> CorrectionExplanation:
    """Project a learned correction field onto the field changes of candidate causes.

    Args:
        prepared: the calibrated session.
        correction: {sequence: (F, nx*ny, 3) float correction of the top-layer nodes, m,
            phantom frame} of the network, applied to the plain replay ``config``
            (``core.learning.correction_field``); NaN rows (diverged frames) are skipped.
        config: the replay the network was trained on (its E, grid, effects; the
            checkpoint's ``replay_config()``).
        causes: effect dicts (SESSION_FORMAT kinds with parameters), one per cause to
            project on, e.g. each candidate's fit.
        claimed: the causes the diagnosis claimed (effect dicts), projected on jointly.
        executor: where the replays run (default: this process).

    Returns:
        A :class:`CorrectionExplanation`.

    Raises:
        TissueTwinError: an unknown sequence, a correction of the wrong shape, or no
            frame where every replay is finite.
    """
    executor = executor or SerialExecutor()
    names = sorted(correction)
    grid = tuple(int(g) for g in config.grid)
    n_top = grid[0] * grid[1]
    for n in names:
        if n not in prepared.sequences:
            raise TissueTwinError(f"{prepared.path}: no sequence {n!r} to explain a correction on")
        c = np.asarray(correction[n])
        if c.ndim != 3 or c.shape[1:] != (n_top, 3) or c.shape[0] != len(prepared.sequences[n].frame_times):
            raise TissueTwinError(f"correction of {n!r} has shape {c.shape}; expected "
                                  f"({len(prepared.sequences[n].frame_times)}, {n_top}, 3) for grid {grid}")
    own = tuple(config.effects)
    models = [own] + [own + (effect_from_dict(e),) for e in causes]
    models += [own + tuple(effect_from_dict(e) for e in claimed)] if claimed else []
    items = [(n, replace(config, effects=m)) for m in models for n in names]
    runs = executor.map(_top_trajectory, prepared, items)
    per_model = [runs[i * len(names):(i + 1) * len(names)] for i in range(len(models))]

    # frames finite in the correction and in every replay
    keep = []
    for j, n in enumerate(names):
        ok = np.all(np.isfinite(np.asarray(correction[n])), axis=(1, 2))
        for m in per_model:
            ok &= np.all(np.isfinite(m[j]), axis=(1, 2))
        keep.append(ok)
    frames = int(sum(k.sum() for k in keep))
    if frames == 0:
        raise TissueTwinError(f"{prepared.path}: no frame where the correction and every replay are finite")

    def stack(arrays) -> np.ndarray:
        return np.concatenate([np.asarray(a)[k].ravel() for a, k in zip(arrays, keep)])

    c = stack([correction[n] for n in names])
    base = per_model[0]
    deltas = [stack([m[j] - base[j] for j in range(len(names))]) for m in per_model[1:]]
    cc = float(c @ c)
    shares = []
    for e, d in zip(causes, deltas):
        dd = float(d @ d)
        cd = float(c @ d)
        share = cd * cd / (cc * dd) if cc > 0 and dd > 0 else 0.0
        shares.append(CauseShare(kind=str(e["kind"]), effect=dict(e), share=share, scale=cd / dd if dd > 0 else 0.0,
                                 cause_rms=float(np.sqrt(dd / d.size))))
    shares.sort(key=lambda s: -s.share)

    claimed_share = None
    if claimed:
        d = deltas[-1]  # the replay with every claimed cause
        dd = float(d @ d)
        claimed_share = float((c @ d) ** 2 / (cc * dd)) if cc > 0 and dd > 0 else 0.0
    return CorrectionExplanation(
        sequences=names, frames=frames, correction_rms=float(np.sqrt(cc / c.size)), causes=shares,
        claimed_share=claimed_share, unexplained_share=1.0 - (claimed_share or 0.0),
    )


def explain_diagnosis(diag, prepared: PreparedSession, correction: Mapping[str, np.ndarray], config: ReplayConfig,
                      *, executor: Executor | None = None):
    """A copy of the :class:`core.diagnosis.engine.Diagnosis` ``diag`` with the learned
    correction explained (its ``learned_correction``): the correction is projected onto
    every candidate as fitted against the base model (selection round 0) and onto the
    claimed causes jointly. Arguments and errors as :func:`explain_correction`."""
    causes = [{"kind": c.kind, **c.parameters} for c in diag.candidates if c.round == 0]
    claimed = [{"kind": c.kind, **c.parameters} for c in diag.causes]
    ex = explain_correction(prepared, correction, config, causes, claimed=claimed, executor=executor)
    return replace(diag, learned_correction=ex.to_json())
