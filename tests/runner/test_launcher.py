"""The shared venv's ``vecsim`` command (``service/launcher.py``, written by scripts/setup.sh)
names the checkout it runs, and when that checkout is gone says so plainly instead of failing
with ``No module named 'service'``."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from support import ROOT

from service.launcher import write_launcher


def run(launcher: Path, *args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run(
        [str(launcher), *args], env=env, cwd=launcher.parent, capture_output=True, text=True, timeout=60, check=False
    )


def test_the_command_names_the_checkout_it_runs(tmp_path):
    launcher = tmp_path / "vecsim"
    write_launcher(launcher, Path(sys.executable), ROOT)
    done = run(launcher, "--version")
    assert done.returncode == 0 and done.stdout.strip().endswith(f"from {ROOT}"), done.stderr
    assert f"from {ROOT}" in run(launcher, "--help").stdout


def test_a_command_whose_checkout_is_gone_says_which_and_how_to_point_the_venv_elsewhere(tmp_path):
    gone = tmp_path / "old-checkout"
    launcher = tmp_path / "vecsim"
    write_launcher(launcher, Path(sys.executable), gone)
    done = run(launcher, "demo")
    assert done.returncode == 1
    assert f"runs the checkout at {gone}, which is gone" in done.stderr and "scripts/setup.sh" in done.stderr
    assert "No module named" not in done.stderr
