"""The serving benchmarks of docs/benchmarks.md keep working: each runs with ``--quick``
and prints one ``RESULT {json}`` line with the fields the benchmark table is built from.

Each benchmark runs as a real script, as a person would run it, from a copy of ``bench/`` in a
temporary directory, so that its JSON lands there and not over the recorded results in
``out/bench``. No timing is asserted: the figures depend on the machine and its load.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from support.bench_scripts import bench_env, bench_result

# A benchmark script run end to end, with its own pods: 20-60 s a run on 2 cores.
pytestmark = pytest.mark.slow

COMMON_FIELDS = {"name", "command", "machine", "baseline", "ratio", "target", "met", "quick"}


def run_quick(script: str, tmp_path: Path, *args: str) -> tuple[dict[str, Any], Path]:
    """Run ``bench/<script> --quick [args]`` from a copy of bench/ (with the caller's
    ``PYTHONPATH``); return its RESULT and its JSON file."""
    result = bench_result(tmp_path, script, "--quick", *args, timeout=280, env=bench_env(repo_on_path=False))
    return result, tmp_path / "out" / "bench" / f"{result['name']}.json"


def assert_common(result: dict[str, Any], name: str, written: Path) -> None:
    assert COMMON_FIELDS <= set(result), f"missing {COMMON_FIELDS - set(result)}"
    assert result["name"] == name and result["quick"] is True
    assert isinstance(result["ratio"], float) and result["ratio"] > 0
    assert isinstance(result["met"], bool)
    assert {"date", "cores", "load_avg_1m"} <= set(result["machine"])
    assert json.loads(written.read_text())["name"] == name


@pytest.mark.timeout(300)
def test_serving_benchmark_reports_http_against_in_process(tmp_path: Path) -> None:
    result, written = run_quick("bench_serving.py", tmp_path)
    assert_common(result, "bench_serving", written)
    cheap = result["cheap"]
    assert set(cheap["env_steps_per_s"]) == {"http", "inproc"}
    assert cheap["ratio_http_vs_inproc"]["n"] == 2
    assert cheap["peak_rss_mib_per_env"]["pod"] > 0 and cheap["peak_rss_mib_per_env"]["inproc"] > 0


@pytest.mark.timeout(300)
def test_pipeline_benchmark_reports_each_stage_count_against_one(tmp_path: Path) -> None:
    result, written = run_quick("bench_pipeline.py", tmp_path)
    assert_common(result, "bench_pipeline", written)
    assert set(result["speedup_vs_1_stage"]) == {"1", "2", "4"}
    assert result["speedup_vs_1_stage"]["1"]["median"] == 1.0
    assert result["setup"]["forward_ms"] > 0 and result["setup"]["stage_sim_ms"] > 0


@pytest.mark.timeout(300)
def test_scaling_benchmark_reports_a_fraction_of_linear_per_pod_count(tmp_path: Path) -> None:
    result, written = run_quick("bench_scaling.py", tmp_path)
    assert_common(result, "bench_scaling", written)
    fractions = result["cheap"]["fraction_of_linear"]
    assert fractions["1"]["median"] == 1.0
    assert str(result["pods"]) in fractions


@pytest.mark.timeout(300)
def test_control_plane_benchmark_reports_heartbeat_p99_and_replan_time(tmp_path: Path) -> None:
    result, written = run_quick("bench_control_plane.py", tmp_path)
    assert_common(result, "bench_control_plane", written)
    assert result["heartbeat_p99_ms"] > 0 and result["baseline_heartbeat_p99_ms"] > 0
    assert result["replan_s"] is not None and result["baseline_replan_s"] is not None
    for runs in result["runs"].values():
        assert all(run["error_count"] == 0 and run["heartbeats_in_window"] > 0 for run in runs)


@pytest.mark.timeout(300)
def test_cheap_scenes_benchmark_reports_the_pod_against_async_vector_env(tmp_path: Path) -> None:
    result, written = run_quick("bench_cheap_scenes.py", tmp_path)
    assert_common(result, "bench_cheap_scenes", written)
    cheap = result["cheap"]["4"]
    assert set(cheap["env_steps_per_s"]) == {"async", "pod_auto", "pod_1", "sync"}
    assert cheap["auto_envs_per_worker"] >= 1


@pytest.mark.timeout(300)
def test_profile_call_reports_every_layer_of_one_step(tmp_path: Path) -> None:
    result, written = run_quick("profile_call.py", tmp_path)
    assert result["name"] == "profile_call" and result["quick"] is True
    medians = result["median_ms_per_call"]
    assert set(medians) >= {
        "http_vector_env",
        "raw_httpx",
        "bare_http_client",
        "in_process",
        "async_vector_env",
        "sync_vector_env",
    }
    assert all(ms > 0 for ms in medians.values())
    # The timers inside the client and inside the pod both saw the calls.
    assert result["client_layers_median_ms"]["client.PodConnection._request (HTTP round trip via transport)"] > 0
    assert result["pod_layers_median_ms"]["calls"] > 0
    assert result["pod_layers_median_ms"]["median_ms"]["pod.step_envs"] > 0
    details = json.loads(written.read_text())["details"]
    assert details["pod_profile"]["main_thread_top"] and details["client_profile"]["loop_thread_top"]


@pytest.mark.timeout(300)
def test_refill_benchmark_reports_refill_against_batch_at_once_over_the_same_steps(tmp_path: Path) -> None:
    # In chunks of 4 actions per env and policy call, cut to each trajectory's own horizon.
    result, written = run_quick("bench_refill.py", tmp_path, "--chunk", "4")
    assert_common(result, "bench_refill", written)
    assert result["setup"]["chunk"] == 4
    assert set(result["env_steps_per_s"]) == {"refill", "batch"}
    assert result["ratio_refill_vs_batch"]["n"] == result["setup"]["rounds"]
    steps = result["setup"]["env_steps_per_run"]
    assert result["env_steps_median"] == {"refill": steps, "batch": steps}
    low, _mean, high = result["setup"]["horizons_min_mean_max"]
    assert low < high == result["setup"]["horizon"]
    # The trainer's CPU seconds per wall second says whether it, not the pods, bounds the rollout.
    assert set(result["trainer_cpu_per_wall_s"]) == {"refill", "batch"}
    assert result["trainer_cpu_per_wall_s"]["refill"]["median"] > 0
    # Where a pod's call goes: the client's view against the pods' own /metrics.
    for name in ("refill", "batch"):
        split = result["call_split_ms"][name]
        assert split["in_flight"] > 0 and split["pod_step"] > 0
        assert split["physics"] > 0 and split["turnaround"] > 0
