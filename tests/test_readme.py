"""The README's main command, run as a user would (smoke test)."""

import os
import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _commands() -> list[str]:
    blocks = re.findall(r"```bash\n(.*?)```", (ROOT / "README.md").read_text(), flags=re.S)
    return [b.strip() for b in blocks[:2]]


def test_readme_gives_exactly_two_setup_commands():
    main_cmd, test_cmd = _commands()
    assert "\n" not in main_cmd and "\n" not in test_cmd
    assert main_cmd.startswith("bash scripts/setup.sh && ") and "tissuetwin demo" in main_cmd
    assert test_cmd.startswith("bash scripts/setup.sh && ") and "pytest" in test_cmd
    ci = (ROOT / ".ci" / "run").read_text()
    assert test_cmd in ci


@pytest.mark.slow
def test_readme_main_command_runs(tmp_path):
    """Runs the README's main command verbatim from the repository root; the demo data
    go to a temporary folder through TISSUETWIN_DATA so the checkout stays clean."""
    main_cmd, _ = _commands()
    env = dict(os.environ, TISSUETWIN_DATA=str(tmp_path / "data"))
    proc = subprocess.run(main_cmd, shell=True, cwd=ROOT, env=env, capture_output=True, text=True, timeout=1800)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert (tmp_path / "data" / "runs" / "demo-replay" / "replay.json").exists()
    if (ROOT.parent / "shared" / "sample-session" / "session.json").exists():
        assert (tmp_path / "data" / "runs" / "sample-replay" / "replay.json").exists()
    assert "mean error (mm)" in proc.stdout
