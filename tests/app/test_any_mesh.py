"""The workbench on a phantom given by ``phantom.stl`` (issue 18, item 9): the viewer's
arrays, the export and the jobs use the replay's Gmsh mesh, not a box grid.

One dome session (the virtual lab, 6 s sequences, seed 3; ~10 s) is made for the module
and one of its sequences replayed (~10 s). Meshes and preparations are cached in the
module's own folder (``TISSUETWIN_CACHE_DIR``).
"""

from __future__ import annotations

import io
import json
import time
import zipfile
from types import SimpleNamespace

import numpy as np
import pytest

from tests.app._server import FINAL, _free_port


@pytest.fixture(scope="module")
def dome(tmp_path_factory):
    """A dome session (``phantom.stl``, landmark calibration), with the module's own cache."""
    from core.lab import generate_session
    from core.lab.generate import PRESETS

    root = tmp_path_factory.mktemp("dome")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("TISSUETWIN_CACHE_DIR", str(root / "cache"))
        yield generate_session(root / "session", preset=PRESETS["small"].with_duration(6.0), seed=3, shape="dome")


@pytest.fixture(scope="module")
def dome_run(dome, tmp_path_factory):
    """(run folder, ReplayResult, PreparedSession) of seq01 replayed as the replay job does."""
    from app.viewer.data import write_viewer_arrays
    from core.preparation import prepare_session
    from core.simulation.replay import ReplayConfig, replay, write_replay

    folder = tmp_path_factory.mktemp("dome-run") / "run"
    config = ReplayConfig(sequences=("seq01",))
    prepared = prepare_session(dome, config)
    result = replay(dome, config, prepared=prepared)
    write_replay(result, folder)
    write_viewer_arrays(prepared, result, folder)
    return folder, result, prepared


def _naive_vertex_errors(x: np.ndarray, triangles: np.ndarray, points: np.ndarray, n: int) -> np.ndarray:
    """The viewer's per-node error of one frame, by brute force: every triangle's points at
    barycentric (i, j, k) / 3 (shared points repeated), each measured point's distance to
    the nearest of them, assigned to the nearest surface node, averaged per node."""
    bary = np.array([(i, j, 3 - i - j) for i in range(4) for j in range(4 - i)], float) / 3.0
    samples = np.einsum("bk,tkd->tbd", bary, x[triangles]).reshape(-1, 3)
    surface = np.unique(triangles)
    d = np.empty(len(points))
    node = np.empty(len(points), dtype=np.int64)
    for i in range(0, len(points), 256):
        p = points[i:i + 256]
        d[i:i + 256] = np.sqrt(((p[:, None, :] - samples[None]) ** 2).sum(-1)).min(axis=1)
        node[i:i + 256] = surface[((p[:, None, :] - x[surface][None]) ** 2).sum(-1).argmin(axis=1)]
    out = np.full(n, np.nan)
    for k in np.unique(node):
        out[k] = d[node == k].mean()
    return out


def test_viewer_data_of_a_dome_run_is_on_its_mesh(dome_run):
    from app.viewer.data import load_run

    folder, result, prepared = dome_run
    mesh = result.mesh
    assert mesh.grid is None and mesh.n_nodes > 400
    run = load_run(folder)
    seq = run.sequences["seq01"]
    F = seq.n_frames
    np.testing.assert_array_equal(seq.faces, mesh.surface_triangles)
    assert seq.positions.shape == (F, mesh.n_nodes, 3) and seq.vertex_error.shape == (F, mesh.n_nodes)
    assert run.mesh == {"kind": "stl", "grid": None, "nodes": mesh.n_nodes, "tets": mesh.n_tets}
    # errors only on surface nodes, and as a brute-force reference gives them (float32 storage)
    inner = np.setdiff1d(np.arange(mesh.n_nodes), mesh.surface_nodes)
    assert inner.size > 0 and np.isnan(seq.vertex_error[:, inner]).all()
    f = F // 2
    x = result.sequences["seq01"].simulation.positions[f]
    expected = _naive_vertex_errors(x, mesh.surface_triangles, np.asarray(prepared.sequences["seq01"].clouds[f]),
                                    mesh.n_nodes)
    assert np.isfinite(expected).sum() > 20
    np.testing.assert_allclose(seq.vertex_error[f], expected, rtol=1e-5, atol=1e-9)


def test_vertex_errors_of_a_box_are_the_grids():
    """The box keeps today's numbers: its TetMesh (what a replay now passes) and its grid
    tuple (what it passed before) give the same errors, bit for bit."""
    from app.viewer.data import vertex_errors
    from core.simulation.mesh import box_mesh

    rng = np.random.default_rng(0)
    mesh = box_mesh((0.0687, 0.0393, 0.0358), (6, 4, 3))
    positions = mesh.nodes[None] + rng.normal(0.0, 5e-4, (4, mesh.n_nodes, 3))
    positions[3, 0] = np.nan  # a diverged frame
    clouds = [mesh.nodes[mesh.surface_nodes] + rng.normal(0.0, 1e-3, (mesh.surface_nodes.size, 3)) for _ in range(4)]
    clouds[1] = np.zeros((0, 3))
    by_grid = vertex_errors(positions, (6, 4, 3), clouds)
    np.testing.assert_array_equal(vertex_errors(positions, mesh, clouds), by_grid)
    assert np.isfinite(by_grid[0]).any() and np.isnan(by_grid[1]).all() and np.isnan(by_grid[3]).all()


def test_export_of_a_dome_run_writes_its_tets(dome_run, tmp_path, capsys):
    """``tissuetwin export`` of the dome run: the VTU's cells are the replayed mesh's
    tetrahedra, its points the rest nodes and each frame's the replay's positions; SOFA and
    MJCF carry the same mesh; a box --grid is refused."""
    import meshio
    import mujoco

    from app.cli import main

    folder, result, _ = dome_run
    mesh = result.mesh
    out = tmp_path / "vtu"
    assert main(["export", str(folder), "--format", "vtu", "--out", str(out)]) == 0
    assert f"STL mesh, {mesh.n_nodes} nodes, {mesh.n_tets} tetrahedra" in capsys.readouterr().out
    rest = meshio.read(out / "rest.vtu")
    assert [c.type for c in rest.cells] == ["tetra"]
    np.testing.assert_array_equal(rest.cells[0].data, mesh.tets)
    np.testing.assert_array_equal(rest.points, mesh.nodes)
    assert rest.point_data["fixed"].sum() == mesh.bottom_nodes().size > 0
    positions = result.sequences["seq01"].simulation.positions
    f = positions.shape[0] // 2
    frame = meshio.read(out / "seq01" / f"frame_{f:06d}.vtu")
    np.testing.assert_array_equal(frame.cells[0].data, mesh.tets)
    np.testing.assert_allclose(frame.points, positions[f], rtol=0, atol=1e-12)
    twin = json.loads((out / "twin.json").read_text())
    assert twin["grid"] is None and twin["mesh"]["kind"] == "stl"
    assert (twin["nodes"], twin["tetrahedra"]) == (mesh.n_nodes, mesh.n_tets)

    assert main(["export", str(folder), "--format", "mjcf", "--out", str(tmp_path / "mjcf")]) == 0
    model = mujoco.MjModel.from_xml_path(str(tmp_path / "mjcf" / "twin.xml"))
    assert model.flex_elemnum.sum() == mesh.n_tets
    assert main(["export", str(folder), "--format", "sofa", "--out", str(tmp_path / "sofa")]) == 0
    assert "phantom frame (of phantom.stl" in (tmp_path / "sofa" / "scene.py").read_text()
    capsys.readouterr()
    assert main(["export", str(folder), "--format", "vtu", "--out", str(tmp_path / "x"), "--grid", "13", "5", "5"]) != 0
    assert "phantom.stl" in capsys.readouterr().err and not (tmp_path / "x").exists()


def test_plan_view_of_a_dome_draws_and_touches_its_surface(dome):
    """A plan over the dome: the view carries the STL's surface, and contact is measured
    against the dome, not its bounding box (a centre above a corner of the box touches the
    box but not the dome)."""
    from app.viewer.plan_data import plan_view
    from core.io import read_session

    session = read_session(dome)
    surface = session.phantom_mesh()
    size = np.asarray(session.meta.phantom.size, float)
    r = 0.005
    apex = np.array([size[0] / 2, size[1] / 2, surface.bounds[1, 2]])
    centres = np.array([apex + [0, 0, 3 * r],  # free
                        apex + [0, 0, 0.5 * r],  # presses the apex
                        [0.002, 0.002, 0.002 + 0.5 * r],  # in the box's corner, outside the dome
                        [size[0] / 2, size[1] / 2, 0.5 * surface.bounds[1, 2]]])  # inside the dome
    plan = SimpleNamespace(path_phantom=centres, path_t=np.arange(4.0), moves=[], description=["test"], targets={},
                           predicted={}, current={}, record_force=False)
    view = plan_view(plan, size, r, stl=session.phantom_stl)
    assert view["contact"] == [False, True, False, True]
    np.testing.assert_allclose(view["surface"]["vertices"], surface.vertices)
    np.testing.assert_array_equal(view["surface"]["faces"], surface.faces)
    box = plan_view(plan, size, r)
    assert box["contact"][2] and "surface" not in box


@pytest.fixture(scope="module")
def server(dome, tmp_path_factory):
    """(TestClient of the workbench on a one-worker Dask cluster, the dome's session id)."""
    from fastapi.testclient import TestClient

    from app.server.main import create_app
    from app.server.settings import Settings

    data = tmp_path_factory.mktemp("workbench") / "data"
    settings = Settings(data_dir=data, viewer_port=_free_port(), workers=1, progress_interval=0.1)
    with TestClient(create_app(settings)) as client:
        yield client, client.post("/api/sessions", json={"path": str(dome)}).json()["id"]


def _run_job(client, type_: str, params: dict, timeout: float = 180.0) -> dict:
    r = client.post("/api/jobs", json={"type": type_, "params": params})
    assert r.status_code == 201, r.text
    deadline = time.monotonic() + timeout
    while (job := client.get(f"/api/jobs/{r.json()['id']}").json())["status"] not in FINAL:
        assert time.monotonic() < deadline, job
        time.sleep(0.2)
    return job


def test_replay_job_on_a_dome_through_the_server(dome, server):
    """A replay job with an element size (the CLI's --element-size) on the dome session:
    done, on the STL's mesh of that size; the viewer shows it with the mesh in its state
    and the export's zip holds its tetrahedra."""
    from core.simulation.meshing import tetrahedralise

    client, sid = server
    types = {t["name"]: t["params_schema"]["properties"] for t in client.get("/api/job-types").json()}
    assert all("element_size" in types[t] for t in ("replay", "sweep", "fit", "train", "evaluate"))
    assert client.post("/api/jobs", json={"type": "replay", "params": {"session_id": sid, "element_size": 0}}).status_code == 422
    job = _run_job(client, "replay", {"session_id": sid, "sequences": ["seq01"], "element_size": 0.009})
    assert job["status"] == "done", job["error"]
    mesh = tetrahedralise(dome / "phantom.stl", 0.009)
    assert job["result"]["mesh"] == {"kind": "stl", "grid": None, "nodes": mesh.n_nodes, "tets": mesh.n_tets,
                                     "element_size": 0.009}
    assert job["result"]["sequences"]["seq01"]["status"] == "ok"
    state = client.post("/api/viewer/show", json={"job_id": job["id"]}).json()
    assert state["mesh"] == {"kind": "stl", "grid": None, "nodes": mesh.n_nodes, "tets": mesh.n_tets}
    assert state["n_frames"] == job["result"]["sequences"]["seq01"]["frames"]
    z = client.get(f"/api/jobs/{job['id']}/export", params={"format": "vtu"})
    assert z.status_code == 200, z.text
    with zipfile.ZipFile(io.BytesIO(z.content)) as zf:
        twin = json.loads(zf.read(f"job-{job['id']}-vtu/twin.json"))
    assert (twin["nodes"], twin["tetrahedra"], twin["grid"]) == (mesh.n_nodes, mesh.n_tets, None)


def test_train_job_on_a_dome_through_the_server(dome, server):
    """A tiny 2D network (widths 4 8 8, one epoch) on the dome: done; its viewer run's
    corrected mesh and per-vertex errors are on the replayed STL mesh (Gmsh's mesh of the
    STL at the default element size)."""
    from core.simulation.meshing import tetrahedralise

    client, sid = server
    job = _run_job(client, "train", {"session_id": sid, "sequences": ["seq00", "seq01", "seq02"], "widths": [4, 8, 8],
                                     "epochs": 1, "max_points": 128, "batch_size": 8})
    assert job["status"] == "done", job["error"]
    mesh = job["result"]["mesh"]
    assert mesh["kind"] == "stl" and mesh["grid"] is None
    shown = np.load(io.BytesIO(client.get(f"/api/jobs/{job['id']}/artifacts/viewer_run/corrected/seq01.npz").content))
    F, N = shown["positions"].shape[:2]
    assert N == mesh["nodes"] == tetrahedralise(dome / "phantom.stl").n_nodes and shown["vertex_error"].shape == (F, N) and np.isfinite(shown["vertex_error"]).any()
    state = client.post("/api/viewer/show", json={"job_id": job["id"]}).json()
    assert state["layers"] == ["cloud", "fem", "corrected", "probe"] and state["mesh"]["nodes"] == N


@pytest.mark.slow
def test_dashboard_and_viewer_show_a_dome_run_in_chromium(dome, dome_run, chromium, tmp_path):
    """The finished dome replay (stored as the runner stores it) in a real browser: the
    results panel names the STL mesh and its counts, the view button loads it into the
    embedded viewer (its frame text appears) and the status line names the mesh."""
    import shutil

    import httpx

    from app.run_mesh import mesh_summary
    from app.server.jobs.types import ReplayParams
    from tests.app._server import Server, store_finished_jobs
    from tests.app.test_browser import _viewer_connected

    folder, result, _ = dome_run
    data = tmp_path / "data"
    job_dir = data / "jobs" / "1"
    shutil.copytree(folder, job_dir)
    summary = {**result.to_json(), "viewer": True}
    summary["mesh"] = {**mesh_summary(result.mesh), **summary["mesh"]}
    store_finished_jobs(data, dome, "dome", [(1, "replay", ReplayParams(session_id=1, sequences=["seq01"]), summary,
                                              job_dir)])
    server = Server(data, viewer=True, args=["--workers", "1"])
    page = chromium.new_page(viewport={"width": 1300, "height": 1300})
    try:
        page.goto(server.url + "/#job-1")
        page.wait_for_selector("body[data-ready='1']")
        text = page.locator("#replay-mesh").inner_text(timeout=30_000)
        n, e = result.mesh.n_nodes, result.mesh.n_tets
        assert text == f"STL phantom: Gmsh mesh, {n} nodes, {e} tetrahedra"
        assert page.locator("#replay-mesh").get_attribute("data-kind") == "stl"
        _viewer_connected(page, server)
        page.click("#result-body .view-btn")
        page.frame_locator("#viewer-frame").get_by_text("frame 0 /", exact=False).wait_for(timeout=30_000)
        page.wait_for_function("document.querySelector('#viewer-status').textContent.includes('STL phantom')",
                               timeout=30_000)
        assert f"{n} nodes, {e} tetrahedra" in page.locator("#viewer-status").inner_text()
        state = httpx.get(f"{server.url}/api/viewer").json()
        assert state["run_id"] == 1 and state["mesh"]["kind"] == "stl"
    finally:
        page.close()
        server.stop()
