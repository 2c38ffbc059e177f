"""The workbench's 3D viewer (viser, its own port; the dashboard embeds it in an iframe).

It only consumes: arrays (:class:`app.viewer.data.RunArrays`) and callbacks given by
the server (list runs, load a run, list sessions, ICP inputs, preview, accept). It never
reaches into solvers. GUI building is split into ``_populate_*`` functions per tab
(nerfstudio's habit).

Every browser tab has its own GUI and scene (viser's per-client ``client.gui`` and
``client.scene``, built when the tab connects): its run, sequence, frame, playback,
layer toggles and ICP picks are its own. What all tabs share is read-only: the loaded
runs and the encoded mesh frames. The server-side calls (the dashboard's "view" and
"ICP init" buttons, over REST) act on the viewer tab embedded in the dashboard tab that
pressed them (a token in the iframe's websocket path) and set what it opens with.

Replay tab: the cleaned measured cloud, the raw FEM mesh surface coloured by per-vertex
error (legend in mm), the corrected mesh when the run has one, the probe sphere; layer
toggles; a timeline slider, play/pause, -1/+1 frame, frame number and time. A run is
loaded once; moving the slider swaps buffers (mesh GLBs are encoded once per frame and
cached).

Diagnosis tab (a diagnose run's residuals, each claimed cause's change and geometry, the
answer per kind, the largest-error frames): :mod:`app.viewer.diagnosis_panel`. Plan tab
(a plan job's probe path over the phantom): :mod:`app.viewer.plan_panel`. ICP tab:
:mod:`app.viewer.icp_panel`. Shared buffers and colour maps: :mod:`app.viewer.buffers`.
"""

from __future__ import annotations

import logging
import re
import threading
import time
from typing import Any, Callable

import numpy as np

from app.viewer.buffers import SequenceView, SharedRuns, ViewerCallbacks, colorbar, error_colors
from app.viewer.data import RunArrays, SequenceArrays
from app.viewer.diagnosis_panel import DiagnosisPanel
from app.viewer.icp_panel import IcpPanel
from app.viewer.plan_panel import PlanPanel

__all__ = ["ViewerCallbacks", "WorkbenchViewer", "TabView", "error_colors", "colorbar"]

log = logging.getLogger(__name__)


class TabView(IcpPanel, DiagnosisPanel, PlanPanel):
    """One browser tab (one viser client): its own GUI, scene nodes, camera and selection
    (run, sequence, frame, playback, layers, ICP picks), built with ``client.gui`` and
    ``client.scene`` when the tab connects. Choices made in one tab never change another."""

    def __init__(self, shared: SharedRuns, client, token: str | None = None):
        self.shared = shared
        self.token = token
        """The token of the dashboard tab whose iframe this is (None: opened on its own)."""
        self.cb = shared.cb
        self.client = client
        self._lock = threading.RLock()
        self._mute = False
        self.mode = "replay"
        self.run_id: int | None = None
        self.run: RunArrays | None = None
        self.view: SequenceView | None = None
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
        self._plan_root = scene.add_frame("/plan", show_axes=False, visible=False)
        tabs = client.gui.add_tab_group()
        replay_tab, diagnosis_tab = tabs.add_tab("Replay"), tabs.add_tab("Diagnosis")
        plan_tab, icp_tab = tabs.add_tab("Plan"), tabs.add_tab("ICP init")
        self._populate_diagnosis(diagnosis_tab)
        self._populate_replay(replay_tab)
        self._populate_plan(plan_tab)
        self._populate_icp(icp_tab)
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
            self._reset_diagnosis()
            self._build_replay_nodes()
            self._set_mode("replay")
            self.set_frame(frame)

    def _build_replay_nodes(self) -> None:
        scene = self.client.scene
        seq = self.view.seq
        self._remove_geometry()
        for key in ("cloud", "fem", "corrected", "probe"):
            h = self._handles.pop(key, None)
            if h is not None:
                h.remove()
        self._handles["cloud"] = scene.add_point_cloud(
            "/replay/cloud", seq.cloud(0), colors=(90, 170, 255), point_size=0.0012, precision="float32", point_shape="circle")
        self._handles["fem"] = scene.add_glb("/replay/fem", self.view.glb("fem", 0, self.colour))
        if seq.corrected_positions is not None:
            self._handles["corrected"] = scene.add_glb("/replay/corrected", self.view.glb("corrected", 0))
        self._handles["probe"] = scene.add_icosphere(
            "/replay/probe", radius=seq.probe_radius, color=(220, 60, 60), position=tuple(float(v) for v in seq.probe_centres[0]))
        self._build_diagnosis_nodes()
        self._frame(seq.positions[0], (0.0, -0.16, 0.12))

    def _apply_visibility(self) -> None:
        for key, box in (("cloud", self.gui_cloud), ("fem", self.gui_fem), ("corrected", self.gui_corrected), ("probe", self.gui_probe)):
            h = self._handles.get(key)
            if h is not None:
                h.visible = bool(box.value)
        for key, h in self._handles.items():
            if key.startswith("geometry:"):
                h.visible = bool(self.gui_geometry.value)

    def set_frame(self, f: int) -> None:
        """Show frame ``f`` (clipped to the sequence): swap the cloud, mesh and probe buffers."""
        with self._lock:
            if self.view is None:
                return
            seq = self.view.seq
            f = int(np.clip(f, 0, seq.n_frames - 1))
            self.frame = f
            self._handles["cloud"].points = seq.cloud(f)
            self._handles["fem"].glb_data = self.view.glb("fem", f, self.colour)
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

    # ------------------------------------------------------------------ camera
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

    # ------------------------------------------------------------------ state
    def _set_mode(self, mode: str) -> None:
        self.mode = mode
        self._replay_root.visible = mode == "replay"
        self._icp_root.visible = mode == "icp"
        self._plan_root.visible = mode == "plan"
        if mode == "replay" and self.view is not None:
            self._frame(self.view.seq.positions[self.frame], (0.0, -0.16, 0.12))

    def visible(self) -> dict[str, bool]:
        """This tab's layer toggles: cloud, fem, corrected, probe, geometry (a diagnosis's causes)."""
        return {k: bool(box.value) for k, box in (("cloud", self.gui_cloud), ("fem", self.gui_fem),
                                                  ("corrected", self.gui_corrected), ("probe", self.gui_probe),
                                                  ("geometry", self.gui_geometry))}

    def state(self) -> dict:
        """JSON-able state of this tab: mode, run (and its mesh), sequence, frame, time, layers, playback,
        picks, camera."""
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
                "diagnosis": self.diagnosis_state(),
                "plan": self.plan_state(),
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
        "mesh": run.mesh if run else None,
    }


class WorkbenchViewer:
    """A viser server with the replay and ICP tabs, one independent view per browser tab.

    Each tab that connects gets its own GUI and scene (viser's ``client.gui`` and
    ``client.scene``): picking a run, a sequence, a frame, a layer or ICP points in one tab
    leaves the others alone. Runs are loaded, and mesh frames encoded, once for all tabs.

    The server-side methods (:meth:`show_run`, :meth:`set_frame`, :meth:`start_icp`; the
    dashboard's REST calls) act as a remote control on the viewer tab of the dashboard tab
    that called them (its token, see :meth:`_tab_token`), or on every open tab without a
    token, and set what such a tab that connects later starts with.

    Args:
        callbacks: see :class:`ViewerCallbacks`.
        host, port: where viser listens (the next free port is taken if busy; see ``port``).
    """

    def __init__(self, callbacks: ViewerCallbacks, host: str = "127.0.0.1", port: int = 8081):
        import viser

        self.cb = callbacks
        self.shared = SharedRuns(callbacks)
        self.server = viser.ViserServer(host=host, port=port, label="Tissue Twin", verbose=False)
        self.port = int(self.server.get_port())
        self.server.scene.set_up_direction("+z")
        self._lock = threading.RLock()
        self._tabs: dict[int, TabView] = {}
        self.shown: dict[str, Any] = {"run_id": None, "sequence": None, "frame": 0}
        """What a new tab starts with: the run, sequence and frame last shown from the server side."""
        self._shown_for: dict[str, dict[str, Any]] = {}
        """The same per dashboard token, for the tabs of one dashboard (a reloaded iframe)."""
        self.first_frame_seconds: float | None = None
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)
        self._stop = threading.Event()
        self._player = threading.Thread(target=self._play_loop, name="viewer-play", daemon=True)
        self._player.start()

    def _connect(self, client) -> None:
        token = self._tab_token(client)
        tab = TabView(self.shared, client, token=token)  # viser prints what this raises
        with self._lock:
            self._tabs[int(client.client_id)] = tab
            shown = dict(self._shown_for.get(token) or self.shown)
        if shown["run_id"] is not None:
            try:
                tab.show_run(shown["run_id"], shown["sequence"], shown["frame"])
            except Exception as exc:  # noqa: BLE001 - e.g. the run's files were removed; the tab still opens
                tab.gui_info.content = f"could not show run {shown['run_id']}: {exc}"

    def _tab_token(self, client) -> str | None:
        """The dashboard tab's token of a viewer client: the dashboard opens its iframe with
        ``?websocket=ws://host:port/tab/<token>``, so the websocket handshake's path names
        the dashboard tab that embeds it. None for a viewer opened on its own.

        Reads the connection from viser's websocket server (viser 1.1.1, pinned: a viser
        client handle does not expose its request path)."""
        try:
            conn = self.server._websock_server._live_connections.get(int(client.client_id))
            path = str(conn.request.path)
        except Exception:  # noqa: BLE001 - another viser: every tab then follows every dashboard
            return None
        m = re.search(r"/tab/([A-Za-z0-9_-]{1,64})", path)
        return m.group(1) if m else None

    def _disconnect(self, client) -> None:
        with self._lock:
            self._tabs.pop(int(client.client_id), None)

    def tabs(self, token: str | None = None) -> list[TabView]:
        """The open tabs, oldest first; with ``token``, those a dashboard tab of that token embeds."""
        with self._lock:
            return [t for t in self._tabs.values() if token is None or t.token == token]

    def show_run(self, run_id: int, sequence: str | None = None, tab: str | None = None) -> None:
        """Show ``sequence`` (default: the run's first) of run ``run_id`` at frame 0 in the
        viewer tabs of dashboard token ``tab`` (None: every open tab) and in tabs opened
        later (a reloaded tab of a token opens what its dashboard last showed); the run's
        arrays are loaded on first use and kept.

        Raises:
            KeyError: the run has no such sequence. Whatever ``load_run`` raises.
        """
        t0 = time.perf_counter()
        view = self.shared.view(run_id, sequence)
        view.glb("fem", 0)
        if view.seq.corrected_positions is not None:
            view.glb("corrected", 0)
        shown = {"run_id": run_id, "sequence": view.seq.name, "frame": 0}
        with self._lock:
            self.shown = dict(shown)  # what any new tab opens with, whichever dashboard asked
            if tab is None:
                self._shown_for.clear()
            else:
                self._shown_for[tab] = shown
        self._each_tab(lambda t: t.show_run(run_id, view.seq.name), tab)
        self.first_frame_seconds = time.perf_counter() - t0

    def set_frame(self, f: int, tab: str | None = None) -> None:
        """Show frame ``f`` (clipped to the sequence) in the tabs of ``tab`` (None: every
        tab) and in such tabs opened later."""
        with self._lock:
            shown = self.shown if tab is None else self._shown_for.get(tab, dict(self.shown))
            if shown["run_id"] is None:
                return
            n = self.shared.view(shown["run_id"], shown["sequence"]).seq.n_frames
            shown["frame"] = int(np.clip(f, 0, n - 1))
            if tab is not None:
                self._shown_for[tab] = shown
        self._each_tab(lambda t: t.set_frame(f), tab)

    def start_icp(self, session_id: int, tab: str | None = None) -> None:
        """Open the picking mode on a session's reference cloud in the tabs of ``tab``
        (None: every open tab)."""
        self.shared.icp_inputs(session_id)  # raises here, once, if the session cannot be read
        self._each_tab(lambda t: t.start_icp(session_id), tab)

    def show_plan(self, job_id: int, tab: str | None = None) -> None:
        """Draw plan job ``job_id`` (its ``plan_view.json``, read through the callbacks) in
        the tabs of ``tab`` (None: every open tab).

        Raises:
            RuntimeError: the server gave no ``load_plan`` callback. Whatever it raises.
        """
        if self.cb.load_plan is None:
            raise RuntimeError("this viewer cannot load plans (no load_plan callback)")
        view = self.cb.load_plan(job_id)
        self._each_tab(lambda t: t.show_plan(job_id, view), tab)

    def _each_tab(self, action: Callable[[TabView], None], token: str | None = None) -> None:
        """Apply ``action`` to every open tab of ``token`` (None: all); a tab closing
        meanwhile does not stop the others."""
        for tab in self.tabs(token):
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

    def state(self, tab: str | None = None) -> dict:
        """JSON-able state: the newest open tab's (of dashboard token ``tab`` when given and
        open) (mode, run, sequence, frame, time, layers, visibility, playback, picks, camera)
        or, with no tab open, what a new tab would show; plus the port, the number of tabs,
        each tab's selection in ``tabs`` and the server-side time to the first frame of the
        last :meth:`show_run`."""
        tabs = self.tabs()
        mine = (self.tabs(tab) or tabs) if tab else tabs
        if mine:
            state = mine[-1].state()
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
                     tabs=[{"client_id": int(t.client.client_id), "token": t.token, "mode": t.mode, "run_id": t.run_id,
                            "sequence": t.view.seq.name if t.view else None, "frame": t.frame,
                            "visible": t.visible()} for t in tabs])
        return state

    def stop(self) -> None:
        """Stop playback and the viser server."""
        self._stop.set()
        self._player.join(timeout=2)
        self.server.stop()
