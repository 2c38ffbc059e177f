"""`tissuetwin train` and `tissuetwin evaluate` as a user runs them (narrow networks, few epochs)."""

import json

import pytest

from app.cli import main
from core.learning import load_checkpoint

from tests.learning.conftest import WRONG_E

QUICK = ["--widths", "4", "8", "8", "--max-points", "128", "--threads", "1", "--effects", '[{"kind": "gravity"}]']


def test_train_writes_results_checkpoint_and_trajectories(gravity_session, tmp_path, capsys):
    out = tmp_path / "run"
    rc = main(["train", str(gravity_session), "--model", "2d", "--youngs", str(WRONG_E), "--out", str(out),
               "--epochs", "2", *QUICK])
    assert rc == 0
    data = json.loads((out / "train.json").read_text())
    te = data["test_error"]
    assert set(te) >= {"no_network", "corrected"}
    assert te["no_network"] > 3e-3 and te["corrected"] > 0
    assert data["improvement"] == pytest.approx(1 - te["corrected"] / te["no_network"])
    assert data["youngs_modulus"] == WRONG_E and data["model"] == "2d"
    # signed column: at the too soft E the mesh sags below the measured top (positive residual)
    assert data["test_signed_residual"]["no_network"] > 1e-3
    assert set(data["sequences"]["seq01"]["signed_residual"]) == {"no_network", "corrected", "corrected_offline"}
    assert 0 <= data["max_unobserved_offset"] < 1e-2
    assert len(data["losses"]) == 2 and all(r["validation_loss"] > 0 for r in data["losses"])
    assert data["timings"]["per_epoch"] > 0
    ck = load_checkpoint(out / "checkpoint.pt")
    assert ck.youngs_modulus == WRONG_E and ck.session == str(gravity_session) and ck.network.config.kind == "2d"
    assert [e["kind"] for e in ck.replay["effects"]] == ["gravity"]
    assert (out / "trajectories" / "seq01_in_loop.npz").exists() and (out / "trajectories" / "seq01_offline.npz").exists()
    assert "all test" in capsys.readouterr().out


def test_evaluate_writes_table3(gravity_session, tmp_path):
    """Given E (the fit is tested in core.identification), 3 E values, the 2D network, 1 epoch."""
    out = tmp_path / "eval"
    rc = main(["evaluate", str(gravity_session), "--identified", "5000", "--out", str(out), "--epochs", "1", "--models", "2d",
               "--sequences", "seq00", "seq01", "seq02", *QUICK])
    assert rc == 0
    data = json.loads((out / "evaluation.json").read_text())
    assert data["youngs_modulus"] == {"identified": 5000.0, "too stiff": 10000.0, "10 Pa": 10.0}
    rows = [r for r in data["rows"] if r["sequence"] == "seq01"]
    assert [r["label"] for r in rows] == ["identified", "too stiff", "10 Pa"]
    # gravity in the model: 10 Pa collapses, which the table reports as N/A, not as a crash
    assert rows[2]["no_network"] is None and rows[2]["no_network_signed"] is None
    assert rows[0]["no_network"] < 2e-3  # the right E with gravity is near the noise floor
    # signed: the too-stiff E sags less than the truth, so its mesh sits above the points
    assert rows[1]["no_network_signed"] < rows[0]["no_network_signed"]
    assert rows[0]["2d_signed"] is not None and rows[0]["2d_offline_signed"] is not None
    md = (out / "evaluation.md").read_text()
    assert "| E | sequence | no network | 2D | improvement | 3D | improvement | signed: no network | 2D | 3D |" in md
    assert "N/A" in md


def test_train_without_test_sequence_is_a_clear_error(gravity_session, tmp_path, capsys):
    rc = main(["train", str(gravity_session), "--model", "3d", "--out", str(tmp_path / "x"),
               "--sequences", "seq00", "seq02", *QUICK])
    assert rc == 2
    assert "missing role(s) ['test']" in capsys.readouterr().err
