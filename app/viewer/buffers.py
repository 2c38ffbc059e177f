"""The viewer's shared, read-only display buffers: colour maps and legends, the per-sequence
buffers (colours and one GLB per frame, encoded once) and the runs and ICP inputs every
browser tab reads (:class:`SharedRuns`), and what the viewer may ask of the server
(:class:`ViewerCallbacks`)."""

from __future__ import annotations

import io
import threading
from dataclasses import dataclass
from typing import Callable

import numpy as np

from app.viewer.data import RunArrays, SequenceArrays

__all__ = ["ViewerCallbacks", "SequenceView", "SharedRuns", "error_colors", "signed_colors", "colorbar", "nice_ceil_mm"]

_NAN_GREY = np.array([150, 150, 150], dtype=np.uint8)


def error_colors(err: np.ndarray, vmax: float) -> np.ndarray:
    """(…) errors in m -> (…, 3) uint8 RGB on viridis over [0, vmax]; NaN -> grey."""
    from matplotlib import colormaps

    cmap = colormaps["viridis"]
    x = np.clip(np.nan_to_num(err / max(vmax, 1e-12), nan=0.0), 0.0, 1.0)
    rgb = (cmap(x)[..., :3] * 255).astype(np.uint8)
    rgb[~np.isfinite(err)] = _NAN_GREY
    return rgb


def signed_colors(value: np.ndarray, vmax: float) -> np.ndarray:
    """(…) signed values in m -> (…, 3) uint8 RGB on coolwarm over [-vmax, vmax] (blue
    negative, white zero, red positive); NaN -> grey."""
    from matplotlib import colormaps

    cmap = colormaps["coolwarm"]
    x = np.clip(0.5 + 0.5 * np.nan_to_num(value / max(vmax, 1e-12), nan=0.0), 0.0, 1.0)
    rgb = (cmap(x)[..., :3] * 255).astype(np.uint8)
    rgb[~np.isfinite(value)] = _NAN_GREY
    return rgb


def colorbar(width: int = 256, height: int = 16, signed: bool = False) -> np.ndarray:
    """(height, width, 3) uint8 ramp: viridis, left = 0; or (``signed``) coolwarm, left = -max."""
    ramp = signed_colors(np.linspace(-1.0, 1.0, width), 1.0) if signed else error_colors(np.linspace(0.0, 1.0, width), 1.0)
    return np.repeat(ramp[None, :, :], height, axis=0)


def nice_ceil_mm(x_m: float) -> float:
    """Round a positive length (m) up to 1, 2 or 5 x 10^k mm; returned in m."""
    mm = max(x_m * 1e3, 1e-3)
    k = np.floor(np.log10(mm))
    for m in (1.0, 2.0, 5.0, 10.0):
        if mm <= m * 10**k:
            return float(m * 10**k * 1e-3)
    return float(10 ** (k + 1) * 1e-3)


@dataclass(frozen=True)
class ViewerCallbacks:
    """What the viewer may ask of the server.

    Attributes:
        runs: ``() -> [(run_id, label)]`` finished replay runs.
        load_run: ``(run_id) -> RunArrays``.
        sessions: ``() -> [(session_id, label)]``.
        icp_inputs: ``(session_id) -> (reference_camera (N, 3), rest_surface (P, 3), size (3,))`` m.
        icp_preview: ``(session_id, points_camera (K, 3), points_phantom (K, 3)) -> dict``
            with ``T_init``, ``T_phantom_camera``, ``rms_init``, ``rms``, ``fitness``.
        icp_accept: same arguments; saves the calibration; returns the stored dict.
        load_plan: ``(job_id) -> dict`` a plan job's ``plan_view.json``
            (:mod:`app.viewer.plan_data`), or None (no plans).
    """

    runs: Callable[[], list[tuple[int, str]]]
    load_run: Callable[[int], RunArrays]
    sessions: Callable[[], list[tuple[int, str]]]
    icp_inputs: Callable[[int], tuple[np.ndarray, np.ndarray, np.ndarray]]
    icp_preview: Callable[[int, np.ndarray, np.ndarray], dict]
    icp_accept: Callable[[int, np.ndarray, np.ndarray], dict]
    load_plan: Callable[[int], dict] | None = None


class SequenceView:
    """Per-sequence display buffers, made once when the sequence is first shown.

    The FEM layer is coloured by a *colour mode*: ``"error"`` (per-vertex error, viridis)
    or, for a diagnose run, ``"base_residual"`` / ``"extended_residual"`` (the systematic
    signed residual of the base / extended model, the latter drawn on the extended mesh)
    and ``"change_<kind>"`` (what that claimed cause alone changes of the surface), signed
    on coolwarm (:meth:`colour_modes`).
    """

    def __init__(self, seq: SequenceArrays):
        self.seq = seq
        finite = seq.vertex_error[np.isfinite(seq.vertex_error)]
        self.vmax = nice_ceil_mm(float(np.percentile(finite, 95)) if finite.size else 1e-3)
        self.colors = error_colors(seq.vertex_error, self.vmax)
        self.corrected_colors = None
        if seq.corrected_positions is not None:
            err = seq.corrected_vertex_error
            self.corrected_colors = (error_colors(err, self.vmax) if err is not None
                                     else np.tile(np.array([255, 140, 0], np.uint8), (*seq.corrected_positions.shape[:2], 1)))
        self._glb: dict[tuple[str, int, str], bytes] = {}
        self._signed: dict[str, tuple[np.ndarray, float]] = {}

    def colour_modes(self) -> list[str]:
        """The colour modes this sequence has: ``"error"``, then its diagnosis layers."""
        d = self.seq.diagnosis
        if d is None:
            return ["error"]
        modes = ["error", "base_residual"]
        if d.extended_residual is not None and self.seq.corrected_positions is not None:
            modes.append("extended_residual")
        return modes + [f"change_{k}" for k in d.changes]

    def signed_layer(self, mode: str) -> tuple[np.ndarray, float]:
        """(values (F, N) or (N,), m; legend bound vmax, m) of a signed colour mode.

        Raises:
            KeyError: the sequence has no such layer.
        """
        if mode not in self._signed:
            d = self.seq.diagnosis
            if d is None or mode not in self.colour_modes() or mode == "error":
                raise KeyError(f"sequence {self.seq.name!r} has no colour mode {mode!r}; it has {self.colour_modes()}")
            values = (d.base_residual if mode == "base_residual" else d.extended_residual if mode == "extended_residual"
                      else d.changes[mode[len("change_"):]])
            scaled = values  # the residuals of both models share one scale, to compare them
            if mode in ("base_residual", "extended_residual") and d.extended_residual is not None:
                scaled = np.concatenate([d.base_residual, d.extended_residual])
            finite = np.abs(scaled[np.isfinite(scaled)])
            bound = max(float(np.percentile(finite, 90)) if finite.size else 0.0, 1e-5)
            self._signed[mode] = (values, nice_ceil_mm(bound))
        return self._signed[mode]

    def glb(self, which: str, f: int, mode: str = "error") -> bytes:
        """GLB bytes of the raw (``"fem"``) or corrected mesh at frame ``f`` (cached), the
        raw one coloured by colour ``mode`` (the ``"extended_residual"`` mode draws the
        extended mesh)."""
        key = (which, f, mode if which == "fem" else "error")
        if key not in self._glb:
            import trimesh

            if which == "fem" and mode != "error":
                values, vmax = self.signed_layer(mode)
                col = signed_colors(values[f] if values.ndim == 2 else values, vmax)
                pos = self.seq.corrected_positions[f] if mode == "extended_residual" else self.seq.positions[f]
            else:
                pos = self.seq.positions[f] if which == "fem" else self.seq.corrected_positions[f]
                col = self.colors[f] if which == "fem" else self.corrected_colors[f]
            rgba = np.concatenate([col, np.full((col.shape[0], 1), 255, np.uint8)], axis=1)
            mesh = trimesh.Trimesh(np.nan_to_num(pos), self.seq.faces, vertex_colors=rgba, process=False)
            with io.BytesIO() as buf:
                mesh.export(buf, file_type="glb")
                self._glb[key] = buf.getvalue()
        return self._glb[key]


class SharedRuns:
    """What every browser tab shares: runs loaded once, per-sequence display buffers (colours
    and the GLB of each frame, encoded once), ICP inputs of a session. The last few runs and
    sessions are kept (least recently used first out), so memory stays bounded."""

    def __init__(self, callbacks: ViewerCallbacks, keep: int = 3):
        from collections import OrderedDict

        self.cb = callbacks
        self.keep = keep
        self._lock = threading.RLock()
        self._runs: OrderedDict[int, RunArrays] = OrderedDict()
        self._views: dict[tuple[int, str], SequenceView] = {}
        self._icp: OrderedDict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = OrderedDict()

    def run(self, run_id: int) -> RunArrays:
        """The run's arrays, loaded on first use. Raises whatever ``load_run`` raises."""
        with self._lock:
            if run_id not in self._runs:
                self._runs[run_id] = self.cb.load_run(run_id)
                while len(self._runs) > self.keep:
                    old, _ = self._runs.popitem(last=False)
                    self._views = {k: v for k, v in self._views.items() if k[0] != old}
            self._runs.move_to_end(run_id)
            return self._runs[run_id]

    def view(self, run_id: int, sequence: str | None) -> SequenceView:
        """Display buffers of ``sequence`` (default: the run's first) of run ``run_id``.

        Raises:
            KeyError: the run has no such sequence.
        """
        with self._lock:
            run = self.run(run_id)
            name = sequence or next(iter(run.sequences))
            if name not in run.sequences:
                raise KeyError(f"run {run_id} has no sequence {name!r}; it has {list(run.sequences)}")
            if (run_id, name) not in self._views:
                self._views[(run_id, name)] = SequenceView(run.sequences[name])
            return self._views[(run_id, name)]

    def icp_inputs(self, session_id: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        with self._lock:
            if session_id not in self._icp:
                self._icp[session_id] = self.cb.icp_inputs(session_id)
                while len(self._icp) > self.keep:
                    self._icp.popitem(last=False)
            self._icp.move_to_end(session_id)
            return self._icp[session_id]
