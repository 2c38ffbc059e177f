"""Virtual lab end to end: sessions readable by core.io, truth complete, conventions of the
input-side effects, determinism, the small preset's cost."""

import dataclasses
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from core.lab import PRESETS, LabConfig, LabError, Intrinsics, generate_session

sim = pytest.importorskip("core.simulation", reason="core.simulation is not available yet")
from core.io import SessionExistsError, read_session, read_truth  # noqa: E402

SIZE = np.array([0.0687, 0.0393, 0.0358])

ALL_EFFECTS = [
    {"kind": "gravity"},
    {"kind": "inclusion", "center": [0.03, 0.02, 0.025], "radius": 0.007},
    {"kind": "viscoelasticity", "relaxation_time": 0.3},
    {"kind": "friction"},
    {"kind": "base_compliance", "stiffness": 3e5},
    {"kind": "probe_radius", "radius": 0.0055},
    {"kind": "time_offset", "offset": 0.04},
    {"kind": "kinematic_offset"},
]

# A tiny session for convention and determinism checks: 2 x 10 s, 5 Hz, 160 x 120,
# coarse truth mesh, no encoder noise (so kinematics can be compared exactly).
TINY = LabConfig(
    sequence_durations=(10.0, 10.0),
    sequence_roles=("train", "test"),
    camera_rate_hz=5.0,
    kinematics_rate_hz=100.0,
    intrinsics=Intrinsics.from_fov(160, 120, 64.0),
    grid=(10, 5, 5),
    dt=1.0 / 60.0,
    newton_iterations=1,
    encoder_noise=0.0,
    reference_frames=1,
    workers=0,
)


def files_of(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def to_phantom(T, pts):
    T = np.asarray(T)
    return np.asarray(pts, float) @ T[:3, :3].T + T[:3, 3]


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    out = tmp_path_factory.mktemp("lab") / "small"
    messages = []
    path = generate_session(out, preset="small", seed=3, effects=ALL_EFFECTS, with_force=True,
                            callback=lambda f, m: messages.append((f, m)))
    return path, messages


def test_small_session_is_readable(small):
    """(Generation time is measured in benchmarks/bench_lab.py, not asserted.)"""
    path, messages = small
    s = read_session(path, check_clouds=True)
    assert [q.role for q in s.sequences.values()] == ["validation", "test", "train", "train"]
    assert s.has_force
    assert s.meta.probe.radius == 0.005  # nominal, although the true radius differs
    assert s.meta.camera.intrinsics["width"] == 320
    assert s.reference_cloud() is not None and len(s.reference_cloud()) > 1000
    for q in s.sequences.values():
        assert len(q) == pytest.approx(10.0 * 15, abs=2)
        assert q.kinematics.t[-1] >= q.frames.t[-1]
        n = [len(q.cloud(i)) for i in range(0, len(q), 25)]
        assert 2000 < min(n) and max(n) < 8000, n  # "a few thousand raw points per frame"
    fr = [f for f, _ in messages]
    assert fr[0] == 0.0 and fr[-1] == 1.0 and all(b >= a - 1e-12 for a, b in zip(fr, fr[1:]))


def test_truth_holds_every_effect_with_all_parameters(small):
    path, _ = small
    truth = read_truth(path)
    assert truth["format"] == "tissue-truth/1"
    assert truth["generator"]["name"] == "tissuetwin-lab" and truth["generator"]["seed"] == 3
    kinds = [e["kind"] for e in truth["effects"]]
    assert kinds == [e["kind"] for e in ALL_EFFECTS]
    for e in truth["effects"]:
        cls = sim.EFFECT_KINDS[e["kind"]]
        assert set(e) == {"kind"} | {f.name for f in dataclasses.fields(cls)}, e
    by = {e["kind"]: e for e in truth["effects"]}
    assert by["inclusion"]["center"] == [0.03, 0.02, 0.025] and by["inclusion"]["radius"] == 0.007
    assert by["base_compliance"]["stiffness"] == 3e5
    assert by["probe_radius"]["radius"] == 0.0055 and truth["probe"]["radius_true"] == 0.0055
    assert truth["youngs_modulus"] == 5000.0 and truth["poisson_ratio"] == 0.44
    assert truth["material"]["law"] == "stable_neo_hookean"
    assert truth["mesh"]["grid"] == list(PRESETS["small"].grid) == [25, 9, 9]
    for key in ("T_phantom_robot", "T_phantom_camera"):
        T = np.asarray(truth[key])
        np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(T[3], [0, 0, 0, 1])
    robot_origin = np.asarray(truth["T_phantom_robot"])[:3, 3]
    assert 0.2 <= np.linalg.norm(robot_origin) <= 0.5
    seqs = truth["sequences"]
    assert [q["role"] for q in seqs] == ["validation", "test", "train", "train"]
    assert all(q["pokes"] for q in seqs)


def test_corners_and_clouds_agree_with_the_true_transforms(small):
    path, _ = small
    s = read_session(path)
    truth = read_truth(path)
    r_true = truth["probe"]["radius_true"]
    corners = to_phantom(truth["T_phantom_robot"], s.corners.positions)
    expected = s.corners.phantom_points(SIZE, r_true)
    err = np.linalg.norm(corners - expected, axis=1)
    assert err.max() < 0.0015  # 0.3 mm per axis touch noise: 5 sigma
    # the reference cloud's top points sit on the (sagged) top face
    ref = to_phantom(truth["T_phantom_camera"], s.reference_cloud())
    top = ref[(ref[:, 0] > 0.01) & (ref[:, 0] < SIZE[0] - 0.01) & (ref[:, 1] > 0.01)
              & (ref[:, 1] < SIZE[1] - 0.01) & (ref[:, 2] > 0.025)]
    assert len(top) > 500
    # gravity (~1 mm at E = 5 kPa) plus the elastic base (weight / area / stiffness ~1.3 mm)
    # lower the top; with noise sigma ~1 mm the median of >500 points is good to ~0.1 mm
    sag = SIZE[2] - np.median(top[:, 2])
    assert 0.0005 < sag < 0.004


def test_kinematics_see_the_pokes_with_offsets_applied(small):
    """Map the written kinematics to the phantom frame, undo the kinematic offset: a top
    poke's deepest point is top + true radius - depth."""
    path, _ = small
    s = read_session(path)
    truth = read_truth(path)
    by = {e["kind"]: e for e in truth["effects"]}
    off = np.asarray(by["kinematic_offset"]["offset"])
    dt = by["time_offset"]["offset"]
    r = truth["probe"]["radius_true"]
    checked = 0
    for q, tq in zip(s.sequences.values(), truth["sequences"]):
        p = to_phantom(truth["T_phantom_robot"], q.kinematics.position) + off
        for poke in tq["pokes"]:
            if poke["kind"] != "top":
                continue
            sel = (q.kinematics.t >= poke["t_start"] + dt) & (q.kinematics.t <= poke["t_end"] + dt)
            assert p[sel, 2].min() == pytest.approx(SIZE[2] + r - poke["depth"], abs=1e-4)
            checked += 1
        # tool frame: z points from the shaft to the tip, i.e. down into the phantom
        from scipy.spatial.transform import Rotation

        z_tool = Rotation.from_quat(q.kinematics.quaternion[0]).as_matrix()[:, 2]
        z_phantom = np.asarray(truth["T_phantom_robot"])[:3, :3] @ z_tool
        assert -np.cos(np.radians(36)) > z_phantom[2] > -np.cos(np.radians(14))
        # forces: the probe pushes, so over a sequence the phantom is pressed (net push inward)
        f = q.kinematics.force @ np.asarray(truth["T_phantom_robot"])[:3, :3].T
        assert np.abs(f).max() > 0.05
    assert checked >= 1


def test_input_effects_shift_only_the_kinematics(tmp_path):
    """time_offset and kinematic_offset leave the truth and the clouds untouched; the written
    kinematics become k(s) = p(s - offset) - offset_xyz (robot frame)."""
    a = generate_session(tmp_path / "a", preset=TINY, seed=11)
    b = generate_session(tmp_path / "b", preset=TINY, seed=11, effects=[
        {"kind": "time_offset", "offset": 0.2}, {"kind": "kinematic_offset", "offset": [0.002, -0.001, 0.0005]}])
    fa, fb = files_of(a), files_of(b)
    clouds = [k for k in fa if k.endswith(".ply") or k.endswith("frames.csv")]
    assert clouds and all(fa[k] == fb[k] for k in clouds)
    sa, sb = read_session(a), read_session(b)
    T = np.asarray(read_truth(a)["T_phantom_robot"])
    for name in sa.sequences:
        ka, kb = sa.sequences[name].kinematics, sb.sequences[name].kinematics
        shift = 20  # 0.2 s at 100 Hz
        pa = to_phantom(T, ka.position)
        pb = to_phantom(T, kb.position)
        np.testing.assert_allclose(pb[shift:], pa[:-shift] - [0.002, -0.001, 0.0005], atol=1e-9)
        np.testing.assert_array_equal(ka.quaternion, kb.quaternion)


def test_same_seed_same_files_other_seed_other_files(tmp_path):
    a = files_of(generate_session(tmp_path / "a", preset=TINY, seed=5))
    b = files_of(generate_session(tmp_path / "b", preset=TINY, seed=5))
    c = files_of(generate_session(tmp_path / "c", preset=TINY, seed=6))
    assert a == b
    assert a["truth.json"] != c["truth.json"]
    assert a["sequences/seq00/clouds/000000.ply"] != c["sequences/seq00/clouds/000000.ply"]


def test_worker_process_gives_identical_files(tmp_path):
    a = files_of(generate_session(tmp_path / "a", preset=TINY, seed=2))
    b = files_of(generate_session(tmp_path / "b", preset=replace(TINY, workers=1), seed=2))
    assert a == b


def test_bad_inputs_are_reported(tmp_path):
    with pytest.raises(LabError, match="unknown preset"):
        generate_session(tmp_path / "x", preset="huge")
    with pytest.raises(LabError, match="unknown effect kind"):
        generate_session(tmp_path / "x", preset=TINY, effects=[{"kind": "magnetism"}])
    with pytest.raises(LabError, match="no parameter"):
        generate_session(tmp_path / "x", preset=TINY, effects=[{"kind": "gravity", "gee": 1}])
    with pytest.raises(LabError, match="twice"):
        generate_session(tmp_path / "x", preset=TINY, effects=[{"kind": "gravity"}, {"kind": "gravity"}])
    assert not (tmp_path / "x").exists()
    out = generate_session(tmp_path / "y", preset=TINY, seed=0)
    with pytest.raises(SessionExistsError):
        generate_session(out, preset=TINY, seed=0)
    generate_session(out, preset=TINY, seed=1, overwrite=True)
    assert read_truth(out)["generator"]["seed"] == 1


def test_presets_are_consistent():
    for name, cfg in PRESETS.items():
        assert len(cfg.sequence_durations) == len(cfg.sequence_roles), name
        assert {"validation", "test", "train"} <= set(cfg.sequence_roles), name
    paper = PRESETS["paper"]
    assert len(paper.sequence_durations) == 12 and paper.sequence_durations[0] == 120.0
    assert paper.sequence_roles[:3] == ("validation", "test", "test")
    assert paper.camera_rate_hz == 30.0 and paper.kinematics_rate_hz == 1000.0


def test_a_diverging_truth_is_retried_with_stronger_numerics(tmp_path):
    """Field seed 111 draws the finest mesh (31x11x11) with the stiffest contact
    (1.4e6 E/m): one Newton iteration per 1/120 s step diverged at t = 2.9 s and the
    generator gave up. It now retries with more iterations (then smaller steps) and
    says so in truth.json."""
    path = generate_session(tmp_path / "s", preset=PRESETS["field"].with_duration(6.0), seed=111, with_force=True)
    truth = read_truth(path)
    assert truth["sim"]["newton_iterations"] == 1
    retried = truth["sim"]["retried"]
    assert retried and all(r["newton_iterations"] >= 3 for r in retried.values())
    session = read_session(path)
    for name, seq in session.sequences.items():
        assert np.all(np.isfinite(seq.kinematics.force))
    assert max(s["max_displacement"] for s in truth["sequences"]) < 0.02  # a dent, not a blow-up
