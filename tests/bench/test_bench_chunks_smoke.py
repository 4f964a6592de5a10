"""The chunks benchmark keeps working here: ``bench/bench_chunks.py --cpu-small`` on a cheap gym
scene runs as a person would run it (the physics-only processes, a real job of two pinned pods,
the service alone and the EnvLoop at each K, two stages at K = 8) and prints one ``RESULT {json}``
line with every figure docs/benchmarks.md's chunks section is built from. It runs from a copy of
``bench/`` in a temporary directory, so its JSON lands there. No timing is asserted."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from support.bench_scripts import bench_result

# A benchmark script run end to end, with its own pods: 20-60 s a run on 2 cores.
pytestmark = pytest.mark.slow

ARGS = [
    "--cpu-small",
    "--tasks",
    "gym/HalfCheetah-v5",
    "--envs-per-task",
    "2",
    "--size",
    "16",
    "--actions",
    "8",
    "--chunks",
    "1,8",
    "--physics-seconds",
    "0.5",
    "--waves",
    "2",
]


@pytest.fixture(scope="module")
def summary(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict[str, Any], Path]:
    root = tmp_path_factory.mktemp("bench-chunks")
    return bench_result(root, "bench_chunks.py", *ARGS, timeout=170), root


@pytest.mark.timeout(180)
def test_chunks_bench_measures_every_k_against_k1_and_physics_only(summary):
    result, root = summary
    assert result["name"] == "bench_chunks_cpu" and set(result["met"]) == {"chunks", "physics_only", "ceiling"}
    for kind in ("service", "loop"):
        assert set(result[kind]) == {"K=1", "K=8"}
        for row in result[kind].values():
            assert row["env_steps_per_s"]["median"] > 0 and row["fraction_of_physics_only"] > 0
            assert row["fraction_of_ceiling"] > 0
        assert result[kind]["K=8"]["over_K=1"]["n"] == 1
    assert result["physics_only"]["processes"] == 2 and result["physics_only"]["env_steps_per_s"] > 0
    assert isinstance(result["ratio"], float) and isinstance(result["ratio_of_physics_only"], float)
    record = json.loads((root / "out" / "bench" / "bench_chunks_cpu.json").read_text())
    assert set(record["details"]["per_round"]) == {
        "service/K=1",
        "service/K=8",
        "loop/K=1",
        "loop/K=8",
        "loop_stages=2/K=8",
        "loop_slices=2/K=8",
        "ceiling/K=1",
        "ceiling/K=1/reset_every_8",
        "ceiling/K=8",
        "ceiling/K=8/reset_every_8",
    }


@pytest.mark.timeout(180)
def test_chunks_bench_holds_the_node_against_its_ceiling_with_cameras_and_the_pods_physics_against_the_bare(summary):
    result, _ = summary
    ceiling = result["ceiling"]
    assert ceiling["processes"] == 2 and ceiling["camera"]["height"] == 16
    for k in ("K=1", "K=8"):
        assert ceiling[k]["env_steps_per_s"] > 0 and ceiling[k]["render_ms_per_env_step"] > 0
        # ... and again with every env reset after --actions actions, as a rollout of that horizon.
        assert ceiling[f"{k}/reset_every_8"]["env_steps_per_s"] > 0
        assert result["loop"][k]["fraction_of_ceiling_with_resets"] > 0
    assert isinstance(result["ratio_of_ceiling"], float)
    # The ceiling is a contender of every round (while the pods idle), and the fractions of it
    # are paired by round.
    assert len(ceiling["K=8"]["per_round"]) == result["setup"]["rounds"] == 1
    assert ceiling["K=8"]["env_steps_per_s"] == ceiling["K=8"]["per_round"][0]
    loop = result["loop"]["K=8"]
    assert loop["fraction_of_ceiling"] == pytest.approx(
        loop["env_steps_per_s"]["median"] / ceiling["K=8"]["per_round"][0], abs=0.002
    )
    assert loop["fraction_of_ceiling_with_resets_by_round"]["n"] == 1
    times = result["per_env_step_ms"]
    assert times["bare_physics_only"] > 0 and times["bare_ceiling/K=8"]["physics_ms_per_env_step"] > 0
    assert times["pod/loop/K=8"]["physics_ms_per_env_step"] > 0


@pytest.mark.timeout(180)
def test_chunks_bench_measures_pipelining_at_k8(summary):
    result, _ = summary
    assert result["pipeline"]["speedup_2_vs_1"]["n"] == 1
    assert result["pipeline"]["stages=2"]["env_steps_per_s"]["median"] > 0
    # ... and with the two stages as slices of every pod; the best of the loops is named.
    assert result["slices"]["speedup_2_vs_1"]["n"] == 1
    assert result["slices"]["stages=2"]["fraction_of_ceiling"] > 0
    assert result["best_loop_of_ceiling"]["contender"].startswith("loop/")


@pytest.mark.timeout(180)
def test_chunks_bench_runs_every_loop_rollout_with_its_waves_of_trajectories_per_env(summary):
    result, _ = summary
    # --waves 2: two trajectories per env of the 2 pods x 2 envs, refilled as envs free up.
    assert result["setup"]["waves"] == 2
    for k in ("K=1", "K=8"):
        assert result["loop"][k]["trajectories"] == 2 * 4
