"""Tests of core.io.session: write -> read round trips, the independent sample session,
one error class per bad input, and the writer's safety guarantees."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from core.errors import (
    ColumnError,
    MissingFileError,
    PlyError,
    SessionFormatError,
    TimestampError,
    UnitsError,
)
from core.io import (
    CameraSpec,
    Corners,
    Kinematics,
    PhantomSpec,
    ProbeSpec,
    SequenceSpec,
    SessionExistsError,
    SessionMeta,
    SessionWriter,
    read_session,
    read_truth,
    write_ply,
    write_session,
)

SAMPLE = Path(__file__).parents[2].parent / "shared" / "sample-session"
SIZE = np.array([0.0687, 0.0393, 0.0358])
RADIUS = 0.005
N_FRAMES = 3


# --------------------------------------------------------------------------------------
# A small synthetic session
# --------------------------------------------------------------------------------------


def make_meta(names=("seq00", "seq01"), roles=("train", "test")) -> SessionMeta:
    """Metadata with unknown keys at the top level, nested in objects and in sequences."""
    raw = {
        "format": "tissue-session/1",
        "lab": {"operator": "ana", "room": 3},
        "phantom": {"material_note": "Ecoflex 00-30"},
        "camera": {"model": "D405"},
        "sequences": [{"name": names[0], "role": roles[0], "notes": "first poke"}],
    }
    return SessionMeta(
        phantom=PhantomSpec(size=SIZE, mass=0.10401),
        probe=ProbeSpec(radius=RADIUS),
        camera=CameraSpec(rate_hz=30.0, depth_accuracy=0.002,
                          intrinsics={"width": 64, "height": 48, "fx": 50.0, "fy": 50.0,
                                      "cx": 32.0, "cy": 24.0}),
        sequences=tuple(SequenceSpec(n, r) for n, r in zip(names, roles)),
        raw=raw,
    )


def make_kinematics(seed: int, k: int = 25, force: bool = True, extra: bool = True) -> Kinematics:
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.001, 0.01, size=k))  # full-precision, irregular
    q = rng.normal(size=(k, 4))
    return Kinematics(
        t=t,
        position=np.array([0.4, -0.02, -0.1]) + rng.normal(0, 0.01, size=(k, 3)),
        quaternion=q,
        force=rng.normal(0, 0.5, size=(k, 3)) if force else None,
        extra={"jaw": rng.uniform(size=k), "e_force_est": rng.normal(size=k)} if extra else {},
    )


def make_corners() -> Corners:
    pos = np.array([[0.40, -0.02, -0.11], [0.47, -0.02, -0.11], [0.40, 0.02, -0.11],
                    [0.47, 0.02, -0.11], [0.4001, -0.0199, -0.1101]])
    return Corners(labels=("x0y0", "x1y0", "x0y1", "x1y1", "x0y0"), positions=pos)


def make_cloud(seed: int, n: int = 60) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.array([0.0, 0.0, 0.35]) + rng.normal(0, 0.03, size=(n, 3))


def frame_times(seed: int) -> np.ndarray:
    return 0.01 + np.arange(N_FRAMES) / 30.0 + seed * 1e-4


def build_session(path: Path, *, force=(True, False), binary: bool = True, stl: bool = False,
                  overwrite: bool = False, meta: SessionMeta | None = None) -> dict:
    """Write a 2-sequence session; return everything written, for comparison."""
    meta = meta or make_meta()
    written = {"meta": meta, "corners": make_corners(), "reference": make_cloud(99, 100),
               "kinematics": {}, "clouds": {}, "truth": {"format": "tissue-truth/1",
                                                         "effects": [], "T": np.eye(4)}}
    with SessionWriter(path, meta, overwrite=overwrite, ply_binary=binary) as w:
        w.write_corners(written["corners"])
        w.write_reference(written["reference"])
        if stl:
            import trimesh

            box = trimesh.creation.box(extents=SIZE)
            box.apply_translation(SIZE / 2)
            w.write_phantom_stl(box)
        for s, spec in enumerate(meta.sequences):
            kin = make_kinematics(s, force=force[s % len(force)])
            w.write_kinematics(spec.name, kin)
            written["kinematics"][spec.name] = kin
            for i, t in enumerate(frame_times(s)):
                pts = make_cloud(10 * s + i)
                w.write_frame(spec.name, i, t, pts)
                written["clouds"][(spec.name, i)] = pts
        w.write_truth(written["truth"])
    return written


def assert_kinematics_equal(a: Kinematics, b: Kinematics) -> None:
    # repr() is round-trip exact: everything but the re-normalised quaternion is bitwise equal.
    np.testing.assert_array_equal(a.t, b.t)
    np.testing.assert_array_equal(a.position, b.position)
    np.testing.assert_allclose(a.quaternion, b.quaternion, rtol=0, atol=1e-15)  # 1 ulp-ish
    if a.force is None:
        assert b.force is None
    else:
        np.testing.assert_array_equal(a.force, b.force)
    assert list(a.extra) == list(b.extra)
    for k in a.extra:
        np.testing.assert_array_equal(a.extra[k], b.extra[k])


def f32(a: np.ndarray) -> np.ndarray:
    return np.asarray(a).astype(np.float32).astype(np.float64)


def snapshot(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha1(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


# --------------------------------------------------------------------------------------
# Round trips
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("binary", [True, False], ids=["binary_ply", "ascii_ply"])
def test_write_read_round_trip(tmp_path, binary):
    path = tmp_path / "s"
    w = build_session(path, binary=binary, stl=True)
    s = read_session(path, check_clouds=True)

    meta = w["meta"]
    assert s.meta.to_json() == meta.to_json()
    assert s.meta.phantom == meta.phantom and s.meta.probe == meta.probe
    assert s.meta.camera == meta.camera and s.meta.sequences == meta.sequences
    # unknown keys, top level and nested, survive
    assert s.meta.raw["lab"] == {"operator": "ana", "room": 3}
    assert s.meta.raw["phantom"]["material_note"] == "Ecoflex 00-30"
    assert s.meta.raw["camera"]["model"] == "D405"
    assert s.meta.raw["sequences"][0]["notes"] == "first poke"

    assert s.corners == w["corners"]
    np.testing.assert_array_equal(s.reference_cloud(), f32(w["reference"]))
    assert list(s.sequences) == ["seq00", "seq01"]
    for name, kin in w["kinematics"].items():
        seq = s.sequences[name]
        assert_kinematics_equal(kin, seq.kinematics)
        assert len(seq) == N_FRAMES
        np.testing.assert_array_equal(seq.frames.index, np.arange(N_FRAMES))
        np.testing.assert_array_equal(seq.frames.t, frame_times(int(name[-1])))
        assert seq.frames.files[1] == "clouds/000001.ply"
        for i in range(N_FRAMES):
            cloud = seq.cloud(i)
            assert cloud.dtype == np.float64 and cloud.shape == (60, 3)
            np.testing.assert_array_equal(cloud, f32(w["clouds"][(name, i)]))
    assert s.sequences["seq00"].has_force and not s.sequences["seq01"].has_force
    assert not s.has_force
    assert [q.name for q in s.sequences_with_role("test")] == ["seq01"]
    assert s.sequences_with_role("validation") == []
    assert read_truth(path) == {"format": "tissue-truth/1", "effects": [],
                                "T": np.eye(4).tolist()}
    mesh = s.phantom_mesh()
    np.testing.assert_allclose(mesh.bounds, [np.zeros(3), SIZE], atol=1e-7)  # float32 STL
    assert [p.name for p in tmp_path.iterdir()] == ["s"]  # no temporary folder left


def test_has_force_when_all_sequences_have_it(tmp_path):
    build_session(tmp_path / "s", force=(True,))
    assert read_session(tmp_path / "s").has_force


def test_write_session_copy_round_trip(tmp_path):
    build_session(tmp_path / "a", stl=True)
    a = read_session(tmp_path / "a")
    out = write_session(a, tmp_path / "b")
    b = read_session(out, check_clouds=True)
    assert b.meta.to_json() == a.meta.to_json()
    assert b.corners == a.corners
    np.testing.assert_array_equal(b.reference_cloud(), a.reference_cloud())
    for name, seq in a.sequences.items():
        assert_kinematics_equal(seq.kinematics, b.sequences[name].kinematics)
        assert b.sequences[name].frames == seq.frames
        for i in range(len(seq)):
            np.testing.assert_array_equal(b.sequences[name].cloud(i), seq.cloud(i))
    assert read_truth(out) == read_truth(tmp_path / "a")
    assert (out / "phantom.stl").read_bytes() == (tmp_path / "a" / "phantom.stl").read_bytes()
    # and in place, replacing itself
    write_session(b, out, overwrite=True)
    assert read_session(out).meta.to_json() == a.meta.to_json()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "b"]


def test_meta_to_json_without_raw():
    meta = SessionMeta(PhantomSpec(SIZE, 0.1), ProbeSpec(0.005), CameraSpec(30.0, 0.002),
                       (SequenceSpec("s", "train"),))
    assert meta.to_json() == {
        "format": "tissue-session/1",
        "phantom": {"shape": "box", "size": SIZE.tolist(), "mass": 0.1, "fixed": "bottom"},
        "probe": {"shape": "sphere", "radius": 0.005},
        "camera": {"rate_hz": 30.0, "depth_accuracy": 0.002},
        "sequences": [{"name": "s", "role": "train"}],
    }


def test_quaternions_are_normalised_on_read(tmp_path):
    build_session(tmp_path / "s")
    p = tmp_path / "s" / "sequences" / "seq00" / "kinematics.csv"
    for col, v in zip(("qx", "qy", "qz", "qw"), ("0", "0", "0", "2.0")):
        _csv_set(p, 2, col, v)
    q = read_session(tmp_path / "s").sequences["seq00"].kinematics.quaternion
    np.testing.assert_array_equal(q[1], [0, 0, 0, 1])
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, rtol=1e-15)


def test_corner_phantom_points():
    c = Corners(("x0y0", "x1y1", "x1y0", "x0y1"), np.zeros((4, 3)))
    np.testing.assert_array_equal(
        c.phantom_points(SIZE, RADIUS),
        [[0, 0, SIZE[2] + RADIUS], [SIZE[0], SIZE[1], SIZE[2] + RADIUS],
         [SIZE[0], 0, SIZE[2] + RADIUS], [0, SIZE[1], SIZE[2] + RADIUS]],
    )


# --------------------------------------------------------------------------------------
# The sample session written by an independent tool
# --------------------------------------------------------------------------------------


@pytest.mark.skipif(not SAMPLE.is_dir(), reason="shared sample session absent")
def test_reads_sample_session():
    s = read_session(SAMPLE, check_clouds=True)
    assert s.meta.to_json() == json.loads((SAMPLE / "session.json").read_text())
    assert {n: q.role for n, q in s.sequences.items()} == {
        "seq00": "validation", "seq01": "test", "seq02": "train", "seq03": "train"}
    assert s.meta.camera.intrinsics["width"] == 320
    assert not s.has_force and s.phantom_stl is None
    assert len(s.corners) == 12
    for seq in s.sequences.values():
        kin = seq.kinematics
        assert len(kin) == 2401 and len(seq) == 179
        np.testing.assert_allclose(np.linalg.norm(kin.quaternion, axis=1), 1.0, rtol=1e-12)
        assert kin.t[0] <= seq.frames.t[0] and seq.frames.t[-1] <= kin.t[-1]
        for i in (0, -1):
            cloud = seq.cloud(i)
            assert cloud.shape[1] == 3 and len(cloud) > 100
            assert 0.05 < np.median(np.linalg.norm(cloud, axis=1)) < 2.0  # metres, not mm
    assert s.reference_cloud().shape[1] == 3


@pytest.mark.skipif(not (SAMPLE / "truth.json").is_file(), reason="shared sample session absent")
def test_sample_corners_agree_with_truth():
    """Independent check of the corner convention: corners mapped by the generator's
    T_phantom_robot land on the phantom-frame sphere centres. Tolerance 2 mm: the
    touches carry ~0.5 mm of simulated jitter."""
    s = read_session(SAMPLE)
    T = np.array(read_truth(SAMPLE)["T_phantom_robot"])
    mapped = s.corners.positions @ T[:3, :3].T + T[:3, 3]
    expected = s.corners.phantom_points(s.meta.phantom.size, s.meta.probe.radius)
    assert np.abs(mapped - expected).max() < 2e-3


# --------------------------------------------------------------------------------------
# Bad inputs: each gets its own error class and a message naming the file
# --------------------------------------------------------------------------------------


def _csv_rows(path: Path) -> list[list[str]]:
    return [line.split(",") for line in path.read_text().splitlines()]


def _csv_write(path: Path, rows: list[list[str]]) -> None:
    path.write_text("\n".join(",".join(r) for r in rows) + "\n")


def _csv_set(path: Path, row: int, col: str, value: str) -> None:
    """Set data row ``row`` (1-based) of column ``col``."""
    rows = _csv_rows(path)
    rows[row][rows[0].index(col)] = value
    _csv_write(path, rows)


def _csv_drop(path: Path, col: str) -> None:
    rows = _csv_rows(path)
    j = rows[0].index(col)
    _csv_write(path, [r[:j] + r[j + 1:] for r in rows])


def _csv_map(path: Path, cols: tuple[str, ...], fn) -> None:
    rows = _csv_rows(path)
    js = [rows[0].index(c) for c in cols]
    for r in rows[1:]:
        for j in js:
            r[j] = repr(fn(float(r[j])))
    _csv_write(path, rows)


def _json_edit(fn):
    def mutate(root: Path) -> None:
        p = root / "session.json"
        obj = json.loads(p.read_text())
        fn(obj)
        p.write_text(json.dumps(obj))
    return mutate


KIN0 = Path("sequences/seq00/kinematics.csv")
KIN1 = Path("sequences/seq01/kinematics.csv")  # seq01 has no force columns
FRAMES0 = Path("sequences/seq00/frames.csv")
CORNERS = Path("calibration/corners.csv")
CLOUD1 = Path("sequences/seq00/clouds/000001.ply")
_PLY_HEAD = "ply\nformat {fmt} 1.0\nelement vertex {n}\n{props}end_header\n"
_XYZ = "property float x\nproperty float y\nproperty float z\n"

# (id, mutation of a good session folder, expected class, file named in the message)
BAD_INPUTS = [
    # missing files
    ("missing_session_json", lambda r: (r / "session.json").unlink(), MissingFileError,
     "session.json"),
    ("missing_corners", lambda r: (r / CORNERS).unlink(), MissingFileError, "corners.csv"),
    ("missing_kinematics", lambda r: (r / KIN0).unlink(), MissingFileError, "kinematics.csv"),
    ("missing_frames", lambda r: (r / FRAMES0).unlink(), MissingFileError, "frames.csv"),
    ("missing_cloud", lambda r: (r / CLOUD1).unlink(), MissingFileError, "000001.ply"),
    ("missing_sequence_folder", lambda r: shutil.rmtree(r / "sequences" / "seq01"),
     MissingFileError, "seq01"),
    # PLY (checked up front with check_clouds=True)
    ("ply_truncated", lambda r: (r / CLOUD1).write_bytes((r / CLOUD1).read_bytes()[:-5]),
     PlyError, "000001.ply"),
    ("ply_empty_file", lambda r: (r / CLOUD1).write_bytes(b""), PlyError, "000001.ply"),
    ("ply_zero_vertices",
     lambda r: (r / CLOUD1).write_text(_PLY_HEAD.format(fmt="ascii", n=0, props=_XYZ)),
     PlyError, "000001.ply"),
    ("ply_malformed_header",
     lambda r: (r / CLOUD1).write_text("ply\nformat ascii 1.0\nelement vertex two\n"),
     PlyError, "000001.ply"),
    ("ply_no_float_xyz",
     lambda r: (r / CLOUD1).write_text(_PLY_HEAD.format(
         fmt="ascii", n=1, props="property uchar x\nproperty uchar y\nproperty uchar z\n")
         + "1 2 3\n"),
     PlyError, "000001.ply"),
    # timestamps
    ("kin_t_nan", lambda r: _csv_set(r / KIN0, 3, "t", "nan"), TimestampError, "kinematics.csv"),
    ("kin_t_inf", lambda r: _csv_set(r / KIN0, 3, "t", "inf"), TimestampError, "kinematics.csv"),
    ("kin_t_decreasing", lambda r: _csv_set(r / KIN0, 5, "t", "0.0"), TimestampError,
     "kinematics.csv"),
    ("kin_t_duplicate", lambda r: _csv_set(r / KIN0, 5, "t", _csv_rows(r / KIN0)[4][0]),
     TimestampError, "kinematics.csv"),
    ("frames_t_nan", lambda r: _csv_set(r / FRAMES0, 2, "t", "nan"), TimestampError,
     "frames.csv"),
    ("frames_t_duplicate", lambda r: _csv_set(r / FRAMES0, 2, "t", _csv_rows(r / FRAMES0)[1][1]),
     TimestampError, "frames.csv"),
    # columns
    ("kin_missing_qw", lambda r: _csv_drop(r / KIN0, "qw"), ColumnError, "kinematics.csv"),
    ("kin_only_fx", lambda r: (_csv_drop(r / KIN0, "fy"), _csv_drop(r / KIN0, "fz")),
     ColumnError, "kinematics.csv"),
    ("kin_partial_force_fx_fy", lambda r: _csv_drop(r / KIN0, "fz"), ColumnError,
     "kinematics.csv"),
    ("kin_non_numeric", lambda r: _csv_set(r / KIN1, 4, "x", "abc"), ColumnError,
     "kinematics.csv"),
    ("kin_empty_cell", lambda r: _csv_set(r / KIN1, 4, "y", ""), ColumnError, "kinematics.csv"),
    ("kin_nan_position", lambda r: _csv_set(r / KIN0, 2, "z", "nan"), ColumnError,
     "kinematics.csv"),
    ("kin_zero_quaternion",
     lambda r: [_csv_set(r / KIN0, 6, c, "0") for c in ("qx", "qy", "qz", "qw")],
     ColumnError, "kinematics.csv"),
    ("kin_duplicate_column", lambda r: _csv_set(r / KIN1, 0, "qw", "qx"), ColumnError,
     "kinematics.csv"),
    ("frames_non_integer_frame", lambda r: _csv_set(r / FRAMES0, 2, "frame", "1.5"), ColumnError,
     "frames.csv"),
    ("frames_missing_file_column", lambda r: _csv_drop(r / FRAMES0, "file"), ColumnError,
     "frames.csv"),
    ("corners_bad_label", lambda r: _csv_set(r / CORNERS, 2, "corner", "x2y0"), ColumnError,
     "corners.csv"),
    ("corners_non_numeric", lambda r: _csv_set(r / CORNERS, 2, "x", "0.4m"), ColumnError,
     "corners.csv"),
    # units
    ("phantom_size_mm", _json_edit(lambda o: o["phantom"].update(size=[68.7, 39.3, 35.8])),
     UnitsError, "session.json"),
    ("corners_mm", lambda r: _csv_map(r / CORNERS, ("x", "y", "z"), lambda v: v * 1000),
     UnitsError, "corners.csv"),
    ("kinematics_mm", lambda r: _csv_map(r / KIN0, ("x", "y", "z"), lambda v: v * 1000),
     UnitsError, "kinematics.csv"),
    ("cloud_mm", lambda r: write_ply(r / CLOUD1, make_cloud(5) * 1000), UnitsError, "000001.ply"),
    # session.json
    ("json_invalid", lambda r: (r / "session.json").write_text("{'format': 1"),
     SessionFormatError, "session.json"),
    ("json_wrong_format", _json_edit(lambda o: o.update(format="tissue-session/2")),
     SessionFormatError, "session.json"),
    ("json_missing_format", _json_edit(lambda o: o.pop("format")), SessionFormatError,
     "session.json"),
    ("json_missing_phantom", _json_edit(lambda o: o.pop("phantom")), SessionFormatError,
     "session.json"),
    ("json_missing_probe", _json_edit(lambda o: o.pop("probe")), SessionFormatError,
     "session.json"),
    ("json_missing_sequences", _json_edit(lambda o: o.pop("sequences")), SessionFormatError,
     "session.json"),
    ("json_bad_role", _json_edit(lambda o: o["sequences"][0].update(role="training")),
     SessionFormatError, "session.json"),
    ("json_size_non_positive", _json_edit(lambda o: o["phantom"].update(size=[0.06, 0.0, 0.03])),
     SessionFormatError, "session.json"),
    ("json_mass_zero", _json_edit(lambda o: o["phantom"].update(mass=0)), SessionFormatError,
     "session.json"),
    ("json_radius_negative", _json_edit(lambda o: o["probe"].update(radius=-0.005)),
     SessionFormatError, "session.json"),
    ("json_duplicate_sequence", _json_edit(lambda o: o["sequences"][1].update(name="seq00")),
     SessionFormatError, "session.json"),
]


@pytest.mark.parametrize("mutate,error,file", [c[1:] for c in BAD_INPUTS],
                         ids=[c[0] for c in BAD_INPUTS])
def test_bad_input_raises_its_own_error(tmp_path, mutate, error, file):
    root = tmp_path / "s"
    build_session(root)
    mutate(root)
    with pytest.raises(SessionFormatError) as info:
        s = read_session(root, check_clouds=True)
        for seq in s.sequences.values():  # clouds' units are checked when read
            for i in range(len(seq)):
                seq.cloud(i)
    assert type(info.value) is error, f"{type(info.value).__name__}: {info.value}"
    assert file in str(info.value)
    if error is UnitsError:
        assert "looks like millimetres" in str(info.value)


def test_units_message_quotes_the_value(tmp_path):
    build_session(tmp_path / "s")
    _json_edit(lambda o: o["phantom"].update(size=[68.7, 39.3, 35.8]))(tmp_path / "s")
    with pytest.raises(UnitsError, match=r"68\.7"):
        read_session(tmp_path / "s")


def test_timestamp_message_names_row_and_values(tmp_path):
    build_session(tmp_path / "s")
    kin = tmp_path / "s" / KIN0
    _csv_set(kin, 5, "t", "0.0")
    with pytest.raises(TimestampError, match=r"kinematics\.csv: column 't' is not strictly "
                                             r"increasing at row 5 \(line 6\) \(0\.0 after"):
        read_session(tmp_path / "s")


@pytest.mark.parametrize("case", ["ply_truncated", "ply_zero_vertices", "ply_no_float_xyz"])
def test_bad_cloud_is_found_lazily_without_check_clouds(tmp_path, case):
    root = tmp_path / "s"
    build_session(root)
    dict((c[0], c[1]) for c in BAD_INPUTS)[case](root)
    seq = read_session(root).sequences["seq00"]  # does not parse clouds
    seq.cloud(0)
    with pytest.raises(PlyError, match="000001.ply"):
        seq.cloud(1)
    with pytest.raises(IndexError):
        seq.cloud(N_FRAMES)


# --------------------------------------------------------------------------------------
# Writer safety
# --------------------------------------------------------------------------------------


def test_writer_refuses_existing_folder_by_default(tmp_path):
    path = tmp_path / "s"
    build_session(path)
    before = snapshot(path)
    with pytest.raises(SessionExistsError, match="already exists") as info:
        SessionWriter(path, make_meta())
    assert isinstance(info.value, FileExistsError)
    assert snapshot(path) == before
    assert [p.name for p in tmp_path.iterdir()] == ["s"]


def test_exception_mid_write_leaves_existing_session_untouched(tmp_path):
    path = tmp_path / "s"
    build_session(path)
    before = snapshot(path)
    with pytest.raises(RuntimeError, match="boom"):
        with SessionWriter(path, make_meta(), overwrite=True) as w:
            w.write_corners(make_corners())
            w.write_kinematics("seq00", make_kinematics(7))
            w.write_frame("seq00", 0, 0.0, make_cloud(1))
            raise RuntimeError("boom")
    assert snapshot(path) == before
    assert [p.name for p in tmp_path.iterdir()] == ["s"]  # temporary folder removed


def test_validation_error_mid_write_leaves_nothing(tmp_path):
    path = tmp_path / "new"
    with pytest.raises(TimestampError, match="frames.csv"):
        with SessionWriter(path, make_meta()) as w:
            w.write_frame("seq00", 0, 0.5, make_cloud(1))
            w.write_frame("seq00", 1, 0.5, make_cloud(2))
    assert list(tmp_path.iterdir()) == []


def test_overwrite_replaces_only_at_finish(tmp_path):
    path = tmp_path / "s"
    build_session(path)
    before = snapshot(path)
    meta2 = make_meta(names=("only",), roles=("validation",))
    w = SessionWriter(path, meta2, overwrite=True)
    w.write_corners(make_corners())
    w.write_kinematics("only", make_kinematics(3, force=False, extra=False))
    w.write_frame("only", 4, 1.0, make_cloud(3))
    assert snapshot(path) == before  # still the old session
    assert w.finish() == path
    s = read_session(path)
    assert list(s.sequences) == ["only"] and s.sequences["only"].frames.files == (
        "clouds/000004.ply",)
    assert [p.name for p in tmp_path.iterdir()] == ["s"]


def test_overwrite_refuses_a_folder_that_is_not_a_session(tmp_path):
    path = tmp_path / "precious"
    path.mkdir()
    (path / "thesis.tex").write_text("do not delete")
    with pytest.raises(SessionExistsError, match="session.json"):
        SessionWriter(path, make_meta(), overwrite=True)
    assert (path / "thesis.tex").read_text() == "do not delete"


def test_finish_requires_corners_kinematics_and_frames(tmp_path):
    meta = make_meta(names=("a",), roles=("train",))
    w = SessionWriter(tmp_path / "s", meta)
    with pytest.raises(MissingFileError, match="corners.csv"):
        w.finish()
    w.write_corners(make_corners())
    with pytest.raises(MissingFileError, match="kinematics.csv"):
        w.finish()
    w.write_kinematics("a", make_kinematics(0))
    with pytest.raises(SessionFormatError, match="frames.csv"):
        w.finish()
    w.abort()
    assert list(tmp_path.iterdir()) == []


def test_writer_validates_like_the_reader(tmp_path):
    with SessionWriter(tmp_path / "s", make_meta()) as w:
        with pytest.raises(UnitsError, match="looks like millimetres"):
            w.write_frame("seq00", 0, 0.0, make_cloud(0) * 1000)
        with pytest.raises(UnitsError, match="kinematics.csv"):
            k = make_kinematics(0)
            w.write_kinematics("seq00", Kinematics(k.t, k.position * 1000, k.quaternion))
        with pytest.raises(TimestampError, match="kinematics.csv"):
            k = make_kinematics(0)
            w.write_kinematics("seq00", Kinematics(k.t[::-1], k.position, k.quaternion))
        with pytest.raises(KeyError):
            w.write_frame("nope", 0, 0.0, make_cloud(0))
        w.abort()
    assert list(tmp_path.iterdir()) == []


def test_kinematics_rejects_zero_quaternion_and_bad_shapes():
    with pytest.raises(ValueError, match="quaternion"):
        Kinematics(np.arange(2.0), np.zeros((2, 3)), np.zeros((2, 4)))
    with pytest.raises(ValueError, match="position"):
        Kinematics(np.arange(2.0), np.zeros((3, 3)), np.tile([0, 0, 0, 1.0], (2, 1)))


def test_writer_rejects_metadata_the_reader_would_reject(tmp_path):
    meta = make_meta()
    bad = SessionMeta(PhantomSpec(SIZE * 1000, 0.1), meta.probe, meta.camera, meta.sequences)
    with pytest.raises(UnitsError, match="looks like millimetres"):
        SessionWriter(tmp_path / "s", bad)
    assert list(tmp_path.iterdir()) == []
