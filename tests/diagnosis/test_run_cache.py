"""The diagnosis's cache of field runs is bounded in bytes (a paper-size diagnosis kept ~3 GB
of runs): dropping a run costs a replay, never a different answer."""

import numpy as np

from core.diagnosis.config import DiagnosisConfig
from core.diagnosis.evidence import Evidence, LruCache, _run_bytes
from core.diagnosis.patches import field_layout
from core.diagnosis.trials import drop_binned_points
from core.identification.execution import SerialExecutor
from core.preparation import prepare_session


def _evidence(session, limit):
    prepared = prepare_session(session)
    cfg = DiagnosisConfig(fine_grid=None)
    ev = Evidence(prepared, cfg, SerialExecutor(), field_layout(prepared, cfg))
    ev.cache = LruCache(limit, _run_bytes)
    return ev


def test_a_bounded_cache_replays_what_it_dropped_and_answers_the_same(small_session):
    roomy, tight = _evidence(small_session, 1 << 30), _evidence(small_session, 1)
    gravity = [{"kind": "gravity", "g": [0.0, 0.0, -9.81]}]
    first = {name: ev.runs([[], gravity], "validation") for name, ev in (("roomy", roomy), ("tight", tight))}
    n_val = len(roomy.names["validation"])
    assert roomy.simulations == tight.simulations == 2 * n_val
    # the limit keeps one run; the roomy cache holds all of them
    assert len(tight.cache) == 1 and len(roomy.cache) == 2 * n_val
    assert roomy.cache.bytes == sum(_run_bytes(r) for r in roomy.cache.values()) > 0
    again = {name: ev.runs([[], gravity], "validation") for name, ev in (("roomy", roomy), ("tight", tight))}
    assert roomy.simulations == 2 * n_val  # all cached
    assert tight.simulations > 2 * n_val  # dropped runs replayed
    # and counted as repeated work: every simulation past the first pass replays a dropped run
    assert roomy.repeated == 0 and tight.repeated == tight.simulations - 2 * n_val
    for name in ("roomy", "tight"):
        for a, b in zip(first[name], again[name]):
            for ra, rb in zip(a, b):
                np.testing.assert_array_equal(ra.field, rb.field)
    for a, b in zip(first["roomy"], first["tight"]):
        for ra, rb in zip(a, b):
            np.testing.assert_array_equal(ra.field, rb.field)
            np.testing.assert_array_equal(ra.force, rb.force)
    # gravity changes the field: the runs compared are not all the same run
    assert not np.array_equal(first["roomy"][0][0].field, first["roomy"][1][0].field)
    # the base model's runs count the inverted elements (the diagnosis's note), a model with
    # effects does not (nothing reads it): 0 under the small session's shallow presses
    assert [r.inverted for r in first["roomy"][0]] == [0] * n_val
    assert [r.inverted for r in first["roomy"][1]] == [None] * n_val


def test_the_least_recently_used_run_goes_first():

    from dataclasses import make_dataclass

    Run = make_dataclass("Run", [("a", np.ndarray)])
    cache = LruCache(3 * 800, _run_bytes)
    for k in "abc":
        cache.put(k, Run(np.zeros(100)))
    assert cache.get_recent("a") is not None  # a is now the most recent
    cache.put("d", Run(np.zeros(100)))
    assert list(cache) == ["c", "a", "d"] and cache.bytes == 2400
    assert cache.get_recent("b") is None
    cache.put("big", Run(np.zeros(1000)))  # larger than the limit: kept alone
    assert list(cache) == ["big"] and cache.bytes == 8000


def _binned_entries() -> int:
    from core.diagnosis import trials

    return len(trials._BINS)


def test_the_test_stage_can_empty_every_workers_binned_points(small_session):
    """Each Dask worker caches the binned points of the sequences it replays; the diagnosis
    empties them on every worker before its test stage (run_everywhere), and a later run
    bins again and gives the same field."""
    from core.identification import executor

    prepared = prepare_session(small_session)
    cfg = DiagnosisConfig(fine_grid=None)
    with executor(workers=2) as ex:
        ev = Evidence(prepared, cfg, ex, field_layout(prepared, cfg))
        first = ev.runs([[]], "validation")[0]
        held = ex.client.run(_binned_entries)
        assert sum(held.values()) >= len(ev.names["validation"]) and len(held) == 2
        ex.run_everywhere(drop_binned_points)
        assert set(ex.client.run(_binned_entries).values()) == {0}
        ev.cache.clear()
        again = ev.runs([[]], "validation")[0]
        assert sum(ex.client.run(_binned_entries).values()) >= len(ev.names["validation"])
    for a, b in zip(first, again):
        np.testing.assert_array_equal(a.field, b.field)
