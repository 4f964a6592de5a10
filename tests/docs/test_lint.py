"""The tree passes ruff's checks as pyproject.toml's ``[tool.ruff]`` sets them (errors only:
syntax, undefined and unused names, imports): run here so that the fast tier fails on them."""

from __future__ import annotations

import subprocess
import sys

from support import ROOT


def test_ruff_finds_nothing():
    done = subprocess.run(
        [sys.executable, "-m", "ruff", "check", "--no-cache", "--output-format", "concise", "."],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stdout + done.stderr
