"""The tree passes ruff's checks as pyproject.toml's ``[tool.ruff]`` sets them (errors only:
syntax, undefined and unused names, imports) and is laid out as ``ruff format`` lays it out: run
here so that the fast tier fails on either."""

from __future__ import annotations

import subprocess
import sys

from support import ROOT


def ruff(*args: str) -> subprocess.CompletedProcess[str]:
    """``ruff *args`` over the whole tree, from the repository root (so pyproject.toml's settings apply)."""
    return subprocess.run(
        [sys.executable, "-m", "ruff", *args, "--no-cache", "."],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_ruff_finds_nothing():
    done = ruff("check", "--output-format", "concise")
    assert done.returncode == 0, done.stdout + done.stderr


def test_the_tree_is_as_ruff_format_lays_it_out():
    done = ruff("format", "--check", "--output-format", "concise")
    assert done.returncode == 0, (
        "not laid out as ruff formats them; `ruff format .` from the repository root fixes them:\n"
        + done.stdout
        + done.stderr
    )
