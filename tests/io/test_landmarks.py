"""Landmarks in sessions: ``landmarks`` of ``session.json`` and ``calibration/landmarks.csv``
(SESSION_FORMAT.md): write -> read round trips, old sessions unchanged, and one
SessionFormatError naming the file (and the key) per bad input."""

from __future__ import annotations

import json
import pickle
from pathlib import Path

import numpy as np
import pytest

from core.errors import ColumnError, MissingFileError, SessionFormatError, UnitsError
from core.io import (
    CameraSpec,
    Corners,
    Kinematics,
    LandmarkTouches,
    PhantomSpec,
    ProbeSpec,
    SequenceSpec,
    SessionMeta,
    SessionWriter,
    read_session,
    write_session,
)

SIZE = np.array([0.0687, 0.0393, 0.0358])
# Four top corners and the centre of the x = size[0] side face, phantom frame, m.
LANDMARKS = {
    "x0y0": [0.0, 0.0, 0.0358],
    "x1y0": [0.0687, 0.0, 0.0358],
    "x0y1": [0.0, 0.0393, 0.0358],
    "x1y1": [0.0687, 0.0393, 0.0358],
    "side": [0.0687, 0.01965, 0.0179],
}
LANDMARKS_CSV = Path("calibration/landmarks.csv")


def make_meta(landmarks=LANDMARKS, raw_extra=None) -> SessionMeta:
    raw = {"format": "tissue-session/1", "lab": {"operator": "ana"},
           "phantom": {"material_note": "Ecoflex 00-30"}}
    raw.update(raw_extra or {})
    return SessionMeta(
        phantom=PhantomSpec(size=SIZE, mass=0.1),
        probe=ProbeSpec(radius=0.005),
        camera=CameraSpec(rate_hz=30.0, depth_accuracy=0.002),
        sequences=(SequenceSpec("seq00", "train"),),
        raw=raw,
        landmarks=landmarks,
    )


def make_touches() -> LandmarkTouches:
    rng = np.random.default_rng(3)
    labels = ("x0y0", "x1y0", "x0y1", "x1y1", "side", "x0y0")  # one repeated touch
    pos = np.array([0.4, -0.02, -0.1]) + rng.normal(0, 0.03, size=(len(labels), 3))
    return LandmarkTouches(labels=labels, positions=pos)


def make_corners() -> Corners:
    pos = np.array([[0.40, -0.02, -0.11], [0.47, -0.02, -0.11], [0.40, 0.02, -0.11],
                    [0.47, 0.02, -0.11]])
    return Corners(labels=("x0y0", "x1y0", "x0y1", "x1y1"), positions=pos)


def write(path: Path, *, meta=None, touches=True, corners=False) -> Path:
    """A one-sequence, one-frame session with landmark touches and/or corners."""
    rng = np.random.default_rng(0)
    with SessionWriter(path, meta or make_meta()) as w:
        if touches:
            w.write_landmark_touches(make_touches())
        if corners:
            w.write_corners(make_corners())
        k = 5
        w.write_kinematics("seq00", Kinematics(t=np.arange(k) / 30.0,
                                               position=np.full((k, 3), 0.4),
                                               quaternion=np.tile([0, 0, 0, 1.0], (k, 1))))
        w.write_frame("seq00", 0, 0.01, np.array([0.0, 0.0, 0.35]) + rng.normal(0, 0.03, (50, 3)))
    return path


# --------------------------------------------------------------------------------------
# Round trips
# --------------------------------------------------------------------------------------


def test_landmark_session_without_corners_round_trips(tmp_path):
    root = write(tmp_path / "s")
    assert not (root / "calibration" / "corners.csv").exists()
    s = read_session(root, check_clouds=True)
    assert s.corners is None
    assert list(s.meta.landmarks) == list(LANDMARKS)  # session.json order
    for name, xyz in LANDMARKS.items():
        np.testing.assert_array_equal(s.meta.landmarks[name], xyz)
        assert s.meta.landmarks[name].dtype == np.float64
    assert s.meta.landmarks == make_meta().landmarks
    assert s.landmark_touches == make_touches()  # float64 written round-trip exact
    assert s.landmark_touches.positions.dtype == np.float64
    on_disk = json.loads((root / "session.json").read_text())
    assert on_disk["landmarks"] == LANDMARKS
    assert on_disk["lab"] == {"operator": "ana"}  # unknown keys still preserved
    assert on_disk["phantom"]["material_note"] == "Ecoflex 00-30"
    assert (root / LANDMARKS_CSV).read_text().splitlines()[0] == "landmark,x,y,z"

    copy = read_session(write_session(s, tmp_path / "copy"))
    assert copy.corners is None
    assert copy.meta == s.meta and copy.landmark_touches == s.landmark_touches
    assert (tmp_path / "copy" / LANDMARKS_CSV).read_bytes() == (root / LANDMARKS_CSV).read_bytes()


def test_write_session_can_add_landmark_touches(tmp_path):
    """Corner session whose session.json names landmarks: write_session(landmark_touches=)
    adds calibration/landmarks.csv and keeps the corners."""
    a = read_session(write(tmp_path / "a", touches=False, corners=True))
    assert a.landmark_touches is None and a.corners == make_corners()
    b = read_session(write_session(a, tmp_path / "b", landmark_touches=make_touches()))
    assert b.landmark_touches == make_touches() and b.corners == a.corners


def test_session_with_corners_and_landmarks_reads_both(tmp_path):
    s = read_session(write(tmp_path / "s", corners=True))
    assert s.corners == make_corners() and s.landmark_touches == make_touches()


def test_old_session_reads_unchanged(tmp_path):
    root = write(tmp_path / "s", meta=make_meta(landmarks=None), touches=False, corners=True)
    s = read_session(root)
    assert s.landmark_touches is None and s.corners == make_corners()
    assert len(s.meta.landmarks) == 0 and dict(s.meta.landmarks) == {}
    on_disk = json.loads((root / "session.json").read_text())
    assert "landmarks" not in on_disk and on_disk == s.meta.to_json()
    assert not (root / LANDMARKS_CSV).exists()
    # and without corners.csv it is refused as before
    (root / "calibration" / "corners.csv").unlink()
    with pytest.raises(MissingFileError, match="corners.csv"):
        read_session(root)


def test_landmarks_are_immutable_and_picklable():
    meta = make_meta()
    with pytest.raises(TypeError):
        meta.landmarks["apex"] = np.zeros(3)
    with pytest.raises(ValueError):
        meta.landmarks["side"][0] = 1.0  # read-only array
    again = pickle.loads(pickle.dumps(meta))
    assert again == meta and again.landmarks == meta.landmarks
    assert make_meta(landmarks={**LANDMARKS, "side": [0.0687, 0.02, 0.0179]}) != meta


def test_to_json_writes_landmarks_only_when_present():
    meta = make_meta(raw_extra={"landmarks": {"stale": [0.0, 0.0, 0.0]}}, landmarks={})
    assert "landmarks" not in meta.to_json()
    meta = make_meta(raw_extra={"landmarks": {"stale": [0.0, 0.0, 0.0]}})
    assert meta.to_json()["landmarks"] == LANDMARKS


# --------------------------------------------------------------------------------------
# Bad inputs
# --------------------------------------------------------------------------------------


def _set_landmarks(fn):
    def mutate(root: Path) -> None:
        p = root / "session.json"
        obj = json.loads(p.read_text())
        fn(obj)
        p.write_text(json.dumps(obj))  # allow_nan: NaN is written as the bare token NaN
    return mutate


def _csv_rows(fn):
    def mutate(root: Path) -> None:
        p = root / LANDMARKS_CSV
        lines = p.read_text().splitlines()
        p.write_text("\n".join(lines[:1] + fn([line.split(",") for line in lines[1:]])) + "\n")
    return mutate


def _rows(rows):
    return [",".join(r) for r in rows]


def _collinear(root: Path) -> None:
    """Touch only x0y0, x1y0 and 'side', moved onto the edge between those two corners."""
    _set_landmarks(lambda o: o["landmarks"].update(side=[0.03, 0.0, 0.0358]))(root)
    _csv_rows(lambda rows: _rows([r for r in rows if r[0] in ("x0y0", "x1y0", "side")]))(root)


# (id, mutation of a good landmark session, expected class, file, text in the message)
BAD = [
    ("csv_unknown_label",
     _csv_rows(lambda rows: _rows([["apex"] + rows[0][1:]] + rows[1:])),
     SessionFormatError, "landmarks.csv", "'apex' is not a landmark of session.json"),
    ("csv_two_landmarks_only",
     _csv_rows(lambda rows: _rows([r for r in rows if r[0] in ("x0y0", "x1y0")])),
     SessionFormatError, "landmarks.csv", "at least 3 distinct landmarks"),
    ("collinear_landmarks", _collinear, SessionFormatError, "landmarks.csv", "collinear"),
    ("csv_mm", _csv_rows(lambda rows: _rows([[r[0]] + [repr(float(v) * 1000) for v in r[1:]]
                                             for r in rows])),
     UnitsError, "landmarks.csv", "looks like millimetres"),
    ("csv_nan", _csv_rows(lambda rows: _rows([rows[0][:2] + ["nan", rows[0][3]]] + rows[1:])),
     ColumnError, "landmarks.csv", "column 'y' is not finite"),
    ("csv_inf", _csv_rows(lambda rows: _rows([rows[0][:3] + ["inf"]] + rows[1:])),
     ColumnError, "landmarks.csv", "column 'z' is not finite"),
    ("csv_no_rows", _csv_rows(lambda rows: []), SessionFormatError, "landmarks.csv",
     "no data rows"),
    ("csv_empty_label", _csv_rows(lambda rows: _rows([[""] + rows[0][1:]] + rows[1:])),
     ColumnError, "landmarks.csv", "column 'landmark' is empty"),
    ("json_no_landmarks", _set_landmarks(lambda o: o.pop("landmarks")),
     SessionFormatError, "landmarks.csv", "names none"),
    ("json_mm", _set_landmarks(lambda o: o["landmarks"].update(side=[68.7, 19.65, 17.9])),
     UnitsError, "session.json", "'landmarks.side' = [68.7, 19.65, 17.9] looks like millimetres"),
    ("json_nan", _set_landmarks(lambda o: o["landmarks"].update(side=[0.0687, float("nan"), 0.01])),
     SessionFormatError, "session.json", "'landmarks.side' must be 3 finite numbers"),
    ("json_two_numbers", _set_landmarks(lambda o: o["landmarks"].update(side=[0.0687, 0.01])),
     SessionFormatError, "session.json", "'landmarks.side' must be 3 finite numbers"),
    ("json_string_coordinate",
     _set_landmarks(lambda o: o["landmarks"].update(side=["0.0687", 0.01, 0.01])),
     SessionFormatError, "session.json", "'landmarks.side' must be 3 finite numbers"),
    ("json_not_an_object", _set_landmarks(lambda o: o.update(landmarks=[[0.0, 0.0, 0.0]])),
     SessionFormatError, "session.json", "'landmarks' must be an object"),
    ("json_empty_name", _set_landmarks(lambda o: o["landmarks"].update({"": [0.0, 0.0, 0.0]})),
     SessionFormatError, "session.json", "landmark name '' in 'landmarks'"),
    ("json_name_with_comma",
     _set_landmarks(lambda o: o["landmarks"].update({"a,b": [0.0, 0.0, 0.0]})),
     SessionFormatError, "session.json", "landmark name 'a,b'"),
]


@pytest.mark.parametrize("mutate,error,file,text", [c[1:] for c in BAD], ids=[c[0] for c in BAD])
def test_bad_landmarks_raise_session_format_error(tmp_path, mutate, error, file, text):
    root = write(tmp_path / "s")
    read_session(root)  # good before the mutation
    mutate(root)
    with pytest.raises(SessionFormatError) as info:
        read_session(root)
    assert type(info.value) is error, f"{type(info.value).__name__}: {info.value}"
    assert info.value.path.name == file
    assert text in str(info.value), str(info.value)


def test_corners_are_still_required_without_landmarks_csv(tmp_path):
    root = write(tmp_path / "s")
    (root / LANDMARKS_CSV).unlink()
    with pytest.raises(MissingFileError, match="corners.csv"):
        read_session(root)


def test_writer_refuses_bad_landmarks(tmp_path):
    with pytest.raises(UnitsError, match="'landmarks.side'") as info:
        SessionWriter(tmp_path / "s", make_meta(landmarks={**LANDMARKS, "side": [68.7, 19.6, 17.9]}))
    assert info.value.path.name == "session.json"
    with SessionWriter(tmp_path / "s", make_meta()) as w:
        t = make_touches()
        with pytest.raises(SessionFormatError, match="'apex' is not a landmark") as info:
            w.write_landmark_touches(LandmarkTouches(("apex",) + t.labels[1:], t.positions))
        assert info.value.path.name == "landmarks.csv"
        with pytest.raises(SessionFormatError, match="at least 3 distinct"):
            w.write_landmark_touches(LandmarkTouches(t.labels[:2], t.positions[:2]))
        with pytest.raises(UnitsError, match="landmarks.csv"):
            w.write_landmark_touches(LandmarkTouches(t.labels, t.positions * 1000))
        with pytest.raises(MissingFileError, match="corners.csv"):
            w.finish()  # neither corners nor landmark touches written
        w.abort()
    assert list(tmp_path.iterdir()) == []
