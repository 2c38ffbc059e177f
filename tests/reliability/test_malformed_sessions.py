"""Malformed sessions, drawn by hypothesis: each one is refused with an error that names
the file and the problem, by ``core.io`` and by the workbench (registration of the folder
and upload of it zipped: HTTP 422 with the same message), and nothing already stored is
touched (the database rows and every file of the sessions and jobs already there are
byte-identical before and after).

Every example starts from a copy of the tiny valid session (tests/reliability/conftest.py)
and breaks one thing that ``SESSION_FORMAT.md`` forbids: a truncated PLY, a NaN or an
infinity, millimetres or centimetres where metres are required, a missing sequence or
file, a duplicate timestamp or frame number, and format violations (wrong format tag,
role, sequence name or cloud path leaving the session, too few corner touches, a zero
quaternion, non-numeric or missing columns, a PLY without float z, a broken picks file).
Hypothesis draws which file, which row, which column, which value and where to cut.
"""

from __future__ import annotations

import hashlib
import io
import json
import re
import shutil
import sqlite3
import tempfile
import time
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import httpx
import numpy as np
import pytest
from hypothesis import HealthCheck, given, note, settings
from hypothesis import strategies as st

from core import errors as E
from core.io import read_picked, read_ply, read_session, write_ply

FINAL = ("done", "failed", "cancelled", "interrupted")
SEQ = "seq00"
N_FRAMES = 30  # frames of the tiny session's one sequence
FUZZ = settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=False)


# ---------------------------------------------------------------------------- what must happen
@dataclass
class Broken:
    """What a mutation must produce: ``read(root)`` (a core.io call) raises ``error`` on
    ``file`` (relative to the session) with a problem matching ``problem``."""

    file: str
    error: type[E.SessionFormatError]
    problem: str
    read: Callable[[Path], object]
    upload: str | None = None
    """What the upload's 422 says instead, when the zip cannot be told from a non-session."""


def full(root: Path):
    return read_session(root, check_clouds=True)


def meta_and_csv(root: Path):
    return read_session(root)


def cloud(i: int) -> Callable[[Path], object]:
    return lambda root: read_session(root).sequences[SEQ].cloud(i)


def reference(root: Path):
    return read_session(root).reference_cloud()


def stl(root: Path):
    return read_session(root).phantom_mesh()


# ---------------------------------------------------------------------------- editing helpers
def cloud_file(i: int) -> str:
    return f"sequences/{SEQ}/clouds/{i:06d}.ply"


def read_csv(path: Path) -> tuple[list[str], list[list[str]]]:
    lines = path.read_text().splitlines()
    return lines[0].split(","), [line.split(",") for line in lines[1:] if line]


def write_csv(path: Path, header: list[str], rows: list[list[str]]) -> None:
    path.write_text("\n".join([",".join(header)] + [",".join(r) for r in rows]) + "\n")


def edit_cell(path: Path, row: int, column: str, value: str) -> None:
    header, rows = read_csv(path)
    rows[row][header.index(column)] = value
    write_csv(path, header, rows)


def edit_meta(root: Path, change: Callable[[dict], None]) -> None:
    meta = json.loads((root / "session.json").read_text())
    change(meta)
    (root / "session.json").write_text(json.dumps(meta, indent=2))  # json writes NaN/Infinity as Python does


def scale_clouds(root: Path, files: list[str], factor: float) -> None:
    for rel in files:
        write_ply(root / rel, read_ply(root / rel) * factor)


def nan_cloud(root: Path, rel: str) -> None:
    n = len(read_ply(root / rel))
    write_ply_raw(root / rel, np.full((n, 3), np.nan, dtype="<f4"))


def write_ply_raw(path: Path, points: np.ndarray, kind: str = "float") -> None:
    """A binary PLY with (N, 3) ``points`` as they are (write_ply refuses NaN)."""
    dtype = {"float": "<f4", "int": "<i4"}[kind]
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(points)}\n"
              f"property {kind} x\nproperty {kind} y\nproperty {kind} z\nend_header\n").encode()
    path.write_bytes(header + np.ascontiguousarray(points, dtype=dtype).tobytes())


# ---------------------------------------------------------------------------- strategies
ROWS_KIN = st.integers(1, 290)  # data rows of kinematics.csv (301 in the tiny session)
ROWS_FRAMES = st.integers(1, N_FRAMES - 1)
FRAMES = st.integers(0, N_FRAMES - 1)
NONFINITE = st.sampled_from(["nan", "inf", "-inf", "NaN"])


@st.composite
def truncated_ply(draw):
    rel = draw(st.sampled_from(["calibration/reference.ply", cloud_file(draw(FRAMES))]))
    fraction = draw(st.floats(0.0, 1.0, exclude_max=True))

    def mutate(root: Path):
        data = (root / rel).read_bytes()
        (root / rel).write_bytes(data[: int(fraction * len(data))])

    return mutate, Broken(rel, E.PlyError, r"malformed|truncated", full)


@st.composite
def non_finite(draw):
    where = draw(st.sampled_from(["kinematics", "corners", "frames", "session.json", "cloud"]))
    value = draw(NONFINITE)
    if where == "kinematics":
        column, row = draw(st.sampled_from(["t", "x", "y", "z", "qx", "qy", "qz", "qw"])), draw(ROWS_KIN)
        rel = f"sequences/{SEQ}/kinematics.csv"
        error = E.TimestampError if column == "t" else E.ColumnError
        return (lambda root: edit_cell(root / rel, row - 1, column, value),
                Broken(rel, error, rf"column '{column}' is not finite at row {row} ", meta_and_csv))
    if where == "corners":
        column, row = draw(st.sampled_from(["x", "y", "z"])), draw(st.integers(1, 12))
        rel = "calibration/corners.csv"
        return (lambda root: edit_cell(root / rel, row - 1, column, value),
                Broken(rel, E.ColumnError, rf"column '{column}' is not finite at row {row} ", meta_and_csv))
    if where == "frames":
        row = draw(st.integers(1, N_FRAMES))
        rel = f"sequences/{SEQ}/frames.csv"
        return (lambda root: edit_cell(root / rel, row - 1, "t", value),
                Broken(rel, E.TimestampError, rf"column 't' is not finite at row {row} ", meta_and_csv))
    if where == "session.json":
        key = draw(st.sampled_from(["phantom.size", "phantom.mass", "probe.radius", "camera.rate_hz"]))
        number, axis = float(value), draw(st.integers(0, 2))

        def mutate(root: Path):
            def change(meta):
                a, b = key.split(".")
                if key == "phantom.size":
                    meta[a][b][axis] = number
                else:
                    meta[a][b] = number
            edit_meta(root, change)

        problem = r"'phantom\.size' must be 3 finite numbers" if key == "phantom.size" else rf"'{re.escape(key)}' must be a finite number"
        return mutate, Broken("session.json", E.SessionFormatError, problem, meta_and_csv)
    # a cloud whose every point is NaN (the depth camera gave nothing): the reference or a sequence's first
    rel = draw(st.sampled_from(["calibration/reference.ply", cloud_file(0)]))
    return (lambda root: nan_cloud(root, rel),
            Broken(rel, E.PlyError, r"no finite point among \d+ vertices", reference if "reference" in rel else cloud(0)))


@st.composite
def wrong_units(draw):
    factor = draw(st.sampled_from([1000.0, 100.0]))  # millimetres, centimetres
    what = draw(st.sampled_from(["phantom.size", "probe.radius", "kinematics", "corners", "all clouds",
                                 "sequence clouds", "last cloud", "phantom.stl"]))
    return units_case(what, factor)


def units_case(what: str, factor: float):
    """(mutate, expected) for ``what`` written in units ``factor`` times too small."""
    mm = r"looks? like millimetres"
    if what == "phantom.size":
        return (lambda root: edit_meta(root, lambda m: m["phantom"].update(size=[v * factor for v in m["phantom"]["size"]])),
                Broken("session.json", E.UnitsError, rf"'phantom\.size' = .* {mm}", meta_and_csv))
    if what == "probe.radius":  # 5 mm written as 5 (in centimetres, 0.5, it would pass for a 0.5 m sphere)
        return (lambda root: edit_meta(root, lambda m: m["probe"].update(radius=m["probe"]["radius"] * 1000.0)),
                Broken("session.json", E.UnitsError, rf"'probe\.radius' = .* {mm}", meta_and_csv))
    if what in ("kinematics", "corners"):
        rel = f"sequences/{SEQ}/kinematics.csv" if what == "kinematics" else "calibration/corners.csv"

        def mutate(root: Path):
            header, rows = read_csv(root / rel)
            for r in rows:
                for c in ("x", "y", "z"):
                    r[header.index(c)] = repr(float(r[header.index(c)]) * factor)
            write_csv(root / rel, header, rows)

        what_pos = "probe position" if what == "kinematics" else "corner position"
        return mutate, Broken(rel, E.UnitsError, rf"{what_pos} at row \d+ .* {mm}", meta_and_csv)
    if what == "last cloud":  # the camera driver switched units mid-recording
        last = N_FRAMES - 1
        return (lambda root: scale_clouds(root, [cloud_file(last)], factor),
                Broken(cloud_file(last), E.UnitsError, rf"median point distance .* {mm}", cloud(last)))
    if what in ("all clouds", "sequence clouds"):
        files = [cloud_file(i) for i in range(N_FRAMES)] + (["calibration/reference.ply"] if what == "all clouds" else [])
        first = "calibration/reference.ply" if what == "all clouds" else cloud_file(0)
        return (lambda root: scale_clouds(root, files, factor),
                Broken(first, E.UnitsError, rf"median point distance .* {mm}", reference if what == "all clouds" else cloud(0)))

    def mutate(root: Path):  # a phantom.stl drawn in millimetres
        import trimesh

        size = json.loads((root / "session.json").read_text())["phantom"]["size"]
        box = trimesh.creation.box(extents=np.asarray(size) * factor)
        box.apply_translation(np.asarray(size) * factor / 2)
        box.export(root / "phantom.stl")

    return mutate, Broken("phantom.stl", E.UnitsError, rf"extents .* {mm}", stl)


@st.composite
def missing(draw):
    what = draw(st.sampled_from(["session.json", "corners.csv", "sequence folder", "kinematics.csv", "frames.csv",
                                 "cloud", "listed sequence", "sequences key"]))
    seq_dir = f"sequences/{SEQ}"
    if what == "session.json":
        return (lambda root: (root / "session.json").unlink(),
                Broken("session.json", E.MissingFileError, "session.json does not exist", meta_and_csv,
                       upload="the zip has no session.json at its top or in one top-level folder"))
    if what == "corners.csv":
        return (lambda root: (root / "calibration/corners.csv").unlink(),
                Broken("calibration/corners.csv", E.MissingFileError, "corners.csv does not exist", meta_and_csv))
    if what == "sequence folder":
        return (lambda root: shutil.rmtree(root / seq_dir),
                Broken(seq_dir, E.MissingFileError, rf"folder of sequence '{SEQ}' .* does not exist", meta_and_csv))
    if what in ("kinematics.csv", "frames.csv"):
        return (lambda root: (root / seq_dir / what).unlink(),
                Broken(f"{seq_dir}/{what}", E.MissingFileError, f"{what} does not exist", meta_and_csv))
    if what == "cloud":
        i = draw(FRAMES)
        return (lambda root: (root / cloud_file(i)).unlink(),
                Broken(cloud_file(i), E.MissingFileError, r"cloud listed in .*frames\.csv at row \d+ .* does not exist",
                       meta_and_csv))
    if what == "listed sequence":
        name = draw(st.from_regex(r"[a-z][a-z0-9_]{0,8}", fullmatch=True).filter(lambda n: n != SEQ))
        role = draw(st.sampled_from(["train", "validation", "test"]))
        return (lambda root: edit_meta(root, lambda m: m["sequences"].append({"name": name, "role": role})),
                Broken(f"sequences/{name}", E.MissingFileError, rf"folder of sequence '{name}' .* does not exist",
                       meta_and_csv))
    return (lambda root: edit_meta(root, lambda m: m.pop("sequences")),
            Broken("session.json", E.SessionFormatError, "missing required key 'sequences'", meta_and_csv))


@st.composite
def duplicates(draw):
    what = draw(st.sampled_from(["kinematics t", "frames t", "frame number", "kinematics t backwards"]))
    if what.startswith("kinematics"):
        rel, row = f"sequences/{SEQ}/kinematics.csv", draw(ROWS_KIN)
        backwards = what.endswith("backwards")

        def mutate(root: Path):
            header, rows = read_csv(root / rel)
            t = header.index("t")
            rows[row][t] = repr(float(rows[row - 1][t]) - (1e-3 if backwards else 0.0))
            write_csv(root / rel, header, rows)

        problem = rf"column 't' is not strictly increasing at row {row + 1} " + ("" if backwards else r".*a duplicate")
        return mutate, Broken(rel, E.TimestampError, problem, meta_and_csv)
    rel, row = f"sequences/{SEQ}/frames.csv", draw(ROWS_FRAMES)
    column = "t" if what == "frames t" else "frame"

    def mutate(root: Path):
        header, rows = read_csv(root / rel)
        c = header.index(column)
        rows[row][c] = rows[row - 1][c]
        write_csv(root / rel, header, rows)

    if column == "t":
        return mutate, Broken(rel, E.TimestampError, rf"not strictly increasing at row {row + 1} .*a duplicate", meta_and_csv)
    return mutate, Broken(rel, E.ColumnError, rf"column 'frame' repeats frame number {row - 1} at rows \[{row}, {row + 1}\]$",
                          meta_and_csv)


@st.composite
def format_violations(draw):
    what = draw(st.sampled_from(["format", "role", "duplicate name", "name escapes", "cloud path escapes",
                                 "few corners", "corner label", "zero quaternion", "not numeric", "missing column",
                                 "partial force", "not json", "ply without z", "ply int", "picked"]))
    kin, frames, corners = f"sequences/{SEQ}/kinematics.csv", f"sequences/{SEQ}/frames.csv", "calibration/corners.csv"
    if what == "format":
        tag = draw(st.text(max_size=20).filter(lambda t: t != "tissue-session/1"))
        return (lambda root: edit_meta(root, lambda m: m.update(format=tag)),
                Broken("session.json", E.SessionFormatError, r"'format' must be 'tissue-session/1'", meta_and_csv))
    if what == "role":
        role = draw(st.text(max_size=12).filter(lambda r: r not in ("train", "validation", "test")))
        return (lambda root: edit_meta(root, lambda m: m["sequences"][0].update(role=role)),
                Broken("session.json", E.SessionFormatError, r"'sequences\[0\]\.role' .* must be one of", meta_and_csv))
    if what == "duplicate name":
        return (lambda root: edit_meta(root, lambda m: m["sequences"].append(dict(m["sequences"][0]))),
                Broken("session.json", E.SessionFormatError, f"duplicate sequence name '{SEQ}'", meta_and_csv))
    if what == "name escapes":
        name = draw(st.sampled_from(["..", "../seq00", "a/b", "..\\x", " seq00"]))
        return (lambda root: edit_meta(root, lambda m: m["sequences"][0].update(name=name)),
                Broken("session.json", E.SessionFormatError, r"'sequences\[0\]\.name' = .* is not a valid folder name",
                       meta_and_csv))
    if what == "cloud path escapes":
        row, target = draw(st.integers(1, N_FRAMES)), draw(st.sampled_from(
            ["../../../../etc/passwd", "/etc/passwd", "clouds/../../seq00/clouds/000000.ply", "C:\\clouds\\0.ply", "..\\x.ply"]))
        return (lambda root: edit_cell(root / frames, row - 1, "file", target),
                Broken(frames, E.SessionFormatError, rf"column 'file' at row {row} .* must be a path inside the sequence folder",
                       meta_and_csv))
    if what == "few corners":
        keep = draw(st.integers(0, 3))

        def mutate(root: Path):
            header, rows = read_csv(root / corners)
            write_csv(root / corners, header, rows[:keep])

        return mutate, Broken(corners, E.SessionFormatError, f"needs at least 4 corner touches, got {keep}", meta_and_csv)
    if what == "corner label":
        row, label = draw(st.integers(1, 12)), draw(st.sampled_from(["x2y0", "X0Y0", "top", ""]))
        return (lambda root: edit_cell(root / corners, row - 1, "corner", label),
                Broken(corners, E.ColumnError, rf"column 'corner' at row {row} .* must be one of", meta_and_csv))
    if what == "zero quaternion":
        row = draw(ROWS_KIN)

        def mutate(root: Path):
            for c in ("qx", "qy", "qz", "qw"):
                edit_cell(root / kin, row - 1, c, "0")

        return mutate, Broken(kin, E.ColumnError, rf"zero quaternion at row {row} ", meta_and_csv)
    if what == "not numeric":
        row, column = draw(ROWS_KIN), draw(st.sampled_from(["t", "x", "qw"]))
        cell = draw(st.sampled_from(["abc", "1,5", "--1", "0x1g"]))
        return (lambda root: edit_cell(root / kin, row - 1, column, cell.replace(",", ";")),
                Broken(kin, E.ColumnError, rf"column '{column}' is not numeric at row {row} ", meta_and_csv))
    if what == "missing column":
        column = draw(st.sampled_from(["t", "x", "y", "z", "qx", "qy", "qz", "qw"]))

        def mutate(root: Path):
            header, rows = read_csv(root / kin)
            c = header.index(column)
            write_csv(root / kin, header[:c] + header[c + 1:], [r[:c] + r[c + 1:] for r in rows])

        return mutate, Broken(kin, E.ColumnError, rf"missing column\(s\) \['{column}'\]", meta_and_csv)
    if what == "partial force":
        columns = draw(st.sampled_from([["fx"], ["fx", "fy"], ["fz"], ["fy", "fz"]]))

        def mutate(root: Path):
            header, rows = read_csv(root / kin)
            write_csv(root / kin, header + columns, [r + ["0.1"] * len(columns) for r in rows])

        return mutate, Broken(kin, E.ColumnError, r"partial force columns", meta_and_csv)
    if what == "not json":
        junk = draw(st.sampled_from([b"{", b"", b"\xff\xfe{}", b'{"format": "tissue-session/1",}', b"[1, 2]"]))
        problem = r"not valid JSON|not UTF-8|top level must be a JSON object"
        return (lambda root: (root / "session.json").write_bytes(junk),
                Broken("session.json", E.SessionFormatError, problem, meta_and_csv))
    if what in ("ply without z", "ply int"):
        i = draw(FRAMES)

        def mutate(root: Path):
            pts = read_ply(root / cloud_file(i))
            if what == "ply int":
                write_ply_raw(root / cloud_file(i), np.round(pts * 1000), kind="int")
            else:
                header = f"ply\nformat ascii 1.0\nelement vertex {len(pts)}\nproperty float x\nproperty float y\nend_header\n"
                (root / cloud_file(i)).write_text(header + "\n".join(f"{x} {y}" for x, y, _ in pts) + "\n")

        problem = r"vertex property 'x' must be float or double" if what == "ply int" else r"lacks float x, y, z \(missing \['z'\]"
        return mutate, Broken(cloud_file(i), E.PlyError, problem, full)
    # calibration/picked.json: the picks the workbench accepted, broken by hand
    bad = draw(st.sampled_from([
        {"format": "tissuetwin-picked/1", "points_camera": [[0, 0, 0]], "points_phantom": [[0, 0, 0]]},
        {"format": "other", "points_camera": [], "points_phantom": []},
        {"format": "tissuetwin-picked/1", "points_camera": [[0, 0, 0]] * 3, "points_phantom": [[0, 0, float("nan")]] * 3},
    ]))
    return (lambda root: (root / "calibration/picked.json").write_text(json.dumps(bad)),
            Broken("calibration/picked.json", E.SessionFormatError, r"K >= 3|tissuetwin-picked/1|must be finite", read_picked))


# ---------------------------------------------------------------------------- the workbench
def _zip(root: Path) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for p in sorted(root.rglob("*")):
            if p.is_file():
                zf.write(p, f"{root.name}/{p.relative_to(root).as_posix()}")
    return buf.getvalue()


def _snapshot(data: Path, registered: Path) -> tuple:
    """The stored state: every row of every table, and the bytes of every file of the data
    directory (uploads, job artifacts) and of the registered session folder."""
    db = sqlite3.connect(f"file:{data / 'workbench.db'}?mode=ro", uri=True)
    try:
        rows = {t: db.execute(f"select * from {t} order by id").fetchall() for t in ("sessions", "jobs")}
    finally:
        db.close()
    files = {}
    for base in (data, registered):
        for p in sorted(base.rglob("*")):
            if p.is_file() and not p.name.startswith("workbench.db"):
                files[str(p)] = hashlib.sha256(p.read_bytes()).hexdigest()
    return rows, files


@pytest.fixture(scope="module")
def bench(live):
    """The shared workbench, holding at least: the registered tiny session, an uploaded
    copy of it and a finished replay job with its artifacts; and its state then."""
    with httpx.Client(base_url=live.url, timeout=60) as client:
        yield _stored(client, live)


def _stored(client: httpx.Client, live) -> tuple:
    client.post("/api/sessions/upload", files={"file": ("up.zip", _zip(live.session), "application/zip")}).raise_for_status()
    job = client.post("/api/jobs", json={"type": "replay", "params": {"session_id": live.session_id, "grid": [4, 3, 3]}}).raise_for_status().json()
    deadline = time.monotonic() + 120
    while (job := client.get(f"/api/jobs/{job['id']}").json())["status"] not in FINAL:
        assert time.monotonic() < deadline, job
        time.sleep(0.2)
    assert job["status"] == "done", job["error"]
    before = _snapshot(live.data, live.session)
    assert len(before[0]["sessions"]) >= 2 and len(before[0]["jobs"]) >= 1 and len(before[1]) > 40
    return client, live.data, live.session, before, live.roots[0]


def check(bench, tiny_session, mutate, expected: Broken) -> None:
    client, data, registered, before, scratch = bench
    note(f"expected: {expected.error.__name__} on {expected.file}: /{expected.problem}/")
    with tempfile.TemporaryDirectory(dir=scratch) as tmp:  # inside the server's session root
        root = Path(shutil.copytree(tiny_session, Path(tmp).resolve() / "broken"))
        mutate(root)

        # core.io: the documented error, on the file, saying the problem
        with pytest.raises(expected.error) as info:
            expected.read(root)
        err = info.value
        assert err.path == root / expected.file, (str(err), expected)
        assert re.search(expected.problem, err.problem), (err.problem, expected.problem)

        # the workbench: registering the folder gives the same message, as a 422
        r = client.post("/api/sessions", json={"path": str(root)})
        assert r.status_code == 422, r.text
        assert r.json()["detail"] == str(err) and r.json()["type"] == type(err).__name__

        # uploading it zipped: the same file (inside the unpacked copy) and the same problem
        r = client.post("/api/sessions/upload", files={"file": ("broken.zip", _zip(root), "application/zip")})
        assert r.status_code == 422, r.text
        detail = r.json()["detail"]
        if expected.upload:
            assert detail == expected.upload
        else:
            assert f"/broken/{expected.file}: " in detail and re.search(expected.problem, detail), detail

    assert _snapshot(data, registered) == before  # nothing stored was touched, nothing left behind


@FUZZ
@given(case=truncated_ply())
def test_truncated_ply(bench, tiny_session, case):
    check(bench, tiny_session, *case)


@FUZZ
@given(case=non_finite())
def test_nan_and_infinity(bench, tiny_session, case):
    check(bench, tiny_session, *case)


@FUZZ
@given(case=wrong_units())
def test_wrong_units(bench, tiny_session, case):
    check(bench, tiny_session, *case)


@settings(FUZZ, max_examples=1)
@given(case=st.just(units_case("last cloud", 1000.0)))
def test_a_units_switch_in_the_last_cloud_is_caught(bench, tiny_session, case):
    check(bench, tiny_session, *case)  # always drawn here, whatever the fuzzing above draws


@FUZZ
@given(case=missing())
def test_missing_sequences_and_files(bench, tiny_session, case):
    check(bench, tiny_session, *case)


@FUZZ
@given(case=duplicates())
def test_duplicate_timestamps_and_frames(bench, tiny_session, case):
    check(bench, tiny_session, *case)


@settings(FUZZ, max_examples=20)
@given(case=format_violations())
def test_format_violations(bench, tiny_session, case):
    check(bench, tiny_session, *case)


def test_a_session_without_sequences_is_refused_by_the_workbench(bench, tiny_session, tmp_path):
    """The format allows any number of sequences and core.io reads such a session; the
    workbench refuses to register one (there is nothing to replay), naming session.json."""
    client, data, registered, before, _ = bench
    root = Path(shutil.copytree(tiny_session, tmp_path / "empty")).resolve()  # under the server's session root
    edit_meta(root, lambda m: m.update(sequences=[]))
    shutil.rmtree(root / "sequences")
    assert read_session(root).sequences == {}
    r = client.post("/api/sessions", json={"path": str(root)})
    assert r.status_code == 422 and r.json()["detail"] == f"{root / 'session.json'}: lists no sequences; a session needs at least one"
    assert _snapshot(data, registered) == before
