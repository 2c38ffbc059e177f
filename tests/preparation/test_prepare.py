"""The preparation cache: each cleaned sequence is written as soon as it is cleaned (a
paper-size session never holds all of them), the entry maps back exactly what was
cleaned, and a cache that cannot be written or a cleaning that fails loses nothing and
leaves no half-written entry."""

import numpy as np
import pytest

from core.errors import CleaningError
from core.preparation import prepare
from core.preparation.prepare import cache_root, prepare_session


def _same(a, b):
    assert list(a.sequences) == list(b.sequences)
    for n in a.sequences:
        sa, sb = a.sequences[n], b.sequences[n]
        assert sa.role == sb.role
        np.testing.assert_array_equal(sa.frame_times, sb.frame_times)
        np.testing.assert_array_equal(sa.clouds.offsets, sb.clouds.offsets)
        np.testing.assert_array_equal(np.asarray(sa.clouds.points), np.asarray(sb.clouds.points))
        np.testing.assert_array_equal(sa.probe.centres, sb.probe.centres)


def _as_cleaned(prepared, cleaned):
    """The prepared clouds are exactly the cleaned ones, sequence by sequence (cleaning
    itself is not bit-reproducible between runs: Open3D's threads)."""
    assert list(prepared.sequences) == [n for n, _, _ in cleaned]
    for n, points, offsets in cleaned:
        np.testing.assert_array_equal(prepared.sequences[n].clouds.offsets, offsets)
        np.testing.assert_array_equal(np.asarray(prepared.sequences[n].clouds.points), points)


def _spy_cleaning(monkeypatch):
    """[(name, points, offsets)] of every sequence cleaned, in order."""
    cleaned = []
    clean = prepare._clean_sequence

    def spy(session, name, *args, **kwargs):
        out = clean(session, name, *args, **kwargs)
        cleaned.append((name, np.array(out[0]), np.array(out[1])))
        return out

    monkeypatch.setattr(prepare, "_clean_sequence", spy)
    return cleaned


def _leftovers():
    root = cache_root()
    return sorted(p.name for p in root.iterdir() if ".tmp-" in p.name) if root.exists() else []


def test_each_sequence_is_written_once_cleaned_and_mapped_back(sample_session, tmp_path, monkeypatch):
    monkeypatch.setenv("TISSUETWIN_CACHE_DIR", str(tmp_path / "cache"))
    cleaned = _spy_cleaning(monkeypatch)
    written = []
    add = prepare._EntryWriter.add

    def spy(self, name, role, frame_times, points, offsets, path, force):
        # a sequence is written as soon as it is cleaned, before the next one is cleaned,
        # and the entry holds every earlier one on disk already
        assert len(cleaned) == len(written) + 1 and len(self.meta["sequences"]) == len(written)
        written.append(name)
        return add(self, name, role, frame_times, points, offsets, path, force)

    monkeypatch.setattr(prepare._EntryWriter, "add", spy)
    cached = prepare_session(sample_session, workers=0)
    assert written == list(cached.sequences) and len(written) >= 2 and cached.cache_key
    _as_cleaned(cached, cleaned)
    for seq in cached.sequences.values():  # mapped from the entry, not held
        assert seq.clouds.files is not None and not seq.clouds.points.flags.owndata
    assert _leftovers() == []
    again = prepare_session(sample_session, workers=0)  # from the cache
    assert again.cache_key == cached.cache_key and "clean" not in again.timings
    _same(again, cached)


def test_a_cache_that_cannot_be_written_keeps_the_preparation_in_memory(sample_session, tmp_path, monkeypatch):
    monkeypatch.setenv("TISSUETWIN_CACHE_DIR", str(tmp_path / "cache"))
    cleaned = _spy_cleaning(monkeypatch)
    add = prepare._EntryWriter.add

    def full_disk(self, *args):
        if len(self.meta["sequences"]) == 1:  # the second sequence does not fit
            raise OSError(28, "No space left on device")
        return add(self, *args)

    monkeypatch.setattr(prepare._EntryWriter, "add", full_disk)
    got = prepare_session(sample_session, workers=0)
    assert got.cache_key == "" and _leftovers() == []
    assert not any((cache_root()).glob("*/meta.json"))
    # the first sequence, written before the disk filled, is read back; the rest kept
    _as_cleaned(got, cleaned)
    assert all(s.clouds.files is None for s in got.sequences.values())


def test_a_failed_cleaning_leaves_no_half_written_entry(sample_session, tmp_path, monkeypatch):
    monkeypatch.setenv("TISSUETWIN_CACHE_DIR", str(tmp_path / "cache"))
    clean = prepare._clean_sequence
    calls = []

    def fails_second(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise CleaningError("frame 7: nothing of the phantom left")
        return clean(*args, **kwargs)

    monkeypatch.setattr(prepare, "_clean_sequence", fails_second)
    with pytest.raises(CleaningError, match="frame 7"):
        prepare_session(sample_session, workers=0)
    assert _leftovers() == [] and not any(cache_root().glob("*/meta.json"))


def test_an_entry_that_cannot_be_renamed_into_place_falls_back_to_memory(sample_session, tmp_path, monkeypatch):
    """Not a race with another process (no entry exists): what was written is read back."""
    monkeypatch.setenv("TISSUETWIN_CACHE_DIR", str(tmp_path / "cache"))
    cleaned = _spy_cleaning(monkeypatch)

    def no_rename(self, target):
        raise OSError(18, "Invalid cross-device link")

    monkeypatch.setattr(prepare.Path, "rename", no_rename)
    got = prepare_session(sample_session, workers=0)
    assert got.cache_key == "" and _leftovers() == []
    _as_cleaned(got, cleaned)
