"""``bench/bench_action_cost.py --quick`` runs as a person would run it: LIBERO envs in one
process, three action streams in turn from the same init states, one ``RESULT {json}`` line and
its record. No timing is asserted: the figures depend on the machine and its load."""

from __future__ import annotations

import json

import pytest
from support.bench_scripts import result_of, run_bench_script


@pytest.mark.timeout(240)
@pytest.mark.slow
@pytest.mark.libero
def test_quick_run_times_each_stream_on_every_task_and_names_its_baseline(tmp_path):
    done = run_bench_script(tmp_path, "bench_action_cost.py", "--quick", "--actions", "4", timeout=230)
    summary = result_of(done)
    assert summary["name"] == "bench_action_cost_quick" and summary["quick"] is True
    assert set(summary["physics_ms_per_env_step"]) == {"random", "sine", "policy"}
    assert all(spread["median"] > 0 and spread["n"] == 1 for spread in summary["physics_ms_per_env_step"].values())
    # Ratios against the loop's stream, paired by round.
    assert (
        set(summary["ratio_by_stream"]) == {"random", "sine"}
        and summary["ratio"] == summary["ratio_by_stream"]["random"]
    )
    assert set(summary["per_task_ms_per_env_step"]) == {"libero_10/0", "libero_10/1"}
    assert summary["setup"]["actions"] == 4 and summary["reset_s_per_env"] > 0
    record = json.loads((tmp_path / "out" / "bench" / "bench_action_cost_quick.json").read_text())
    assert len(record["details"]["per_round"]["random"]) == 1


@pytest.mark.timeout(60)
def test_a_core_this_process_may_not_run_on_is_refused_naming_the_option(tmp_path):
    done = run_bench_script(tmp_path, "bench_action_cost.py", "--quick", "--cpu", "4096", timeout=50)
    assert done.returncode == 2 and "--cpu 4096" in done.stderr and "RESULT" not in done.stdout
