"""Memory-mapped cleaned clouds: a stage done with a sequence gives its pages back."""

import sys

import numpy as np
import pytest

from core.preparation import Clouds, release_pages


def _resident_mib() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096 / 2**20


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/statm")
def test_released_clouds_leave_the_resident_set_and_read_the_same(tmp_path):
    rng = np.random.default_rng(0)
    counts = rng.integers(20_000, 40_000, size=200)
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    points = rng.normal(size=(int(offsets[-1]), 3)).astype(np.float32)  # ~70 MB
    np.save(tmp_path / "points.npy", points)
    np.save(tmp_path / "offsets.npy", offsets)
    clouds = Clouds.open(str(tmp_path / "points.npy"), str(tmp_path / "offsets.npy"))
    window = clouds.window(50, 150)
    before = _resident_mib()
    total = sum(float(c.sum(dtype=np.float64)) for c in clouds)  # every page touched
    touched = _resident_mib()
    assert touched - before > 0.8 * points.nbytes / 2**20
    assert release_pages(window)  # a window's release drops the whole file's mapping
    released = _resident_mib()
    assert touched - released > 0.8 * points.nbytes / 2**20
    # the same values are read back (from the page cache or the file)
    assert sum(float(c.sum(dtype=np.float64)) for c in clouds) == total
    np.testing.assert_array_equal(clouds[137], points[offsets[137]:offsets[138]])


def test_clouds_in_memory_are_not_released():
    clouds = Clouds.from_arrays([np.zeros((5, 3)), np.ones((7, 3))])
    assert not release_pages(clouds) and not release_pages([np.zeros((2, 3))])
    assert float(clouds[1].sum()) == 21.0
