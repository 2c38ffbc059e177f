"""The viewer's Diagnosis tab (issue 19, item 3): a diagnose run told on the phantom.

For a run written by a diagnose job (:mod:`app.viewer.diagnosis_data`) it offers:

- *Surface colour*: the FEM layer coloured by per-vertex error, or by the base model's
  systematic signed residual, the extended model's (on the extended mesh), or what each
  claimed cause alone changes of the surface; a signed legend in mm (red: the measured
  surface, or the cause's surface, lies outside the base model's; blue: inside);
- *Cause geometry*: the inclusion's sphere, the gravity vector above the phantom, a robot
  offset as an arrow at the probe (5x), the probe's true radius as a sphere around it;
- the answer for every kind (found / confounded / not found above a size / cannot tell);
- *Largest-error frames*: the five frames of the sequence where the base model is most
  wrong (mean error), one click away.

:class:`DiagnosisPanel` is a part of :class:`app.viewer.scene.TabView` (a mixin): it uses
the tab's client, lock, handles, view, run and ``set_frame``.
"""

from __future__ import annotations

import numpy as np

from app.viewer.buffers import colorbar

__all__ = ["DiagnosisPanel", "MODE_LABELS", "answers_markdown"]

MODE_LABELS = {"error": "per-vertex error", "base_residual": "base model: systematic residual",
               "extended_residual": "extended model: systematic residual"}
"""Dropdown labels of the colour modes; ``change_<kind>`` reads "<kind>: its change"."""

_ANSWER_TEXT = {"found": "found", "confounded": "confounded", "not_found": "not found", "cannot_tell": "cannot tell"}
_GEOMETRY_COLOUR = (250, 170, 20)
_NO_FRAME = "(pick a frame)"


def _mode_label(mode: str) -> str:
    return MODE_LABELS.get(mode) or f"{mode[len('change_'):]}: its change of the surface"


def answers_markdown(view: dict | None) -> str:
    """The diagnosis's answer for every kind as a markdown table (``view.json``'s ``answers``)."""
    if not view:
        return "This run is not a diagnosis. Press *view* on a finished diagnose job."
    rows = ["| kind | answer | size that would show |", "| --- | --- | --- |"]
    for kind, a in (view.get("answers") or {}).items():
        size = a.get("min_size")
        size_text = f"{size:.3g} {a.get('unit', '')}".strip() if isinstance(size, (int, float)) else "none would"
        rows.append(f"| {kind} | **{_ANSWER_TEXT.get(a.get('answer'), a.get('answer'))}** | {size_text} |")
    te = view.get("test_error") or {}
    claimed = ", ".join(c["kind"] for c in view.get("claimed") or []) or "nothing"
    head = f"**claimed:** {claimed}. Test error: base {te['base'] * 1e3:.3f} mm" if te.get("base") is not None else ""
    if head and te.get("extended") is not None:
        head += f", extended {te['extended'] * 1e3:.3f} mm"
    return (head + ".\n\n" if head else "") + "\n".join(rows)


class DiagnosisPanel:
    """The Diagnosis tab of one browser tab (see the module docstring)."""

    def _populate_diagnosis(self, tab) -> None:
        gui = self.client.gui
        self.colour = "error"
        self.worst_frames: list[int] = []
        with tab:
            self.gui_colour = gui.add_dropdown("Surface colour", options=(MODE_LABELS["error"],),
                                               initial_value=MODE_LABELS["error"], disabled=True)
            self.gui_geometry = gui.add_checkbox("Cause geometry", True, disabled=True)
            self.gui_worst = gui.add_dropdown("Largest-error frames", options=(_NO_FRAME,), initial_value=_NO_FRAME,
                                              disabled=True)
            self.gui_signed_legend = gui.add_image(colorbar(signed=True), label="signed (mm)", format="png", visible=False)
            self.gui_signed_text = gui.add_markdown("", visible=False)
            self.gui_answers = gui.add_markdown(answers_markdown(None))
        self.gui_colour.on_update(lambda _e: None if self._mute else self._on_colour_selected())
        self.gui_geometry.on_update(lambda _e: self._apply_visibility())
        self.gui_worst.on_update(lambda _e: None if self._mute else self._on_worst_selected())

    # ------------------------------------------------------------------ run changes
    def _reset_diagnosis(self) -> None:
        """Fill the tab for the sequence just shown (``self.view``); called by ``show_run``."""
        view = self.view
        modes = view.colour_modes()
        if self.colour not in modes:
            self.colour = "error"
        labels = tuple(_mode_label(m) for m in modes)
        self.worst_frames = [int(f) for f in np.argsort(-np.nan_to_num(view.seq.frame_errors, nan=-np.inf))[:5]]
        worst = (_NO_FRAME,) + tuple(f"frame {f}: {view.seq.frame_errors[f] * 1e3:.3f} mm" for f in self.worst_frames)
        self._mute = True
        try:
            self.gui_colour.options = labels
            self.gui_colour.value = _mode_label(self.colour)
            self.gui_colour.disabled = len(modes) < 2
            self.gui_worst.options = worst
            self.gui_worst.value = _NO_FRAME
            self.gui_worst.disabled = view.seq.n_frames < 2
            self.gui_geometry.disabled = not (self.run.diagnosis or {}).get("geometry")
        finally:
            self._mute = False
        self.gui_answers.content = answers_markdown(self.run.diagnosis)
        self._update_legend()

    def _remove_geometry(self) -> None:
        """Remove the causes' geometry (before the probe it may hang from is removed)."""
        for key in [k for k in self._handles if k.startswith("geometry:")]:
            self._handles.pop(key).remove()

    def _build_diagnosis_nodes(self) -> None:
        """The claimed causes' geometry (under ``/replay/diagnosis`` and, for the probe's,
        under ``/replay/probe`` so it moves with it)."""
        scene = self.client.scene
        self._remove_geometry()
        for i, g in enumerate((self.run.diagnosis or {}).get("geometry") or []):
            shape, name = g["shape"], f"geometry:{i}"
            if shape == "sphere":
                h = scene.add_icosphere(f"/replay/diagnosis/{i}", radius=g["radius"], color=_GEOMETRY_COLOUR,
                                        position=tuple(g["center"]), opacity=0.55)
            elif shape == "probe_sphere":
                h = scene.add_icosphere(f"/replay/probe/true_radius_{i}", radius=g["radius"], color=_GEOMETRY_COLOUR,
                                        wireframe=True)
            elif shape in ("vector", "probe_vector"):
                origin = np.asarray(g.get("origin", (0.0, 0.0, 0.0)), float)
                tip = origin + np.asarray(g["vector"], float)
                length = float(np.linalg.norm(tip - origin))
                parent = "/replay/diagnosis" if shape == "vector" else "/replay/probe"
                h = scene.add_arrows(f"{parent}/arrow_{i}", np.array([[origin, tip]], np.float32), _GEOMETRY_COLOUR,
                                     shaft_radius=max(0.04 * length, 3e-4), head_radius=max(0.12 * length, 8e-4),
                                     head_length=max(0.25 * length, 1.5e-3))
                self._handles[name + ":label"] = scene.add_label(f"{parent}/arrow_{i}_label", g["label"],
                                                                 position=tuple(float(v) for v in tip))
            else:
                continue
            self._handles[name] = h
        self._apply_visibility()

    # ------------------------------------------------------------------ controls
    def _on_colour_selected(self) -> None:
        label = self.gui_colour.value
        mode = next((m for m in (self.view.colour_modes() if self.view else []) if _mode_label(m) == label), None)
        if mode is not None:
            self.set_colour(mode)

    def set_colour(self, mode: str) -> None:
        """Colour the FEM layer by ``mode`` (one of the sequence's ``colour_modes()``); going
        from per-vertex error to a signed layer hides the measured cloud and the corrected
        mesh, which would cover it.

        Raises:
            KeyError: the sequence shown has no such colour mode.
        """
        with self._lock:
            if self.view is None or mode not in self.view.colour_modes():
                raise KeyError(f"no colour mode {mode!r} here; have {self.view.colour_modes() if self.view else []}")
            if self.colour == "error" and mode != "error":
                # the measured points and the corrected mesh (coloured by error) would cover the colours
                self.gui_cloud.value = False
                self.gui_corrected.value = False
                self._apply_visibility()
            self.colour = mode
            if self.gui_colour.value != _mode_label(mode):
                self._mute = True
                try:
                    self.gui_colour.value = _mode_label(mode)
                finally:
                    self._mute = False
            self._update_legend()
            self.set_frame(self.frame)

    def _update_legend(self) -> None:
        signed = self.view is not None and self.colour != "error"
        self.gui_signed_legend.visible = signed
        self.gui_signed_text.visible = signed
        if signed:
            _, vmax = self.view.signed_layer(self.colour)
            what = ("the measured surface outside the model's" if self.colour.endswith("residual")
                    else "the cause moves the surface outward")
            self.gui_signed_text.content = (f"{_mode_label(self.colour)}: -{vmax * 1e3:g} mm (blue) to "
                                            f"+{vmax * 1e3:g} mm (red; {what}); grey: no measured point")

    def _on_worst_selected(self) -> None:
        options = self.gui_worst.options
        if self.gui_worst.value in options[1:]:
            self.playing = False
            self.set_frame(self.worst_frames[options.index(self.gui_worst.value) - 1])

    def diagnosis_state(self) -> dict:
        """This tab's diagnosis controls: colour mode, its options, geometry shown, the
        frames offered as largest-error ones."""
        return {"colour": self.colour,
                "colour_modes": self.view.colour_modes() if self.view is not None else ["error"],
                "geometry": [k for k in self._handles if k.startswith("geometry:") and not k.endswith(":label")],
                "worst_frames": list(self.worst_frames)}
