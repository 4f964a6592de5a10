"""``bench/bench_revisions.py`` runs one benchmark at two git revisions turn about and records
each revision's headline ratio: here the cheapest benchmark (``bench_scaling.py --quick``) at
HEAD and HEAD, one round, as a person would run it, from a copy of ``bench/`` in a temporary
directory so that its record lands there. No timing is asserted."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from support import ROOT
from support.bench_scripts import bench_result

# Two runs of a benchmark with its own pods, and two checkouts: ~30 s on 2 cores.
pytestmark = pytest.mark.slow


def revision_worktrees() -> list[str]:
    """The repository's worktrees that bench_revisions.py made (under its temporary directories)."""
    done = subprocess.run(
        ["git", "-C", str(ROOT), "worktree", "list", "--porcelain"],
        capture_output=True,
        text=True,
        timeout=30,
        check=True,
    )
    return [line for line in done.stdout.splitlines() if line.startswith("worktree ") and "bench_revisions-" in line]


Run = tuple[dict[str, Any], dict[str, Any], list[str]]


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Run:
    root = tmp_path_factory.mktemp("bench-revisions")
    result = bench_result(
        root,
        "bench_revisions.py",
        "--bench",
        "bench_scaling.py",
        "--quick",
        "--revisions",
        "HEAD,HEAD",
        "--repo",
        str(ROOT),
        "--timeout-s",
        "120",
        timeout=170,
    )
    record = json.loads((root / "out" / "bench" / "bench_revisions_bench_scaling.json").read_text())
    return result, record, revision_worktrees()


@pytest.mark.timeout(200)
def test_record_holds_each_revisions_ratio_per_round(run: Run) -> None:
    _, record, _ = run
    for label in ("A", "B"):
        ratios = record["ratios"][label]
        assert ratios["rev"] == "HEAD" and len(ratios["commit"]) == 40
        assert len(ratios["per_round"]) == 1 and ratios["per_round"][0] > 0
        # Each run's ratio is the one its benchmark recorded.
        assert ratios["per_round"][0] == pytest.approx(record["details"][label][0]["ratio"], abs=1e-4)
        assert record["details"][label][0]["name"] == "bench_scaling"


@pytest.mark.timeout(200)
def test_headline_is_b_median_over_a_median(run: Run) -> None:
    result, record, _ = run
    assert result["name"] == "bench_revisions_bench_scaling" and result["quick"] is True
    expected = record["ratios"]["B"]["median"] / record["ratios"]["A"]["median"]
    assert result["ratio"] == pytest.approx(expected, abs=1e-3)
    assert record["setup"]["bench_args"] == ["--quick"]


@pytest.mark.timeout(200)
def test_each_revision_runs_its_own_checkout(run: Run) -> None:
    _, record, _ = run
    assert record["setup"]["imported_from_tree"]["A"] == {
        "vecsim": "vecsim/__init__.py",
        "service": "service/__init__.py",
    }
    assert record["setup"]["imported_from_tree"]["B"] == record["setup"]["imported_from_tree"]["A"]


@pytest.mark.timeout(200)
def test_checkouts_are_removed_afterwards(run: Run) -> None:
    *_, left = run
    assert left == []


@pytest.mark.timeout(60)
def test_an_unknown_revision_is_refused_naming_the_flag(tmp_path: Path) -> None:
    done = subprocess.run(
        [
            sys.executable,
            str(ROOT / "bench" / "bench_revisions.py"),
            "--bench",
            "bench_scaling.py",
            "--revisions",
            "HEAD,no-such-revision-xyz",
        ],
        cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 2
    assert "--revisions" in done.stderr and "no-such-revision-xyz" in done.stderr
