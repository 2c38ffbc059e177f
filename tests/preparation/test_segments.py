"""Informative frames: sequences cut at rest into segments replayed from rest.

On the shared sample session (an independent generator's 12 s sequences: top and side
pokes, holds, slides, rests between some) the segments tile every sequence's frames, and a segment replayed from rest matches the
whole sequence's replay there: the gel is back at rest when the probe has been clear for
a second (measured: at most 0.001 mm and 0.7 mN apart on a 12 s randomised-lab session).
A Maxwell arm of 1 s relaxation remembers the previous poke (measured: 0.58 mm), which is
what the tolerance below would catch.
"""

import numpy as np
import pytest

from core.preparation import prepare_session
from core.preparation.segments import segment_session, segments_of, select_segments
from core.simulation.replay import ReplayConfig, replay_sequence


@pytest.fixture(scope="module")
def prepared(sample_session):
    return prepare_session(sample_session)


def test_segments_tile_the_frames_and_start_at_rest(prepared):
    n_cut = 0
    for name, seq in prepared.sequences.items():
        segs = segments_of(prepared, name)
        assert segs[0].start == 0 and segs[-1].stop == seq.frame_times.size
        assert all(a.stop == b.start for a, b in zip(segs[:-1], segs[1:]))
        rest = set(prepared.rest_frames(name, settle=0.5).tolist())
        for s in segs[1:]:
            assert s.start in rest  # every cut lies in a rest
        n_cut += len(segs) - 1
        assert {s.kind for s in segs} <= {"top", "side", "slide", "rest"}
    assert n_cut >= 3  # it rests between some pokes


def test_a_segment_replayed_from_rest_is_the_sequence_replayed_whole(prepared):
    segments = [s for n in prepared.sequences for s in segments_of(prepared, n)]
    cut = segment_session(prepared, segments)
    config = ReplayConfig()
    worst = 0.0
    for name in prepared.sequences:
        full = replay_sequence(prepared, name, config).simulation
        for s in (s for s in segments if s.sequence == name):
            part = replay_sequence(cut, s.name, config).simulation
            assert part.ok
            worst = max(worst, float(np.abs(part.positions - full.positions[s.start:s.stop]).max()))
            np.testing.assert_array_equal(np.asarray(cut.sequences[s.name].clouds[0]),
                                          np.asarray(prepared.sequences[name].clouds[s.start]))
    assert worst < 0.02e-3, worst


def test_a_budget_covers_the_kinds_of_palpation(prepared):
    segments = [s for n in prepared.sequences for s in segments_of(prepared, n)]
    kinds = {s.kind for s in segments}
    chosen = select_segments(segments, len(kinds))
    assert {s.kind for s in chosen} == kinds
    assert select_segments(segments, len(segments) + 5) == segments
