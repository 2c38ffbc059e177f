"""The tissuetwin command line as a user runs it."""

import json
import shutil

import pytest


from app.cli import build_parser, main


def test_replay_command_writes_results_and_prints_a_table(sample_session, tmp_path, capsys):
    rc = main(["replay", str(sample_session), "--out", str(tmp_path / "run"), "--sequences", "seq01"])
    assert rc == 0
    out = capsys.readouterr().out
    assert "seq01" in out and "mean error (mm)" in out and "noise floor" in out
    data = json.loads((tmp_path / "run" / "replay.json").read_text())
    assert list(data["sequences"]) == ["seq01"]
    assert 0.5e-3 < data["sequences"]["seq01"]["mean_error"] < 3e-3  # metres in files
    assert (tmp_path / "run" / "seq01.npz").exists() and (tmp_path / "run" / "frame_errors.csv").exists()


def test_bad_session_gives_one_clear_line_and_exit_2(sample_session, tmp_path, capsys):
    broken = tmp_path / "broken"
    shutil.copytree(sample_session, broken)
    (broken / "sequences" / "seq01" / "clouds" / "000003.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 5\n")
    rc = main(["replay", str(broken), "--out", str(tmp_path / "run")])
    err = capsys.readouterr().err
    assert rc == 2
    # progress lines (stderr is not a terminal here) come before it; the error is one line
    lines = err.strip().splitlines()
    assert lines[-1].startswith("error: ") and "000003.ply" in lines[-1]
    assert sum(line.startswith("error") for line in lines) == 1 and "Traceback" not in err
    assert not (tmp_path / "run" / "replay.json").exists()


def test_unknown_sequence_and_bad_effects_are_rejected(sample_session, tmp_path, capsys):
    assert main(["replay", str(sample_session), "--out", str(tmp_path), "--sequences", "nope"]) == 2
    assert "nope" in capsys.readouterr().err
    assert main(["replay", str(sample_session), "--out", str(tmp_path), "--effects", "[{\"kind\": \"magic\"}]"]) == 2
    assert "unknown effect kind" in capsys.readouterr().err


def test_generate_command_is_deterministic(tmp_path):
    """The same seed writes the same session, byte for byte (6 s sequences, the shortest with
    a poke: the property does not depend on their length, and two whole small sessions of
    10 s sequences took 33 s of the suite)."""
    args = ["generate", "--preset", "small", "--seed", "5", "--duration", "6"]
    for name in ("a", "b"):
        assert main(args + ["--out", str(tmp_path / name)]) == 0
    for part in ("kinematics.csv", "clouds/000010.ply"):
        a = (tmp_path / "a" / "sequences" / "seq00" / part).read_bytes()
        b = (tmp_path / "b" / "sequences" / "seq00" / part).read_bytes()
        assert a == b, part
    # refusing to clobber an existing session is an error, not a crash
    assert main(args + ["--out", str(tmp_path / "a")]) == 2


def test_sweep_command_writes_the_papers_table(sample_session, tmp_path, capsys):
    rc = main(["sweep", str(sample_session), "--youngs", "1e2,1e4", "--sequences", "seq03", "--serial", "--out", str(tmp_path)])
    assert rc == 0
    lines = (tmp_path / "sweep.csv").read_text().splitlines()
    assert lines[0] == "youngs_modulus,poisson_ratio,sequence,mean_error,status"
    assert [l.split(",")[0] for l in lines[1:]] == ["100", "10000"] and all(l.endswith(",ok") for l in lines[1:])
    assert (tmp_path / "sweep.png").exists()
    out = capsys.readouterr().out  # the sample session (no force, no gravity): no "best E", the fit's verdict
    assert "E not identifiable from these data" in out and "best E" not in out
    verdict = json.loads((tmp_path / "sweep.json").read_text())["youngs_modulus"]
    assert verdict["identifiable"] is False and verdict["value"] is None and verdict["reason"] in out
    assert main(["sweep", str(sample_session), "--youngs", "abc", "--out", str(tmp_path)]) == 2


def test_fit_command_says_when_E_cannot_be_identified(sample_session, tmp_path, capsys):
    """The sample session is displacement-controlled, without gravity or force: E is not identifiable."""
    rc = main(["fit", str(sample_session), "--serial", "--out", str(tmp_path)])
    assert rc == 0
    data = json.loads((tmp_path / "fit.json").read_text())
    assert data["youngs_modulus"]["identifiable"] is False and data["youngs_modulus"]["value"] is None
    assert data["youngs_modulus"]["reason"].startswith("flat profile")
    assert set(data["errors"]) == {"train", "validation", "test"}
    assert all(0.5e-3 < e < 5e-3 for e in data["errors"].values())  # the paper's error, measured at E*
    captured = capsys.readouterr()
    assert "not identifiable" in captured.out
    # a log (not a terminal) gets a timestamped line per stage of the fit, not a silent bar
    stages = [line for line in captured.err.splitlines() if line.startswith("[") and "] fit: E values evaluated" in line]
    said = " ".join(stages)
    for stage in ("coarse scan", "minimising J", "profile", "errors per role"):
        assert stage in said, captured.err
    assert len(stages) < 60, captured.err


def test_help_lists_every_command_and_each_command_has_help(capsys):
    """``--help`` formats every help string (a bare '%' once broke it)."""
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    for name in sub.choices:
        with pytest.raises(SystemExit) as exc:
            main([name, "--help"])
        assert exc.value.code == 0
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    for name in sub.choices:
        assert name in out
