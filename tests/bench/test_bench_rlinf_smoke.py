"""The RLinf benchmark keeps working here: ``bench/bench_rlinf.py --smoke`` runs as a person would
run it (RLinf's own LiberoEnv and vecsim's RLinf env over a pinned standalone pod, 2 slots of
libero_spatial/0 at 32x32, one round) from a copy of ``bench/`` in a temporary directory, and
prints one ``RESULT {json}`` line with the figures docs/trainers.md quotes. No timing is asserted."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from support.bench_scripts import bench_result

pytest.importorskip("rlinf")

pytestmark = pytest.mark.libero


@pytest.mark.timeout(600)
def test_rlinf_bench_reports_both_envs_side_by_side(tmp_path: Path) -> None:
    result = bench_result(tmp_path, "bench_rlinf.py", "--smoke", timeout=580)
    assert result["name"] == "bench_rlinf_smoke" and result["k"] == 8
    (row,) = result["results"]
    assert row["slots"] == 2 and row["vecsim_over_rlinf"]["n"] == 1
    for name in ("rlinf", "vecsim"):
        assert row["env_steps_per_s"][name]["median"] > 0
    assert isinstance(result["ratio"], float) and isinstance(result["met"], bool)
    record = json.loads((tmp_path / "out" / "bench" / "bench_rlinf_smoke.json").read_text())
    assert list(record["details"]["rounds"]) == ["2"]
