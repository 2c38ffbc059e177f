"""End to end through the command line: a session without effects must yield no cause.

The session is the `small` preset with 6 s sequences (train x 2, validation, test) to
keep the suite's time; hidden effects are in test_hidden_*.py and two of them together
in test_diagnose_two_effects.py; the benchmark (benchmarks/bench_diagnosis.py) runs every
kind against all eight candidates on three seeds.
"""

import json

import pytest

from app.cli import main
from tests.diagnosis._hidden import check_contract, lab_session

pytestmark = pytest.mark.slow  # whole diagnoses, 1-3 min each


def test_no_effect_gives_no_cause_through_the_command_line(tmp_path_factory, capsys):
    session = lab_session(tmp_path_factory, "none-0", 0, [])
    out = tmp_path_factory.mktemp("out")
    assert main(["diagnose", str(session), "--out", str(out), "--serial", "--no-mesh-refinement"]) == 0
    assert "no effect found" in capsys.readouterr().out
    data = json.loads((out / "diagnosis.json").read_text())
    check_contract(data, session)
    assert data["causes"] == [] and data["extended"]["kinds"] == []
    assert data["youngs_modulus"]["identifiable"] is False  # displacement only, no gravity
    report = (out / "report.md").read_text()
    assert "No effect found" in report and (out / "residual_maps.png").stat().st_size > 10_000
