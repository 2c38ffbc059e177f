"""Informative frames: a sequence cut into segments that each start from rest.

A poke and the rest that follows it hardly depend on the previous poke once the phantom
is back at rest (the probe clear of it for a while): the Rayleigh stiffness damping of a
gel lets a dent recover within a few tenths of a second. A long sequence can therefore
be replayed as independent segments, each from the rest state, in parallel on the
workers, and a fit or a diagnosis can spend its simulations on a bounded number of
segments chosen to cover the palpation, so that its cost stops growing with the
length of the recording. What this changes against a replay of the whole sequence is
measured in ``tests/preparation/test_segments.py`` and ``benchmarks/bench_scaling.py``;
a viscoelastic phantom whose relaxation outlasts the rests remembers the previous poke,
which a segment starting from rest does not.

A segment of sequence ``name`` is named ``name@k`` and keeps its role; its frames are
the parent's frames between two cuts, each cut in the middle of a rest (frames whose
probe has been clear of the phantom by ``clearance`` for at least ``settle`` seconds),
and its probe path starts ``lead`` seconds before its first frame.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from core.preparation.prepared import Clouds, PreparedSequence, PreparedSession
from core.preparation.probe import ProbePath

__all__ = ["Segment", "segments_of", "segment_session", "select_segments", "informative_session"]


@dataclass(frozen=True)
class Segment:
    """Frames ``[start, stop)`` of sequence ``sequence`` (a poke with its rests).

    Attributes:
        kind: what the probe did in it: "top" (pressed the top face), "side" (pressed a
            side face), "slide" (moved along the pressed face at more than 2 mm/s for at
            least 0.2 s) or "rest" (touched nothing).
        depth: deepest indentation into the rest box, m.
    """

    sequence: str
    start: int
    stop: int
    kind: str
    depth: float

    @property
    def name(self) -> str:
        return f"{self.sequence}@{self.start}"


def _depth(c: np.ndarray, size: np.ndarray, radius: float) -> np.ndarray:
    inside = np.clip(c, 0.0, size)
    gap = np.linalg.norm(c - inside, axis=1)
    depth_in = np.min(np.concatenate([c, size - c], axis=1), axis=1) + radius
    return np.where(gap > 0, np.maximum(radius - gap, 0.0), depth_in)


def segments_of(prepared: PreparedSession, name: str, *, settle: float = 0.5, clearance: float = 0.002,
                min_frames: int = 3) -> list[Segment]:
    """The segments of sequence ``name`` (see the module docstring), in time order; the
    whole sequence as one segment when it never comes to rest between two contacts."""
    seq = prepared.sequences[name]
    F = seq.frame_times.size
    rest = np.zeros(F, dtype=bool)
    rest[prepared.rest_frames(name, settle=settle, clearance=clearance)] = True
    # cut in the middle of every rest run that lies between two active runs
    cuts = [0]
    f = 0
    while f < F:
        if rest[f]:
            g = f
            while g < F and rest[g]:
                g += 1
            if f > 0 and g < F:  # active frames before and after
                mid = (f + g) // 2
                if mid - cuts[-1] >= min_frames and F - mid >= min_frames:
                    cuts.append(mid)
            f = g
        else:
            f += 1
    cuts.append(F)
    size = np.asarray(prepared.size, dtype=np.float64)
    r = float(prepared.probe_radius)
    out = []
    for a, b in zip(cuts[:-1], cuts[1:]):
        t = seq.frame_times[a:b]
        c = seq.probe.at(t)
        d = _depth(c, size, r)
        pressed = d > 0.0005
        kind = "rest"
        if np.any(pressed):
            over = (c[:, 0] > 0) & (c[:, 0] < size[0]) & (c[:, 1] > 0) & (c[:, 1] < size[1])
            kind = "top" if np.any(pressed & over & (c[:, 2] > size[2] - r)) else "side"
            if t.size > 2:
                # the pressed face's normal axis: z over the top, else the nearer side plane's
                side_axis = np.where(np.minimum(np.abs(c[:, 0]), np.abs(c[:, 0] - size[0]))
                                     < np.minimum(np.abs(c[:, 1]), np.abs(c[:, 1] - size[1])), 0, 1)
                axis = np.where(over, 2, side_axis)
                vel = np.gradient(c, t, axis=0)
                tangential = vel.copy()
                tangential[np.arange(t.size), axis] = 0.0  # motion along the face, not into it
                moving = pressed & (np.linalg.norm(tangential, axis=1) > 0.002)
                if np.sum(np.diff(t)[moving[1:]]) >= 0.2:
                    kind = "slide"
        out.append(Segment(name, int(a), int(b), kind, float(d.max(initial=0.0))))
    return out


def _cut(seq: PreparedSequence, seg: Segment, lead: float) -> PreparedSequence:
    t = seq.frame_times[seg.start:seg.stop]
    t0 = float(t[0]) - lead
    keep = (seq.probe.t >= t0) & (seq.probe.t <= float(t[-1]) + 1e-9)
    idx = np.flatnonzero(keep)
    if idx.size < 2:  # a path sampled more coarsely than the segment: interpolate its ends
        pt = np.array([t0, float(t[-1]) + 1e-6])
        path = ProbePath(pt, seq.probe.at(pt))
        force = None if seq.force is None else seq.force_at(pt)
    else:
        lo = max(idx[0] - 1, 0)  # the sample before t0, so that the path covers it
        path = ProbePath(seq.probe.t[lo:idx[-1] + 1], seq.probe.centres[lo:idx[-1] + 1])
        force = None if seq.force is None else seq.force[lo:idx[-1] + 1]
    clouds = seq.clouds
    if isinstance(clouds, Clouds):
        sub = clouds.window(seg.start, seg.stop)
    else:
        sub = tuple(clouds[seg.start:seg.stop])
    return PreparedSequence(seg.name, seq.role, t, path, sub, force)


def segment_session(prepared: PreparedSession, segments: list[Segment] | None = None, *,
                    lead: float = 0.5) -> PreparedSession:
    """The session whose sequences are ``segments`` (default: every segment of every
    sequence, :func:`segments_of`), each a :class:`PreparedSequence` named ``name@k``
    with its parent's role, frames, clouds (views, no copy) and force, its probe path
    starting ``lead`` s before its first frame (the replay starts there, at rest)."""
    if segments is None:
        segments = [s for n in prepared.sequences for s in segments_of(prepared, n)]
    seqs = {s.name: _cut(prepared.sequences[s.sequence], s, lead) for s in segments}
    return replace(prepared, sequences=seqs, cache_key="")


def select_segments(segments: list[Segment], budget: int) -> list[Segment]:
    """At most ``budget`` segments that cover the palpation: round-robin over the kinds
    present (slides, side presses, top presses, then rests), each kind's segments taken
    from the deepest, spread over the sequences; in time order. The choice depends on
    what the probe did, never on residuals, so a held-out test on the chosen segments
    keeps its null distribution."""
    if budget >= len(segments):
        return list(segments)
    order = ("slide", "side", "top", "rest")
    pools = {k: sorted([s for s in segments if s.kind == k], key=lambda s: -s.depth) for k in order}
    chosen: list[Segment] = []
    used_seq: dict[str, int] = {}
    while len(chosen) < budget and any(pools.values()):
        for k in order:
            if not pools[k] or len(chosen) >= budget:
                continue
            # the deepest segment of this kind from the sequence used least so far
            best = min(range(len(pools[k])), key=lambda i: (used_seq.get(pools[k][i].sequence, 0), i))
            s = pools[k].pop(best)
            chosen.append(s)
            used_seq[s.sequence] = used_seq.get(s.sequence, 0) + 1
    return sorted(chosen, key=lambda s: (s.sequence, s.start))


def informative_session(prepared: PreparedSession, budget: int) -> PreparedSession:
    """``prepared`` with its train and validation sequences replaced by at most ``budget``
    segments each (:func:`select_segments`, cut by :func:`segments_of`); test sequences
    whole, so that held-out gains are measured on whole recordings (the diagnosis's
    ``segments`` option)."""
    chosen = []
    for role in ("train", "validation"):
        segs = [s for n, q in prepared.sequences.items() if q.role == role for s in segments_of(prepared, n)]
        chosen += select_segments(segs, budget)
    cut = segment_session(prepared, chosen)
    test = {n: q for n, q in prepared.sequences.items() if q.role == "test"}
    return replace(cut, sequences={**cut.sequences, **test})
