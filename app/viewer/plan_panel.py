"""The viewer's Plan tab (issue 19, item 4): a palpation plan drawn over the phantom.

The phantom's rest shape (translucent: the box, or the surface of ``phantom.stl`` when
the plan view carries one), the probe path of the plan (the sphere's centre;
orange where the sphere touches or presses the phantom, grey in free space), a numbered
label at each move's first touch, the probe sphere at the path's start, and beside it the
plan's description, the sizes it predicts against the session's, and where to download
its ``kinematics.csv`` (the dashboard's link).

:class:`PlanPanel` is a part of :class:`app.viewer.scene.TabView` (a mixin): it uses the
tab's client, lock, handles, ``_set_mode`` and ``_frame``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["PlanPanel", "plan_markdown"]

_CONTACT = (255, 140, 0)
_FREE = (150, 150, 150)


def plan_markdown(view: dict, job_id: int | None = None) -> str:
    """The plan's description and predicted sizes as markdown (``plan_view.json``)."""
    lines = [f"**plan** (job {job_id}): {view['t'][-1]:.1f} s, {len(view['moves'])} moves"
             + (", **record the probe force**" if view.get("record_force") else "")]
    lines += [f"{i + 1}. {m['description']}" for i, m in enumerate(view["moves"])]
    units = view.get("units") or {}
    rows = ["| kind | smallest size now | with this plan |", "| --- | --- | --- |"]
    for k, pred in (view.get("predicted") or {}).items():
        now = (view.get("current") or {}).get(k)
        u = units.get(k, "")
        rows.append(f"| {k} | {'cannot tell' if now is None else f'{now:.3g} {u}'} | "
                    f"{'cannot tell' if pred is None else f'{pred:.3g} {u}'} |")
    return "\n".join(lines) + "\n\n" + "\n".join(rows) + "\n\nkinematics.csv: the dashboard's plan job, *download*."


class PlanPanel:
    """The Plan tab of one browser tab (see the module docstring)."""

    def _populate_plan(self, tab) -> None:
        gui = self.client.gui
        self.plan_job: int | None = None
        with tab:
            self.gui_plan_info = gui.add_markdown("No plan loaded. Finish a plan job, then press *show the plan in 3D* "
                                                  "in the dashboard.")
            self.gui_plan_back = gui.add_button("Back to replay")
        self.gui_plan_back.on_click(lambda _e: self._set_mode("replay"))

    def show_plan(self, job_id: int, view: dict) -> None:
        """Draw plan job ``job_id``'s ``plan_view.json`` (``view``) and switch to plan mode."""
        with self._lock:
            scene = self.client.scene
            for key in [k for k in self._handles if k.startswith("plan:")]:
                self._handles.pop(key).remove()
            size = np.asarray(view["size"], float)
            centres = np.asarray(view["centres"], np.float32)
            contact = np.asarray(view["contact"], bool)
            surface = view.get("surface")
            if surface:
                vertices = np.asarray(surface["vertices"], np.float32)
                self._handles["plan:phantom"] = scene.add_mesh_simple(
                    "/plan/phantom", vertices, np.asarray(surface["faces"], np.uint32), color=(120, 200, 140), opacity=0.35)
                extent = np.concatenate([vertices.min(axis=0, keepdims=True), vertices.max(axis=0, keepdims=True)])
            else:
                self._handles["plan:phantom"] = scene.add_box("/plan/phantom", color=(120, 200, 140),
                                                              dimensions=tuple(size), position=tuple(size / 2), opacity=0.35)
                extent = np.stack([np.zeros(3), size])
            seg = np.stack([centres[:-1], centres[1:]], axis=1)
            colours = np.where((contact[:-1] | contact[1:])[:, None], np.array(_CONTACT), np.array(_FREE)).astype(np.uint8)
            self._handles["plan:path"] = scene.add_line_segments("/plan/path", seg, np.repeat(colours[:, None], 2, axis=1),
                                                                 thickness=0.0006)
            self._handles["plan:probe"] = scene.add_icosphere("/plan/probe", radius=float(view["radius"]),
                                                              color=(220, 60, 60), opacity=0.6,
                                                              position=tuple(float(v) for v in centres[0]))
            for i, m in enumerate(view["moves"]):
                if m.get("start") is not None:
                    self._handles[f"plan:label{i}"] = scene.add_label(
                        f"/plan/move{i}", f"{i + 1}: {m['name']}",
                        position=tuple(float(v) for v in centres[m["start"]] + np.array([0.0, 0.0, view["radius"]])))
            self.plan_job = job_id
            self.gui_plan_info.content = plan_markdown(view, job_id)
            self._set_mode("plan")
            self._frame(np.concatenate([centres, extent]), (0.0, -0.16, 0.12))

    def plan_state(self) -> dict:
        """This tab's plan: the job shown, whether its path is drawn (``segments``: 1 line-segment
        node, 0 none) and its move labels."""
        return {"job_id": self.plan_job,
                "segments": int("plan:path" in self._handles),
                "labels": sorted(k for k in self._handles if k.startswith("plan:label"))}
