"""Tests of core.io.ply: round trips against plyfile-written files and every bad input."""

from __future__ import annotations

import numpy as np
import plyfile
import pytest

from core.errors import MissingFileError, PlyError
from core.io import check_ply, read_ply, write_ply

RNG_SEED = 0


def _points(n: int = 200) -> np.ndarray:
    rng = np.random.default_rng(RNG_SEED)
    return rng.normal([0.0, 0.0, 0.4], 0.05, size=(n, 3))


@pytest.mark.parametrize("binary", [True, False], ids=["binary", "ascii"])
def test_write_read_round_trip(tmp_path, binary):
    pts = _points()
    path = tmp_path / "c.ply"
    write_ply(path, pts, binary=binary)
    back = read_ply(path)
    assert back.dtype == np.float64 and back.shape == pts.shape
    # Stored as float32: exact against the float32 cast (%.9g round-trips float32).
    np.testing.assert_array_equal(back, pts.astype(np.float32).astype(np.float64))
    assert check_ply(path) == len(pts)


@pytest.mark.parametrize("text,byte_order", [(False, "<"), (False, ">"), (True, "=")],
                         ids=["binary_le", "binary_be", "ascii"])
def test_reads_foreign_file_with_extra_properties(tmp_path, text, byte_order):
    """A plyfile-written cloud with double x,y,z, colour, normals and a face element."""
    pts = _points(50)
    vert = np.empty(50, dtype=[("red", "u1"), ("x", "f8"), ("y", "f8"), ("z", "f8"),
                               ("nx", "f4"), ("ny", "f4"), ("nz", "f4")])
    vert["x"], vert["y"], vert["z"] = pts.T
    vert["red"] = 7
    face = np.empty(1, dtype=[("vertex_indices", "i4", (3,))])
    face["vertex_indices"] = [[0, 1, 2]]
    data = plyfile.PlyData(
        [plyfile.PlyElement.describe(vert, "vertex"), plyfile.PlyElement.describe(face, "face")],
        text=text, byte_order=byte_order,
    )
    path = tmp_path / "foreign.ply"
    data.write(str(path))
    np.testing.assert_array_equal(read_ply(path), pts)  # double: exact


def test_non_finite_points_are_dropped(tmp_path):
    pts = _points(10)
    pts[3] = np.nan
    path = tmp_path / "nan.ply"
    vert = np.array([tuple(p) for p in pts], dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    plyfile.PlyData([plyfile.PlyElement.describe(vert, "vertex")]).write(str(path))
    back = read_ply(path)
    assert back.shape == (9, 3)
    assert np.isfinite(back).all()


HEADER = "ply\nformat {fmt} 1.0\nelement vertex {n}\n{props}end_header\n"
FLOAT_XYZ = "property float x\nproperty float y\nproperty float z\n"


def _bad_files():
    """(id, bytes) of PLY files the reader must reject with PlyError."""
    good_bin = HEADER.format(fmt="binary_little_endian", n=10, props=FLOAT_XYZ).encode()
    good_bin += np.zeros((10, 3), "<f4").tobytes()
    return [
        ("empty_file", b""),
        ("not_ply", b"hello world\n"),
        ("bad_format", HEADER.format(fmt="binary_middle_endian", n=1, props=FLOAT_XYZ).encode()),
        ("bad_property_type", HEADER.format(fmt="ascii", n=1, props="property quux x\n").encode()),
        ("header_only_truncated", b"ply\nformat ascii 1.0\nelement vertex 3\n"),
        ("truncated_binary", good_bin[:-7]),
        ("truncated_ascii",
         HEADER.format(fmt="ascii", n=3, props=FLOAT_XYZ).encode() + b"0 0 1\n0 0 1\n"),
        ("malformed_ascii",
         HEADER.format(fmt="ascii", n=2, props=FLOAT_XYZ).encode() + b"0 0 1\n0 zero 1\n"),
        ("zero_vertices", HEADER.format(fmt="binary_little_endian", n=0, props=FLOAT_XYZ).encode()),
        ("int_xyz",
         HEADER.format(fmt="ascii", n=1, props="property int x\nproperty int y\nproperty int z\n"
                       ).encode() + b"1 2 3\n"),
        ("no_z",
         HEADER.format(fmt="ascii", n=1, props="property float x\nproperty float y\n").encode()
         + b"1 2\n"),
        ("no_vertex_element",
         b"ply\nformat ascii 1.0\nelement point 1\n" + FLOAT_XYZ.encode() + b"end_header\n1 2 3\n"),
        ("all_nan",
         HEADER.format(fmt="ascii", n=2, props=FLOAT_XYZ).encode() + b"nan 0 0\n0 nan 0\n"),
    ]


@pytest.mark.parametrize("content", [c for _, c in _bad_files()], ids=[i for i, _ in _bad_files()])
def test_bad_ply_raises_ply_error(tmp_path, content):
    path = tmp_path / "bad_cloud.ply"
    path.write_bytes(content)
    with pytest.raises(PlyError) as info:
        read_ply(path)
    assert type(info.value) is PlyError
    assert "bad_cloud.ply" in str(info.value)


@pytest.mark.parametrize("name", ["truncated_binary", "zero_vertices", "int_xyz", "empty_file"])
def test_check_ply_catches_header_and_size_problems(tmp_path, name):
    path = tmp_path / "bad_cloud.ply"
    path.write_bytes(dict(_bad_files())[name])
    with pytest.raises(PlyError, match="bad_cloud.ply"):
        check_ply(path)


def test_missing_file(tmp_path):
    with pytest.raises(MissingFileError, match="nope.ply"):
        read_ply(tmp_path / "nope.ply")


@pytest.mark.parametrize("points", [np.zeros((0, 3)), np.zeros((5, 2)), np.zeros(3),
                                    np.array([[0.0, np.inf, 1.0]])],
                         ids=["empty", "2d", "flat", "inf"])
def test_write_rejects_bad_points(tmp_path, points):
    with pytest.raises(ValueError):
        write_ply(tmp_path / "x.ply", points)
