"""The workbench's 3D viewer (viser, its own port; the dashboard embeds it in an iframe).

It only consumes: arrays (:class:`app.viewer.data.RunArrays`) and callbacks given by
the server (list runs, load a run, list sessions, ICP inputs, preview, accept). It never
reaches into solvers. GUI building is split into ``_populate_*`` functions per tab
(nerfstudio's habit).

Every browser tab has its own GUI and scene (viser's per-client ``client.gui`` and
``client.scene``, built when the tab connects): its run, sequence, frame, playback,
layer toggles and ICP picks are its own. What all tabs share is read-only: the loaded
runs and the encoded mesh frames. The server-side calls (the dashboard's "view" and
"ICP init" buttons, over REST) act on every open tab and set what a new tab opens with.

Replay tab: the cleaned measured cloud, the raw FEM mesh surface coloured by per-vertex
error (legend in mm), the corrected mesh when the run has one, the probe sphere; layer
toggles; a timeline slider, play/pause, -1/+1 frame, frame number and time. A run is
loaded once; moving the slider swaps buffers (mesh GLBs are encoded once per frame and
cached).

ICP tab: pick K >= 3 points on the reference cloud (shown from the depth camera's own
viewpoint, camera frame) and the matching points on the phantom's rest surface
(phantom frame); *Compute* runs Kabsch + ICP through the server's callback and shows
the reference cloud before (Kabsch, orange) and after (ICP, green) on the rest
surface with the residuals; *Accept* saves the session's calibration.
"""

from __future__ import annotations

import io
import logging
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from app.viewer.data import RunArrays, SequenceArrays

__all__ = ["ViewerCallbacks", "WorkbenchViewer", "error_colors", "colorbar"]

_NAN_GREY = np.array([150, 150, 150], dtype=np.uint8)
log = logging.getLogger(__name__)


def error_colors(err: np.ndarray, vmax: float) -> np.ndarray:
    """(…) errors in m -> (…, 3) uint8 RGB on viridis over [0, vmax]; NaN -> grey."""
    from matplotlib import colormaps

    cmap = colormaps["viridis"]
    x = np.clip(np.nan_to_num(err / max(vmax, 1e-12), nan=0.0), 0.0, 1.0)
    rgb = (cmap(x)[..., :3] * 255).astype(np.uint8)
    rgb[~np.isfinite(err)] = _NAN_GREY
    return rgb


def colorbar(width: int = 256, height: int = 16) -> np.ndarray:
    """(height, width, 3) uint8 viridis ramp, left = 0."""
    ramp = error_colors(np.linspace(0.0, 1.0, width), 1.0)
    return np.repeat(ramp[None, :, :], height, axis=0)


def _nice_ceil_mm(x_m: float) -> float:
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
    """

    runs: Callable[[], list[tuple[int, str]]]
    load_run: Callable[[int], RunArrays]
    sessions: Callable[[], list[tuple[int, str]]]
    icp_inputs: Callable[[int], tuple[np.ndarray, np.ndarray, np.ndarray]]
    icp_preview: Callable[[int, np.ndarray, np.ndarray], dict]
    icp_accept: Callable[[int, np.ndarray, np.ndarray], dict]


class _SequenceView:
    """Per-sequence display buffers, made once when the sequence is first shown."""

    def __init__(self, seq: SequenceArrays):
        self.seq = seq
        finite = seq.vertex_error[np.isfinite(seq.vertex_error)]
        self.vmax = _nice_ceil_mm(float(np.percentile(finite, 95)) if finite.size else 1e-3)
        self.colors = error_colors(seq.vertex_error, self.vmax)
        self.corrected_colors = None
        if seq.corrected_positions is not None:
            err = seq.corrected_vertex_error
            self.corrected_colors = (error_colors(err, self.vmax) if err is not None
                                     else np.tile(np.array([255, 140, 0], np.uint8), (*seq.corrected_positions.shape[:2], 1)))
        self._glb: dict[tuple[str, int], bytes] = {}

    def glb(self, which: str, f: int) -> bytes:
        """GLB bytes of the raw (``"fem"``) or corrected mesh at frame ``f`` (cached)."""
        key = (which, f)
        if key not in self._glb:
            import trimesh

            pos = self.seq.positions[f] if which == "fem" else self.seq.corrected_positions[f]
            col = self.colors[f] if which == "fem" else self.corrected_colors[f]
            rgba = np.concatenate([col, np.full((col.shape[0], 1), 255, np.uint8)], axis=1)
            mesh = trimesh.Trimesh(np.nan_to_num(pos), self.seq.faces, vertex_colors=rgba, process=False)
            with io.BytesIO() as buf:
                mesh.export(buf, file_type="glb")
                self._glb[key] = buf.getvalue()
        return self._glb[key]


class _Shared:
    """What every browser tab shares: runs loaded once, per-sequence display buffers (colours
    and the GLB of each frame, encoded once), ICP inputs of a session. The last few runs and
    sessions are kept (least recently used first out), so memory stays bounded."""

    def __init__(self, callbacks: ViewerCallbacks, keep: int = 3):
        from collections import OrderedDict

        self.cb = callbacks
        self.keep = keep
        self._lock = threading.RLock()
        self._runs: OrderedDict[int, RunArrays] = OrderedDict()
        self._views: dict[tuple[int, str], _SequenceView] = {}
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

    def view(self, run_id: int, sequence: str | None) -> _SequenceView:
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
                self._views[(run_id, name)] = _SequenceView(run.sequences[name])
            return self._views[(run_id, name)]

    def icp_inputs(self, session_id: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        with self._lock:
            if session_id not in self._icp:
                self._icp[session_id] = self.cb.icp_inputs(session_id)
                while len(self._icp) > self.keep:
                    self._icp.popitem(last=False)
            self._icp.move_to_end(session_id)
            return self._icp[session_id]


class _TabView:
    """One browser tab (one viser client): its own GUI, scene nodes, camera and selection
    (run, sequence, frame, playback, layers, ICP picks), built with ``client.gui`` and
    ``client.scene`` when the tab connects. Choices made in one tab never change another."""

    def __init__(self, shared: _Shared, client):
        self.shared = shared
        self.cb = shared.cb
        self.client = client
        self._lock = threading.RLock()
        self._mute = False
        self.mode = "replay"
        self.run_id: int | None = None
        self.run: RunArrays | None = None
        self.view: _SequenceView | None = None
        self.frame = 0
        self.playing = False
        self._next_tick = 0.0
        self.icp: dict[str, Any] = {"session_id": None, "pick_on": "reference", "picks_reference": [],
                                    "picks_phantom": [], "result": None, "accepted": None, "error": None}
        self._icp_data: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._handles: dict[str, Any] = {}
        scene = client.scene
        self._replay_root = scene.add_frame("/replay", show_axes=False)
        self._icp_root = scene.add_frame("/icp", show_axes=False, visible=False)
        tabs = client.gui.add_tab_group()
        self._populate_replay(tabs.add_tab("Replay"))
        self._populate_icp(tabs.add_tab("ICP init"))
        scene.on_click()(self._on_click)

    # ------------------------------------------------------------------ GUI
    def _populate_replay(self, tab) -> None:
        gui = self.client.gui
        with tab:
            self.gui_run = gui.add_dropdown("Run", options=("(none)",), initial_value="(none)")
            self.gui_sequence = gui.add_dropdown("Sequence", options=("(none)",), initial_value="(none)")
            self.gui_refresh = gui.add_button("Refresh runs")
            self.gui_cloud = gui.add_checkbox("Measured cloud", True)
            self.gui_fem = gui.add_checkbox("FEM mesh", True)
            self.gui_corrected = gui.add_checkbox("Corrected mesh", True, disabled=True)
            self.gui_probe = gui.add_checkbox("Probe", True)
            self.gui_frame = gui.add_slider("Frame", min=0, max=1, step=1, initial_value=0, disabled=True)
            self.gui_play = gui.add_button("Play / pause")
            self.gui_prev = gui.add_button("-1 frame")
            self.gui_next = gui.add_button("+1 frame")
            self.gui_info = gui.add_markdown("No run loaded. Finish a replay job, then pick it here or press *view* in the dashboard.")
            self.gui_legend = gui.add_image(colorbar(), label="error (mm)", format="png")
            self.gui_legend_text = gui.add_markdown("per-vertex error: 0 mm (left) to - mm (right); grey: no measured point")

        self.gui_refresh.on_click(lambda _e: self.refresh_runs())
        self.gui_run.on_update(lambda _e: None if self._mute else self._on_run_selected())
        self.gui_sequence.on_update(lambda _e: None if self._mute else self._on_sequence_selected())
        for box in (self.gui_cloud, self.gui_fem, self.gui_corrected, self.gui_probe):
            box.on_update(lambda _e: self._apply_visibility())
        self.gui_frame.on_update(lambda _e: None if self._mute else self.set_frame(int(self.gui_frame.value)))
        self.gui_play.on_click(lambda _e: self.toggle_play())
        self.gui_prev.on_click(lambda _e: self.step(-1))
        self.gui_next.on_click(lambda _e: self.step(+1))
        self.refresh_runs()

    def _populate_icp(self, tab) -> None:
        gui = self.client.gui
        with tab:
            self.gui_session = gui.add_dropdown("Session", options=("(none)",), initial_value="(none)")
            self.gui_load_session = gui.add_button("Load session")
            self.gui_pick_on = gui.add_button_group("Pick on", options=("reference cloud", "phantom surface"))
            self.gui_picks = gui.add_markdown("picks: reference 0, phantom 0")
            self.gui_undo = gui.add_button("Undo last pick")
            self.gui_clear = gui.add_button("Clear picks")
            self.gui_compute = gui.add_button("Compute ICP")
            self.gui_accept = gui.add_button("Accept calibration")
            self.gui_back = gui.add_button("Back to replay")
            self.gui_icp_info = gui.add_markdown("Load a session, click >= 3 points on the reference cloud, then the "
                                                 "matching points on the phantom surface, in the same order.")
        self.gui_load_session.on_click(lambda _e: self._on_load_session())
        self.gui_pick_on.on_click(lambda e: self.set_pick_on("reference" if e.target.value.startswith("reference") else "phantom"))
        self.gui_undo.on_click(lambda _e: self._undo_pick())
        self.gui_clear.on_click(lambda _e: self._clear_picks())
        self.gui_compute.on_click(lambda _e: self.compute_icp())
        self.gui_accept.on_click(lambda _e: self.accept_icp())
        self.gui_back.on_click(lambda _e: self._set_mode("replay"))
        self._refresh_sessions()

    # ------------------------------------------------------------------ replay
    def refresh_runs(self) -> None:
        """Reload the run list (finished runs from the server) into this tab's dropdown."""
        runs = self.cb.runs()
        options = tuple(f"{rid}: {label}" for rid, label in runs) or ("(none)",)
        with self._lock:
            self._mute = True
            try:
                current = self.gui_run.value
                self.gui_run.options = options
                self.gui_run.value = current if current in options else options[0]
            finally:
                self._mute = False

    def _on_run_selected(self) -> None:
        value = self.gui_run.value
        if value and value[0].isdigit():
            self.show_run(int(value.split(":", 1)[0]))

    def _on_sequence_selected(self) -> None:
        if self.run is not None and self.gui_sequence.value in self.run.sequences:
            self.show_run(self.run_id, self.gui_sequence.value)

    def show_run(self, run_id: int, sequence: str | None = None, frame: int = 0) -> None:
        """Show ``sequence`` (default: the first) of run ``run_id`` at ``frame`` in this tab.

        Raises:
            KeyError: the run has no such sequence. Whatever ``load_run`` raises.
        """
        with self._lock:
            view = self.shared.view(run_id, sequence)
            self.run, self.run_id, self.view = self.shared.run(run_id), run_id, view
            self.playing = False
            self._mute = True
            try:
                self.refresh_runs()
                self._mute = True
                label = next((o for o in self.gui_run.options if o.startswith(f"{run_id}:")), None)
                if label:
                    self.gui_run.value = label
                self.gui_sequence.options = tuple(self.run.sequences)
                self.gui_sequence.value = view.seq.name
                n = view.seq.n_frames
                self.gui_frame.max = max(n - 1, 1)
                self.gui_frame.disabled = n < 2
                self.gui_corrected.disabled = view.seq.corrected_positions is None
            finally:
                self._mute = False
            self.gui_legend_text.content = (f"per-vertex error: 0 mm (left) to {view.vmax * 1e3:g} mm (right); "
                                            "grey: no measured point")
            self._build_replay_nodes()
            self._set_mode("replay")
            self.set_frame(frame)

    def _build_replay_nodes(self) -> None:
        scene = self.client.scene
        seq = self.view.seq
        for key in ("cloud", "fem", "corrected", "probe"):
            h = self._handles.pop(key, None)
            if h is not None:
                h.remove()
        self._handles["cloud"] = scene.add_point_cloud(
            "/replay/cloud", seq.cloud(0), colors=(90, 170, 255), point_size=0.0012, precision="float32", point_shape="circle")
        self._handles["fem"] = scene.add_glb("/replay/fem", self.view.glb("fem", 0))
        if seq.corrected_positions is not None:
            self._handles["corrected"] = scene.add_glb("/replay/corrected", self.view.glb("corrected", 0))
        self._handles["probe"] = scene.add_icosphere(
            "/replay/probe", radius=seq.probe_radius, color=(220, 60, 60), position=tuple(float(v) for v in seq.probe_centres[0]))
        self._apply_visibility()
        self._frame(seq.positions[0], (0.0, -0.16, 0.12))

    def _apply_visibility(self) -> None:
        for key, box in (("cloud", self.gui_cloud), ("fem", self.gui_fem), ("corrected", self.gui_corrected), ("probe", self.gui_probe)):
            h = self._handles.get(key)
            if h is not None:
                h.visible = bool(box.value)

    def set_frame(self, f: int) -> None:
        """Show frame ``f`` (clipped to the sequence): swap the cloud, mesh and probe buffers."""
        with self._lock:
            if self.view is None:
                return
            seq = self.view.seq
            f = int(np.clip(f, 0, seq.n_frames - 1))
            self.frame = f
            self._handles["cloud"].points = seq.cloud(f)
            self._handles["fem"].glb_data = self.view.glb("fem", f)
            if "corrected" in self._handles:
                self._handles["corrected"].glb_data = self.view.glb("corrected", f)
            self._handles["probe"].position = tuple(float(v) for v in seq.probe_centres[f])
            err = seq.frame_errors[f]
            self.gui_info.content = (f"**frame** {f} / {seq.n_frames - 1} &nbsp; **t** {seq.times[f]:.3f} s &nbsp; "
                                     f"**mean error** {err * 1e3:.3f} mm &nbsp; ({seq.name}, {seq.role})")
            if int(self.gui_frame.value) != f:
                self._mute = True
                try:
                    self.gui_frame.value = f
                finally:
                    self._mute = False

    def step(self, delta: int) -> None:
        """Move by ``delta`` frames (pauses playback)."""
        self.playing = False
        self.set_frame(self.frame + delta)

    def toggle_play(self) -> None:
        self.playing = not self.playing and self.view is not None
        self._next_tick = time.monotonic()

    def tick(self, now: float) -> None:
        """Advance one frame when playing and the frame's time step has passed (the player thread)."""
        if not self.playing or self.view is None or now < self._next_tick:
            return
        seq = self.view.seq
        dt = float(np.median(np.diff(seq.times))) if seq.n_frames > 1 else 0.1
        self._next_tick = now + max(dt, 0.02)
        self.set_frame((self.frame + 1) % seq.n_frames)

    # ------------------------------------------------------------------ ICP
    def _refresh_sessions(self) -> None:
        options = tuple(f"{sid}: {label}" for sid, label in self.cb.sessions()) or ("(none)",)
        current = self.gui_session.value
        self.gui_session.options = options
        self.gui_session.value = current if current in options else options[0]

    def _on_load_session(self) -> None:
        value = self.gui_session.value
        if value and value[0].isdigit():
            self.start_icp(int(value.split(":", 1)[0]))

    def start_icp(self, session_id: int) -> None:
        """Enter picking mode on a session: show its reference cloud from the camera's viewpoint."""
        with self._lock:
            self._icp_data = self.shared.icp_inputs(session_id)
            ref, surface, _ = self._icp_data
            self.icp.update(session_id=session_id, picks_reference=[], picks_phantom=[], result=None, accepted=None, error=None)
            self._refresh_sessions()
            label = next((o for o in self.gui_session.options if o.startswith(f"{session_id}:")), None)
            if label:
                self.gui_session.value = label
            scene = self.client.scene
            finite = ref[np.all(np.isfinite(ref), axis=1)]
            depth = finite[:, 2]
            shade = np.clip((depth - depth.min()) / max(np.ptp(depth), 1e-9), 0, 1)
            grey = (230 - 130 * shade).astype(np.uint8)
            self._handles["icp_reference"] = scene.add_point_cloud(
                "/icp/reference", finite.astype(np.float32), colors=np.stack([grey, grey, grey], 1),
                point_size=0.0015, precision="float32")
            self._handles["icp_surface"] = scene.add_point_cloud(
                "/icp/surface", surface.astype(np.float32), colors=(120, 200, 140), point_size=0.0012, precision="float32")
            for key in ("icp_before", "icp_after"):
                h = self._handles.pop(key, None)
                if h is not None:
                    h.remove()
            self._draw_picks()
            self._set_mode("icp")
            self.set_pick_on("reference")

    def set_pick_on(self, which: str) -> None:
        """Pick on ``"reference"`` (camera frame, seen from the camera) or ``"phantom"``."""
        if which not in ("reference", "phantom"):
            raise ValueError(f"pick on 'reference' or 'phantom', got {which!r}")
        with self._lock:
            self.icp["pick_on"] = which
            if self._icp_data is None:
                return
            ref, surface, size = self._icp_data
            self._handles["icp_reference"].visible = which == "reference"
            self._handles["icp_surface"].visible = which == "phantom"
            for key in ("icp_before", "icp_after"):
                if key in self._handles:
                    self._handles[key].visible = False
            self._handles["picks_reference"].visible = which == "reference"
            self._handles["picks_phantom"].visible = which == "phantom"
            if which == "reference":
                finite = ref[np.all(np.isfinite(ref), axis=1)]
                self._set_camera(position=(0.0, 0.0, 0.0), look_at=np.median(finite, axis=0), up=(0.0, -1.0, 0.0))
            else:
                self._frame_box(size)

    def _frame_box(self, size) -> None:
        """Frame the phantom box of ``size`` (3,) m, from the front and above."""
        sx, sy, sz = (float(v) for v in size)
        corners = np.array([[x, y, z] for x in (0.0, sx) for y in (0.0, sy) for z in (0.0, sz)])
        self._frame(corners, (0.0, -0.12, 0.16))

    def _frame(self, points: np.ndarray, direction) -> None:
        """Point the tab's camera at ``points`` (N, 3) m from ``direction`` (3,) (any length)
        at the distance where their bounding sphere fills about 70 % of the view's height
        (the camera's vertical field of view; 0.2 m used to leave a 69 mm phantom at a fifth)."""
        pts = np.asarray(points, float).reshape(-1, 3)
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        if pts.size == 0:
            return
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        centre, radius = 0.5 * (lo + hi), max(0.5 * float(np.linalg.norm(hi - lo)), 1e-3)
        try:
            fov = float(self.client.camera.fov)
        except Exception:  # noqa: BLE001 - a camera not yet reported by the browser
            fov = 1.3
        d = radius / (0.7 * np.tan(0.5 * fov))
        u = np.asarray(direction, float) / np.linalg.norm(direction)
        self._set_camera(position=centre + d * u, look_at=centre, up=(0.0, 0.0, 1.0))

    def _set_camera(self, position, look_at, up) -> None:
        camera = self.client.camera
        camera.up_direction = tuple(float(v) for v in up)
        camera.position = tuple(float(v) for v in position)
        camera.look_at = tuple(float(v) for v in look_at)

    def _on_click(self, event) -> None:
        if self.mode != "icp" or self._icp_data is None:
            return
        self.pick_ray(np.asarray(event.ray_origin, float), np.asarray(event.ray_direction, float))

    def pick_ray(self, origin: np.ndarray, direction: np.ndarray) -> np.ndarray | None:
        """Add the point nearest to a ray (front-most surface) on the active cloud.

        Args:
            origin, direction: (3,) the click ray in world coordinates (the active cloud's frame).

        Returns:
            the picked (3,) point, m, or None when the ray passes no point within
            ~0.6 degrees (about 7 pixels).
        """
        with self._lock:
            ref, surface, _ = self._icp_data
            which = self.icp["pick_on"]
            pts = ref[np.all(np.isfinite(ref), axis=1)] if which == "reference" else surface
            d = direction / np.linalg.norm(direction)
            v = pts - origin
            t = v @ d
            perp = np.linalg.norm(v - t[:, None] * d, axis=1)
            ok = (t > 0) & (perp < np.maximum(0.002, 0.01 * t))
            if not ok.any():
                self.gui_icp_info.content = "missed: click on a point of the cloud"
                return None
            idx = np.flatnonzero(ok)
            front = idx[t[idx] < t[idx].min() + 0.005]
            best = front[np.argmin(perp[front])]
            p = pts[best].astype(float)
            self.icp["picks_" + which].append(p.tolist())
            self.icp["result"] = None
            self._draw_picks()
            return p

    def _draw_picks(self) -> None:
        scene = self.client.scene
        for which, color in (("reference", (255, 40, 40)), ("phantom", (255, 40, 200))):
            pts = np.asarray(self.icp["picks_" + which], dtype=np.float32).reshape(-1, 3)
            visible = self.icp["pick_on"] == which and self.mode == "icp"
            self._handles["picks_" + which] = scene.add_point_cloud(
                f"/icp/picks_{which}", pts if len(pts) else np.zeros((1, 3), np.float32), colors=color,
                point_size=0.005, precision="float32", point_shape="circle", visible=visible and len(pts) > 0)
        nr, npk = len(self.icp["picks_reference"]), len(self.icp["picks_phantom"])
        self.gui_picks.content = f"picks: reference {nr}, phantom {npk} (need >= 3 each, same order)"

    def _undo_pick(self) -> None:
        with self._lock:
            picks = self.icp["picks_" + self.icp["pick_on"]]
            if picks:
                picks.pop()
            self._draw_picks()

    def _clear_picks(self) -> None:
        with self._lock:
            self.icp.update(picks_reference=[], picks_phantom=[], result=None)
            self._draw_picks()

    def _pairs(self) -> tuple[np.ndarray, np.ndarray] | None:
        pc = np.asarray(self.icp["picks_reference"], float).reshape(-1, 3)
        pp = np.asarray(self.icp["picks_phantom"], float).reshape(-1, 3)
        if len(pc) < 3 or len(pc) != len(pp):
            self.gui_icp_info.content = f"need the same number (>= 3) of picks on both; have {len(pc)} and {len(pp)}"
            return None
        return pc, pp

    def compute_icp(self) -> dict | None:
        """Kabsch + ICP on the picks (server callback); shows before/after. None if it failed."""
        with self._lock:
            pairs = self._pairs()
            if pairs is None or self.icp["session_id"] is None:
                return None
            try:
                res = self.cb.icp_preview(self.icp["session_id"], *pairs)
            except Exception as exc:  # noqa: BLE001 - shown to the user, the viewer stays up
                self.icp.update(result=None, error=str(exc))
                self.gui_icp_info.content = f"**ICP failed:** {exc}"
                return None
            self.icp.update(result=res, error=None)
            ref, surface, _ = self._icp_data
            finite = ref[np.all(np.isfinite(ref), axis=1)]
            scene = self.client.scene
            for key, T, color in (("icp_before", res["T_init"], (255, 150, 30)), ("icp_after", res["T_phantom_camera"], (40, 200, 60))):
                T = np.asarray(T)
                q = finite @ T[:3, :3].T + T[:3, 3]
                keep = np.all(np.abs(q - q.mean(0)) < 0.2, axis=1)  # the neighbourhood of the phantom
                self._handles[key] = scene.add_point_cloud(f"/icp/{key}", q[keep].astype(np.float32), colors=color,
                                                           point_size=0.0012, precision="float32")
            self._handles["icp_reference"].visible = False
            self._handles["icp_surface"].visible = True
            self._handles["picks_reference"].visible = False
            self._handles["picks_phantom"].visible = False
            self.gui_icp_info.content = (
                f"**before** (Kabsch on picks, orange): rms {res['rms_init'] * 1e3:.2f} mm  \n"
                f"**after** (ICP, green): rms {res['rms'] * 1e3:.2f} mm, fitness {res['fitness']:.2f}  \n"
                "Accept to save the session's calibration.")
            self._frame_box(self._icp_data[2])
            return res

    def accept_icp(self) -> dict | None:
        """Save the calibration through the server callback. None if it failed."""
        with self._lock:
            pairs = self._pairs()
            if pairs is None or self.icp["session_id"] is None:
                return None
            try:
                stored = self.cb.icp_accept(self.icp["session_id"], *pairs)
            except Exception as exc:  # noqa: BLE001
                self.icp["error"] = str(exc)
                self.gui_icp_info.content = f"**not saved:** {exc}"
                return None
            self.icp["accepted"] = stored
            self.gui_icp_info.content = (f"**saved** calibration/picked.json: ICP rms {stored['rms'] * 1e3:.2f} mm. "
                                         "New replay, sweep and fit jobs of this session use it.")
            return stored

    # ------------------------------------------------------------------ state
    def _set_mode(self, mode: str) -> None:
        self.mode = mode
        self._replay_root.visible = mode == "replay"
        self._icp_root.visible = mode == "icp"
        if mode == "replay" and self.view is not None:
            self._frame(self.view.seq.positions[self.frame], (0.0, -0.16, 0.12))

    def visible(self) -> dict[str, bool]:
        """This tab's layer toggles: cloud, fem, corrected, probe."""
        return {k: bool(box.value) for k, box in (("cloud", self.gui_cloud), ("fem", self.gui_fem),
                                                  ("corrected", self.gui_corrected), ("probe", self.gui_probe))}

    def state(self) -> dict:
        """JSON-able state of this tab: mode, run, sequence, frame, time, layers, playback, picks, camera."""
        with self._lock:
            seq = self.view.seq if self.view is not None else None
            c = self.client.camera
            cam = {"position": np.asarray(c.position).tolist(), "look_at": np.asarray(c.look_at).tolist(),
                   "up": np.asarray(c.up_direction).tolist(), "fov": float(c.fov), "aspect": float(c.aspect)}
            return {
                "client_id": int(self.client.client_id),
                "mode": self.mode,
                **_seq_state(self.run_id, self.run, seq, self.frame),
                "visible": self.visible(),
                "playing": self.playing,
                "camera": cam,
                "icp": dict(self.icp),
            }


def _seq_state(run_id: int | None, run: RunArrays | None, seq: SequenceArrays | None, frame: int) -> dict:
    return {
        "run_id": run_id,
        "sequence": seq.name if seq else None,
        "sequences": list(run.sequences) if run else [],
        "frame": frame,
        "n_frames": seq.n_frames if seq else 0,
        "layers": ([k for k, has in (("cloud", True), ("fem", True), ("corrected", seq.corrected_positions is not None),
                                     ("probe", True)) if has] if seq else []),
        "time": float(seq.times[frame]) if seq else None,
    }


class WorkbenchViewer:
    """A viser server with the replay and ICP tabs, one independent view per browser tab.

    Each tab that connects gets its own GUI and scene (viser's ``client.gui`` and
    ``client.scene``): picking a run, a sequence, a frame, a layer or ICP points in one tab
    leaves the others alone. Runs are loaded, and mesh frames encoded, once for all tabs.

    The server-side methods (:meth:`show_run`, :meth:`set_frame`, :meth:`start_icp`; the
    dashboard's REST calls) act on every open tab, as a remote control, and set what a tab
    that connects later starts with.

    Args:
        callbacks: see :class:`ViewerCallbacks`.
        host, port: where viser listens (the next free port is taken if busy; see ``port``).
    """

    def __init__(self, callbacks: ViewerCallbacks, host: str = "127.0.0.1", port: int = 8081):
        import viser

        self.cb = callbacks
        self.shared = _Shared(callbacks)
        self.server = viser.ViserServer(host=host, port=port, label="Tissue Twin", verbose=False)
        self.port = int(self.server.get_port())
        self.server.scene.set_up_direction("+z")
        self._lock = threading.RLock()
        self._tabs: dict[int, _TabView] = {}
        self.shown: dict[str, Any] = {"run_id": None, "sequence": None, "frame": 0}
        """What a new tab starts with: the run, sequence and frame last shown from the server side."""
        self.first_frame_seconds: float | None = None
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)
        self._stop = threading.Event()
        self._player = threading.Thread(target=self._play_loop, name="viewer-play", daemon=True)
        self._player.start()

    def _connect(self, client) -> None:
        tab = _TabView(self.shared, client)
        with self._lock:
            self._tabs[int(client.client_id)] = tab
            shown = dict(self.shown)
        if shown["run_id"] is not None:
            try:
                tab.show_run(shown["run_id"], shown["sequence"], shown["frame"])
            except Exception as exc:  # noqa: BLE001 - e.g. the run's files were removed; the tab still opens
                tab.gui_info.content = f"could not show run {shown['run_id']}: {exc}"

    def _disconnect(self, client) -> None:
        with self._lock:
            self._tabs.pop(int(client.client_id), None)

    def tabs(self) -> list[_TabView]:
        """The open tabs, oldest first."""
        with self._lock:
            return list(self._tabs.values())

    def show_run(self, run_id: int, sequence: str | None = None) -> None:
        """Show ``sequence`` (default: the run's first) of run ``run_id`` at frame 0 in every
        open tab and in tabs opened later; the run's arrays are loaded on first use and kept.

        Raises:
            KeyError: the run has no such sequence. Whatever ``load_run`` raises.
        """
        t0 = time.perf_counter()
        view = self.shared.view(run_id, sequence)
        view.glb("fem", 0)
        if view.seq.corrected_positions is not None:
            view.glb("corrected", 0)
        with self._lock:
            self.shown = {"run_id": run_id, "sequence": view.seq.name, "frame": 0}
        self._each_tab(lambda tab: tab.show_run(run_id, view.seq.name))
        self.first_frame_seconds = time.perf_counter() - t0

    def set_frame(self, f: int) -> None:
        """Show frame ``f`` (clipped to the sequence) in every open tab and in later ones."""
        with self._lock:
            if self.shown["run_id"] is None:
                return
            n = self.shared.view(self.shown["run_id"], self.shown["sequence"]).seq.n_frames
            self.shown["frame"] = int(np.clip(f, 0, n - 1))
        self._each_tab(lambda tab: tab.set_frame(f))

    def start_icp(self, session_id: int) -> None:
        """Open the picking mode on a session's reference cloud in every open tab."""
        self.shared.icp_inputs(session_id)  # raises here, once, if the session cannot be read
        self._each_tab(lambda tab: tab.start_icp(session_id))

    def _each_tab(self, action: Callable[[_TabView], None]) -> None:
        """Apply ``action`` to every open tab; a tab closing meanwhile does not stop the others."""
        for tab in self.tabs():
            try:
                action(tab)
            except Exception:  # noqa: BLE001 - logged; the remote control still reaches the other tabs
                log.exception("viewer tab %s could not follow the server", tab.client.client_id)

    def _play_loop(self) -> None:
        while not self._stop.wait(0.02):
            now = time.monotonic()
            for tab in self.tabs():
                try:
                    tab.tick(now)
                except Exception:  # noqa: BLE001 - a tab that went away mid-frame
                    tab.playing = False

    def state(self) -> dict:
        """JSON-able state: the newest open tab's (mode, run, sequence, frame, time, layers,
        visibility, playback, picks, camera) or, with no tab open, what a new tab would
        show; plus the port, the number of tabs, each tab's selection in ``tabs`` and the
        server-side time to the first frame of the last :meth:`show_run`."""
        tabs = self.tabs()
        if tabs:
            state = tabs[-1].state()
        else:
            with self._lock:
                shown = dict(self.shown)
            run = seq = None
            if shown["run_id"] is not None:
                run = self.shared.run(shown["run_id"])
                seq = self.shared.view(shown["run_id"], shown["sequence"]).seq
            state = {"client_id": None, "mode": "replay", **_seq_state(shown["run_id"], run, seq, shown["frame"]),
                     "playing": False, "camera": None,
                     "icp": {"session_id": None, "pick_on": "reference", "picks_reference": [], "picks_phantom": [],
                             "result": None, "accepted": None, "error": None}}
        state.update(port=self.port, clients=len(tabs), first_frame_seconds=self.first_frame_seconds,
                     tabs=[{"client_id": int(t.client.client_id), "mode": t.mode, "run_id": t.run_id,
                            "sequence": t.view.seq.name if t.view else None, "frame": t.frame,
                            "visible": t.visible()} for t in tabs])
        return state

    def stop(self) -> None:
        """Stop playback and the viser server."""
        self._stop.set()
        self._player.join(timeout=2)
        self.server.stop()
