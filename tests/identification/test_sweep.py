"""The paper's sweep: protocol, divergence handling, Dask equals serial."""

import csv

import numpy as np
import pytest

from core.identification import PAPER_COARSE, Trial, executor, refine_grid, sweep, write_sweep
from core.simulation import SimulationConfig
from core.preparation import prepare_session
@pytest.fixture(scope="module")
def prepared(sample_session):
    return prepare_session(sample_session)


def test_refine_grid_is_the_papers_table_2():
    assert refine_grid(1e4) == [2500.0, 5000.0, 7500.0, 25000.0, 50000.0, 75000.0]
    assert PAPER_COARSE == (1e1, 1e2, 1e3, 1e4, 1e5, 1e6)


def test_a_diverging_trial_is_marked_and_the_sweep_goes_on(prepared, tmp_path):
    # explicit integration at dt = 1/1500 s is stable for a 10 Pa phantom (the contact
    # penalty sets the limit, ~2 ms), not for 1 MPa (~0.4 ms): a real divergence
    base = Trial(sequence="", youngs_modulus=1.0, simulation=SimulationConfig(dt=1 / 1500, integrator="symplectic_euler"))
    with executor(serial=True) as ex:
        result = sweep(prepared, [10.0, 1e6], sequences=["seq01"], base=base, executor=ex)
    write_sweep(result, tmp_path)
    rows = list(csv.DictReader((tmp_path / "sweep.csv").open()))
    assert [r["status"] for r in rows] == ["ok", "diverged"]
    assert float(rows[0]["mean_error"]) > 0 and rows[1]["mean_error"] == ""
    assert list(rows[0]) == ["youngs_modulus", "poisson_ratio", "sequence", "mean_error", "status"]
    assert (tmp_path / "sweep.png").stat().st_size > 0
    assert result.best() == 10.0
    # the lowest error is at the end of the grid and the other value diverged: no evidence, no estimate
    assert result.verdict["identifiable"] is False and result.verdict["value"] is None
    assert result.verdict["statistic"]["rise_below"] == 0.0
    assert (tmp_path / "sweep.json").exists()


def test_two_worker_local_cluster_gives_the_same_csv_as_serial(prepared, tmp_path):
    values = [1e2, 1e4]
    with executor(serial=True) as ex:
        serial = sweep(prepared, values, sequences=["seq02", "seq03"], executor=ex)
    with executor(workers=2) as ex:
        dask = sweep(prepared, values, sequences=["seq02", "seq03"], executor=ex)
    write_sweep(serial, tmp_path / "serial")
    write_sweep(dask, tmp_path / "dask")
    assert (tmp_path / "serial" / "sweep.csv").read_bytes() == (tmp_path / "dask" / "sweep.csv").read_bytes()
    errors = [r.mean_error for r in serial.results]
    assert np.all(np.isfinite(errors)) and len(errors) == 4


def test_refined_sweep_adds_the_fine_grid(prepared):
    with executor(serial=True) as ex:
        result = sweep(prepared, [1e3, 1e4], sequences=["seq01"], refine=True, executor=ex)
    Es = sorted(result.table())
    best_coarse = min((1e3, 1e4), key=lambda E: result.table()[E])
    assert set(refine_grid(best_coarse)) <= set(Es)
