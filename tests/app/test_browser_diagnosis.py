"""The diagnosis in a real headless browser (Debian chromium + playwright): the dashboard's
summary with its figures, the viewer's corrected-mesh layer (the model extended by the
diagnosed effect) toggled on and off, and two viewer tabs that keep their own selection.

A diagnose job takes minutes, so the module makes its job once from a run of the core
library with tiny settings: a 3 x 6 s virtual-lab session with gravity (a 13x5x5 truth
mesh and a 200 x 150 depth camera, which cut its making from ~52 s to ~17 s on a busy
machine), diagnosed with the gravity candidate only, no E fit and no fine-grid
discrepancy reference. Its files
are written by the diagnose job's own code (``write_diagnose_artifacts``) into the job
folder, and its database row is the one the runner stores for a finished job; the
server then serves those real files.
"""

from __future__ import annotations

import io
import json
import time
from dataclasses import replace

import httpx
import numpy as np
import pytest

from tests.app._server import Server, store_finished_jobs
from tests.app.conftest import needs_chromium
from tests.app.test_browser import _canvas, _state, _until, _viewer_connected

pytestmark = [pytest.mark.slow, needs_chromium]

GRAVITY = {"kind": "gravity", "g": [0.0, 0.0, -9.81]}


@pytest.fixture(scope="module")
def diagnosed(tmp_path_factory):
    """A data directory whose database holds session 1 (a gravity session) and its
    finished diagnose job 1; returns (data directory, the job's summary)."""
    from core.diagnosis import DiagnosisConfig, diagnose_prepared
    from core.lab import generate_session
    from core.lab.camera import Intrinsics
    from core.lab.generate import PRESETS
    from core.preparation import prepare_session
    from core.simulation.replay import ReplayConfig
    from app.server.jobs.types import DiagnoseParams, write_diagnose_artifacts

    root = tmp_path_factory.mktemp("diagnosed")
    lab = replace(PRESETS["small"], sequence_durations=(6.0,) * 3, sequence_roles=("validation", "test", "train"),
                  grid=(13, 5, 5), intrinsics=Intrinsics.from_fov(200, 150, 64.0))
    session = generate_session(root / "gravity", preset=lab, seed=1, effects=[GRAVITY])
    prepared = prepare_session(session, ReplayConfig())
    diag = diagnose_prepared(prepared, DiagnosisConfig(fit_youngs=False, n_boot=50, kinds=("gravity",), fine_grid=None))
    data = root / "data"
    folder = (data / "jobs" / "1").resolve()
    summary = write_diagnose_artifacts(diag, prepared, folder)
    store_finished_jobs(data, session, "gravity",
                        [(1, "diagnose", DiagnoseParams(session_id=1, fit_youngs=False), summary, folder)])
    return data, summary


def _checkbox(frame, label: str):
    return frame.get_by_role("checkbox", name=label)


def _grey(png: bytes) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(png)).convert("L"), dtype=np.float64)


def test_diagnosis_summary_and_corrected_mesh_in_chromium(diagnosed, chromium, tmp_path):
    from PIL import Image

    data, summary = diagnosed
    # the tiny diagnosis names the hidden effect, so the job has a corrected mesh to show
    assert [c["kind"] for c in summary["causes"]] == ["gravity"] and summary["viewer"] is True
    on_disk = json.loads((data / "jobs" / "1" / "diagnosis.json").read_text())
    shots = tmp_path / "screenshots"
    shots.mkdir()
    server = Server(data, viewer=True)
    page = chromium.new_page(viewport={"width": 1400, "height": 1500})
    try:
        page.goto(server.url + "/")
        page.wait_for_selector("body[data-ready='1']")

        # the dashboard follows the latest finished job: the diagnosis shows without a click
        page.wait_for_selector("#causes-table")
        assert page.get_attribute("#results", "data-job-id") == "1"
        rows = page.locator("#causes-table tbody tr")
        assert rows.count() == len(on_disk["causes"]) == 1
        cells = rows.first.locator("td").all_inner_texts()
        assert cells[0] == "gravity" and cells[2] == f"{on_disk['causes'][0]['test_error'] * 1e3:.4f}"
        verdict = page.inner_text("#diagnosis-verdict")
        assert "gravity" in verdict and f"{on_disk['extended']['test_error'] * 1e3:.4f} mm" in verdict
        # its figures are the job's PNG files, decoded by the browser at their own size
        page.wait_for_function("() => { const f = [...document.querySelectorAll('img.diagnosis-figure')];"
                               " return f.length === 3 && f.every((i) => i.complete && i.naturalWidth > 0); }")
        shown = page.eval_on_selector_all("img.diagnosis-figure", "els => els.map((e) => [e.alt, e.naturalWidth, e.naturalHeight])")
        for name, w, h in shown:
            with Image.open(data / "jobs" / "1" / name) as im:
                assert (w, h) == im.size, name
        page.screenshot(path=str(shots / "dashboard-diagnosis.png"), full_page=True)

        # the viewer: the diagnosis's run, labelled with the E it used, with its corrected mesh
        frame = page.frame_locator("#viewer-frame")
        _viewer_connected(page, server)
        page.click("#jobs-table tr[data-job-id='1'] .view-btn")
        st = _until(lambda: (s := _state(server.url))["run_id"] == 1 and s, "the diagnosis run in the viewer")
        assert st["layers"] == ["cloud", "fem", "corrected", "probe"]
        assert st["sequence"] in summary["corrected_shown"]
        frame.get_by_text("frame 0 /", exact=False).wait_for(timeout=30_000)
        label = frame.locator("input[value^='1: ']").first.input_value()
        assert label == "1: extended model (gravity) of gravity, E 5000 Pa", label

        # the corrected mesh alone (cloud and FEM mesh hidden), then toggled off: the canvas changes
        for name, key in (("Measured cloud", "cloud"), ("FEM mesh", "fem")):
            _checkbox(frame, name).click()
            _until(lambda: not _state(server.url)["visible"][key], f"{name} hidden")
        time.sleep(1.0)  # let WebGL draw
        canvas = _canvas(page)
        with_corrected = _grey(canvas.screenshot(path=str(shots / "corrected-on.png")))
        _checkbox(frame, "Corrected mesh").click()
        _until(lambda: not _state(server.url)["visible"]["corrected"], "the corrected mesh hidden")
        time.sleep(1.0)
        without = _grey(canvas.screenshot(path=str(shots / "corrected-off.png")))
        changed = np.mean(np.abs(with_corrected - without) > 16)
        assert with_corrected.var() > 20.0, "3D canvas is blank"
        assert changed > 0.005, f"toggling the corrected mesh changed {changed:.2%} of the canvas"

        # a second tab has its own selection: stepping there leaves the first tab's frame alone
        first_id = _state(server.url)["client_id"]
        viewer_port = httpx.get(f"{server.url}/api/config").json()["viewer_port"]
        other = chromium.new_page(viewport={"width": 1000, "height": 800})
        try:
            other.goto(f"http://127.0.0.1:{viewer_port}/")
            st = _until(lambda: (s := _state(server.url))["clients"] == 2 and s["frame"] == 0 and s["run_id"] == 1 and s,
                        "the second tab on the shown run")
            assert st["visible"]["corrected"] and st["visible"]["fem"]  # its own toggles, not the first tab's
            for _ in range(3):
                other.get_by_role("button", name="+1 frame").click()
            tabs = _until(lambda: (s := _state(server.url))["frame"] == 3 and s["tabs"], "frame 3 in the second tab")
            first = next(t for t in tabs if t["client_id"] == first_id)
            assert first["frame"] == 0 and first["visible"] == {"cloud": False, "fem": False, "corrected": False, "probe": True,
                                                       "geometry": True}
        finally:
            other.close()
    finally:
        page.close()
        server.stop()


def _pick(frame, label: str, option: str) -> None:
    """Choose ``option`` in the viewer's dropdown ``label`` (a Mantine select)."""
    frame.get_by_role("combobox", name=label).click()
    frame.get_by_role("option", name=option).click()


def test_diagnosis_layers_in_3d_in_chromium(diagnosed, chromium, tmp_path):
    """Issue 19 item 3: the Diagnosis tab of the viewer colours the phantom by the base
    model's systematic residual and by the claimed cause's change (each changes the
    canvas), draws the cause's geometry (the gravity arrow; toggling it changes the
    canvas), gives the answer per kind and jumps to the largest-error frame."""
    data, summary = diagnosed
    shots = tmp_path / "screenshots"
    shots.mkdir()
    server = Server(data, viewer=True)
    page = chromium.new_page(viewport={"width": 1400, "height": 1500})
    try:
        page.goto(server.url + "/")
        page.wait_for_selector("body[data-ready='1']")
        frame = page.frame_locator("#viewer-frame")
        _viewer_connected(page, server)
        page.click("#jobs-table tr[data-job-id='1'] .view-btn")
        st = _until(lambda: (s := _state(server.url))["run_id"] == 1 and s, "the diagnosis run in the viewer")
        assert st["diagnosis"]["colour_modes"] == ["error", "base_residual", "extended_residual", "change_gravity"]
        assert st["diagnosis"]["geometry"] == ["geometry:0"]  # the gravity arrow
        for name, key in (("Measured cloud", "cloud"), ("Corrected mesh", "corrected")):
            _checkbox(frame, name).click()
            _until(lambda: not _state(server.url)["visible"][key], f"{name} hidden")
        canvas = _canvas(page)
        time.sleep(1.0)
        shots_by = {"error": _grey(canvas.screenshot(path=str(shots / "colour-error.png")))}
        for name, key in (("Measured cloud", "cloud"), ("Corrected mesh", "corrected")):  # on again: a signed
            _checkbox(frame, name).click()  # colour hides them itself, as they would cover it
            _until(lambda: _state(server.url)["visible"][key], f"{name} shown")

        frame.get_by_role("tab", name="Diagnosis").click()
        text = frame.locator("body").inner_text()
        assert "claimed:" in text and "gravity" in text and "found" in text
        for mode, option in (("base_residual", "base model: systematic residual"),
                             ("change_gravity", "gravity: its change of the surface")):
            _pick(frame, "Surface colour", option)
            _until(lambda: _state(server.url)["diagnosis"]["colour"] == mode, f"colour mode {mode}")
            assert not _state(server.url)["visible"]["cloud"] and not _state(server.url)["visible"]["corrected"]
            frame.get_by_text("mm (blue)", exact=False).first.wait_for(timeout=10_000)  # the signed legend
            time.sleep(1.0)
            shots_by[mode] = _grey(canvas.screenshot(path=str(shots / f"colour-{mode}.png")))
        for a, b in (("error", "base_residual"), ("base_residual", "change_gravity")):
            changed = np.mean(np.abs(shots_by[a] - shots_by[b]) > 16)
            assert changed > 0.005, f"{a} -> {b} changed {changed:.2%} of the canvas"

        _checkbox(frame, "Cause geometry").click()
        _until(lambda: not _state(server.url)["visible"]["geometry"], "the cause geometry hidden")
        time.sleep(1.0)
        no_arrow = _grey(canvas.screenshot(path=str(shots / "geometry-off.png")))
        changed = np.mean(np.abs(no_arrow - shots_by["change_gravity"]) > 16)
        assert changed > 0.001, f"hiding the gravity arrow changed {changed:.2%} of the canvas"

        st = _state(server.url)
        worst = st["diagnosis"]["worst_frames"]
        errors = np.load(data / "jobs" / "1" / "viewer_run" / f"{st['sequence']}.npz")["frame_errors"]
        assert worst[0] == int(np.nanargmax(errors)) and len(worst) == min(5, errors.size)
        _pick(frame, "Largest-error frames", f"frame {worst[0]}: {errors[worst[0]] * 1e3:.3f} mm")
        _until(lambda: _state(server.url)["frame"] == worst[0], "the largest-error frame")
        page.screenshot(path=str(shots / "dashboard-diagnosis-3d.png"), full_page=True)
    finally:
        page.close()
        server.stop()
