"""The viewer's ICP tab: pick K >= 3 points on a session's reference cloud (shown from the
depth camera's own viewpoint, camera frame) and the matching points on the phantom's rest
surface (phantom frame); *Compute* runs Kabsch + ICP through the server's callback and
shows the reference cloud before (Kabsch, orange) and after (ICP, green) on the rest
surface with the residuals; *Accept* saves the session's calibration.

:class:`IcpPanel` is a part of :class:`app.viewer.scene.TabView` (a mixin): it uses the
tab's client, lock, handles, ``_set_mode``, ``_frame_box`` and ``_set_camera``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["IcpPanel"]


class IcpPanel:
    """The ICP half of one browser tab (see the module docstring)."""

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
