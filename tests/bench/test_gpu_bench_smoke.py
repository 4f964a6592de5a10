"""The GPU-machine benchmark keeps working here. ``bench/bench_gpu_scale.py --cpu-small`` on a
cheap gym scene runs each of its two measurements as a person would run them: a real job
(controller, pinned pods that all serve the same task mix), the service alone and the EnvLoop
with a vision policy, and prints one ``RESULT {json}`` line with every figure docs/benchmarks.md's
GPU section is built from.

- ``--only scaling``: env-steps/s against pods, the service alone and the loop, the fraction of
  linear, the slowest pod's round trip against the mean, the CPU topology and memory.
- ``--only pipeline``: two pods pinned to one core, 1 stage against 2 stages, with a ViT policy
  calibrated to the 1-stage simulation call.

It runs from a copy of ``bench/`` in a temporary directory (so that its JSON and plots land
there, not over the recorded ones), with the repository on ``PYTHONPATH``. No timing is asserted:
the figures depend on the machine and its load.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path
from typing import Any

import pytest
from support.bench_scripts import bench_env, bench_result, result_of, run_bench_script

GYM = ["--tasks", "gym/HalfCheetah-v5", "--envs-per-task", "2", "--size", "16", "--horizon", "3", "--rounds", "1"]


def run_bench(root: Path, *args: str, timeout: float = 170) -> subprocess.CompletedProcess[str]:
    """``bench_gpu_scale.py args`` from a copy of bench/ in ``root``; its return code unchecked."""
    return run_bench_script(root, "bench_gpu_scale.py", *args, timeout=timeout)


@pytest.fixture(scope="module")
def scaling(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict[str, Any], Path]:
    root = tmp_path_factory.mktemp("gpu-bench-scaling")
    return result_of(run_bench(root, "--cpu-small", "--only", "scaling", *GYM)), root


@pytest.fixture(scope="module")
def pipeline(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict[str, Any], Path]:
    root = tmp_path_factory.mktemp("gpu-bench-pipeline")
    args = (
        "--cpu-small",
        "--only",
        "pipeline",
        "--render-preset",
        "fast",
        "--render-gpu",
        "0",
        "--compare-batch-wait-s",
        "0.01,300",
        *GYM,
    )
    return result_of(run_bench(root, *args)), root


@pytest.mark.timeout(180)
@pytest.mark.slow
def test_scaling_names_its_target_the_machine_and_its_record(scaling):
    summary, root = scaling
    assert summary["name"] == "bench_gpu_scale_scaling_cpu" and summary["quick"] is True and summary["dry"] is False
    assert isinstance(summary["ratio"], float) and isinstance(summary["ratio_loop"], float)
    assert set(summary["met"]) == {"scaling_service", "scaling_loop", "scaling_loop_stage_per_pod"}
    assert isinstance(summary["ratio_loop_stage_per_pod"], float)
    assert {"date", "cores", "load_avg_1m"} <= set(summary["machine"])
    record = json.loads((root / "out" / "bench" / "bench_gpu_scale_scaling_cpu.json").read_text())
    assert record["name"] == summary["name"] and set(record["details"]["per_round"]) == {
        "service/pods=1",
        "service/pods=2",
        "loop/pods=1",
        "loop/pods=2",
        "loop_per_pod/pods=1",
        "loop_per_pod/pods=2",
    }


@pytest.mark.timeout(180)
@pytest.mark.slow
def test_scaling_measures_the_service_alone_and_the_loop_at_every_pod_count(scaling):
    summary, _ = scaling
    for kind in ("service", "loop", "loop_per_pod"):
        assert set(summary[kind]) == {"pods=1", "pods=2"}
        for figures in summary[kind].values():
            assert figures["env_steps_per_s"]["median"] > 0
            assert figures["fraction_of_linear"]["n"] == 1
    assert summary["service"]["pods=2"]["time_split_ms"]["policy_ms"] == 0
    assert summary["loop"]["pods=2"]["time_split_ms"]["policy_ms"] > 0
    # EnvLoop calls each pod on its own (no lockstep: issue 27), whether a stage holds one pod or two.
    assert summary["loop"]["pods=2"]["time_split_ms"]["pods_per_call"] == 1
    assert summary["loop_per_pod"]["pods=2"]["time_split_ms"]["pods_per_call"] == 1
    assert summary["policy"]["name"].startswith("ResNet-18")


@pytest.mark.timeout(180)
@pytest.mark.slow
def test_scaling_records_the_slowest_pod_next_to_the_mean(scaling):
    summary, _ = scaling
    slowest = summary["service"]["pods=2"]["slowest_pod"]
    assert slowest["calls"] == 3  # the service rollout's three steps
    assert slowest["pod_round_trip_slowest_ms"] >= slowest["pod_round_trip_mean_ms"] > 0
    assert slowest["wait_for_slowest_ms"] >= 0
    assert set(slowest["pod_step_ms_by_pod"]) == {"sim-0", "sim-1"}
    assert sum(slowest["slowest_pod_counts"].values()) == 3


@pytest.mark.timeout(180)
@pytest.mark.slow
def test_scaling_records_the_cpu_topology_pins_memory_and_every_pods_task_mix(scaling):
    summary, root = scaling
    topology, setup = summary["topology"], summary["setup"]
    assert topology["cpus"] >= 1 and topology["physical_cores"] >= 1 and topology["threads_per_core"] >= 1
    assert len(setup["pods_pinned_to"]) == 2 and len(setup["pods_physical_cores"]) == 2
    assert set(setup["pod_tasks"]) == {"sim-0", "sim-1"}
    assert all(tasks == ["gym/HalfCheetah-v5 x2"] for tasks in setup["pod_tasks"].values())
    assert setup["memory_used_gib_at_ready"] > 0 and setup["memory_used_gib_peak"] > 0
    assert all(pod["processes"] >= 2 for pod in setup["pod_processes"].values())
    assert {Path(p).name for p in summary["plots"]} == {"gpu_scale_cpu_pods.png", "gpu_scale_cpu_split.png"}
    assert all((root / p).is_file() for p in summary["plots"])


@pytest.mark.timeout(180)
@pytest.mark.slow
def test_pipeline_pins_both_stages_pods_to_one_core_and_compares_one_and_two_stages(pipeline):
    summary, root = pipeline
    assert summary["name"] == "bench_gpu_scale_pipeline_cpu" and isinstance(summary["ratio"], float)
    assert set(summary["met"]) == {"pipelining_slices", "pipelining_pods"}
    setup = summary["setup"]
    assert setup["pods"] == 2 and len(set(setup["pods_pinned_to"])) == 1
    # Each 2-stage layout also ran waiting 10 ms for more of a stage's pods, and waiting for all of
    # them (--compare-batch-wait-s 0.01,300).
    waits = [f"{layout}/stages=2/batch_wait={wait}" for wait in ("0.01s", "300s") for layout in ("slices", "pods")]
    assert set(summary["loop"]) == {"stages=1", "stages=1/lockstep", "slices/stages=2", "pods/stages=2", *waits}
    assert all(run["env_steps_per_s"]["median"] > 0 for run in summary["loop"].values())
    assert [entry["batch_wait_s"] for entry in summary["batch_wait"]] == [0.01, 300]
    assert summary["setup"]["compare_batch_wait_s"] == [0.01, 300]
    for entry in summary["batch_wait"]:
        assert {layout: r["n"] for layout, r in entry["speedup_over_same_layout"].items()} == {"slices": 1, "pods": 1}
        assert {layout: r["n"] for layout, r in entry["speedup_2_vs_1_lockstep"].items()} == {"slices": 1, "pods": 1}
    # Waiting for every pod of the stage: each policy call takes the whole stage, an env of each pod.
    waited = summary["loop"]["slices/stages=2/batch_wait=300s"]["time_split_ms"]
    assert waited["env_steps_per_policy_call"] == 2 * setup["chunk"]
    assert {layout: r["n"] for layout, r in summary["speedup_2_vs_1"].items()} == {"slices": 1, "pods": 1}
    # Also against one stage in lockstep: the whole stage's answers before every policy call.
    assert {layout: r["n"] for layout, r in summary["speedup_2_vs_1_lockstep"].items()} == {"slices": 1, "pods": 1}
    assert set(summary["ratio_over_lockstep_by_layout"]) == {"slices", "pods"}
    assert summary["ratio"] == summary["ratio_by_layout"]["slices"]
    # pods: a stage is one pod; slices: every pod holds half its envs on each stage.
    assert setup["stage_envs_by_layout"] == {"pods": [[2], [2]], "slices": [[1, 1], [1, 1]]}
    assert summary["loop"]["pods/stages=2"]["time_split_ms"]["pods_per_call"] == 1
    assert summary["loop"]["slices/stages=2"]["time_split_ms"]["pods_per_call"] == 1
    # In lockstep every policy call takes the whole stage: its 4 envs, K actions each.
    assert summary["loop"]["stages=1/lockstep"]["time_split_ms"]["env_steps_per_policy_call"] == 4 * setup["chunk"]
    # Both pods share one core: in one stage in lockstep they are always called together.
    assert all(0.0 <= run["core_overlap"] <= 1.0 for run in summary["loop"].values())
    assert summary["loop"]["stages=1/lockstep"]["core_overlap"] > 0.5
    # The trainer's thread: policy, waiting for pods and the rest of the loop make up its wall time.
    for run in summary["loop"].values():
        share = run["thread_share"]
        assert set(share) == {"policy", "wait", "loop"} and share["policy"] > 0
        assert 0.99 <= sum(share.values()) <= 1.01
    # The trainer's side of each stage's turn (sending, the client's own part of a call, taking
    # the last answer to the policy): every figure measured.
    for run in summary["loop"].values():
        split = run["handoff_ms"]
        assert set(split) == {
            "send",
            "send_spread",
            "call_beyond_request",
            "last_answer_to_policy",
            "last_answer_to_policy_idle",
        }
        assert all(value is not None and value >= 0 for value in split.values()), split
    assert {Path(p).name for p in summary["plots"]} == {"gpu_scale_cpu_stages.png"}
    assert all((root / p).is_file() for p in summary["plots"])


@pytest.mark.timeout(180)
@pytest.mark.slow
def test_pipeline_calibrates_a_vit_to_the_one_stage_simulation_call(pipeline):
    summary, _ = pipeline
    service, policy = summary["service"], summary["policy"]
    assert set(service) == {"stages=1", "half"}
    assert policy["target_ms"] == service["stages=1"]["time_split_ms"]["stage_call_ms"] > 0
    assert policy["name"].startswith("ViT") and 1 <= policy["depth"] <= summary["setup"]["vit_max_depth"]
    assert policy["capped"] == (policy["depth_wanted"] > summary["setup"]["vit_max_depth"])
    assert policy["target_batch"] == 4 and set(policy["forward_ms"]) == {"2", "4"}
    assert policy["chunk"] == 1


@pytest.mark.timeout(180)
@pytest.mark.slow
def test_pipeline_records_the_pods_render_preset_and_render_gpu(pipeline):
    summary, _ = pipeline
    setup = summary["setup"]
    assert setup["render_preset"] == "fast" and setup["render_gpu"] == 0
    assert "gpu_processes_at_ready" in setup  # nvidia-smi's process table; None without nvidia-smi


@pytest.mark.timeout(120)
def test_physics_scaling_reports_each_process_count_against_linear(tmp_path):
    # This process's environment as it is, but for the repository on PYTHONPATH.
    env = bench_env(default_mujoco_gl=None, drop=())
    args = ["--procs", "1,2", "--tasks", "gym/HalfCheetah-v5,gym/Hopper-v5", "--seconds", "0.3", "--rounds", "1"]
    summary = bench_result(tmp_path, "bench_physics_scaling.py", *args, timeout=100, env=env)
    assert summary["name"] == "bench_physics_scaling" and summary["setup"]["envs_per_process"] == 2
    assert set(summary["rows"]) == {"1", "2"} and summary["rows"]["1"]["ratio_to_linear"] == 1.0
    row = summary["rows"]["2"]
    assert row["per_process_min"] <= row["per_process_mean"] <= row["per_process_max"]
    assert summary["ratio"] == row["ratio_to_linear"] > 0
    assert (tmp_path / "out" / "bench" / "bench_physics_scaling.json").is_file()


@pytest.mark.timeout(60)
def test_a_run_without_only_is_refused_naming_the_option(tmp_path):
    done = run_bench(tmp_path, "--cpu-small", *GYM, timeout=50)
    assert done.returncode == 2 and "--only" in done.stderr


@pytest.mark.timeout(60)
def test_gpu_mode_fails_at_once_where_torch_sees_no_gpu(tmp_path):
    import torch

    if torch.cuda.is_available():
        pytest.skip("this machine has a CUDA device")
    done = run_bench(tmp_path, "--gpu", "--only", "pipeline", "--chunk", "8", *GYM, timeout=50)
    assert done.returncode == 2 and "--gpu: torch sees no CUDA device" in done.stderr
    assert "RESULT" not in done.stdout and "starting" not in done.stderr  # no job was started


@pytest.mark.timeout(150)
def test_quick_pipeline_compares_both_layouts_at_a_chunk_of_k(tmp_path):
    done = run_bench(tmp_path, "--quick", "--chunk", "4", "--rounds", "1", timeout=140)
    summary = result_of(done)
    assert summary["name"] == "bench_gpu_scale_pipeline_quick" and summary["setup"]["chunk"] == 4
    assert set(summary["loop"]) == {"stages=1", "stages=1/lockstep", "slices/stages=2", "pods/stages=2"}
    assert set(summary["ratio_by_layout"]) == {"slices", "pods"} and summary["target"].endswith("at K=4")
    # The horizon counts actions: a chunk of K takes K of them per call.
    assert summary["setup"]["horizon"] % 4 == 0
    assert (tmp_path / "out" / "bench" / "bench_gpu_scale_pipeline_quick.json").is_file()


@pytest.mark.timeout(60)
@pytest.mark.parametrize(
    "flag, value",
    [
        ("--batch-wait-s", "-1"),
        ("--compare-batch-wait-s", "0.03,nan"),
        ("--compare-batch-wait-s", "30ms"),
        ("--compare-batch-wait-s", "0.03,0.030"),
    ],
)
def test_a_batch_wait_that_is_not_a_duration_is_refused_naming_the_option(tmp_path, flag, value):
    done = run_bench(tmp_path, "--quick", flag, value, timeout=50)
    assert done.returncode == 2 and flag in done.stderr and "RESULT" not in done.stdout


@pytest.mark.timeout(60)
def test_an_unknown_stage_layout_is_refused_naming_the_option(tmp_path):
    done = run_bench(tmp_path, "--quick", "--stage-layout", "slices,rows", timeout=50)
    assert done.returncode != 0 and "--stage-layout" in done.stderr


@pytest.mark.timeout(180)
@pytest.mark.slow
def test_pipeline_with_a_pod_a_core_splits_each_pod_between_the_stages(tmp_path):
    args = (
        "--cpu-small",
        "--only",
        "pipeline",
        "--render-preset",
        "fast",
        "--pods-per-core",
        "1",
        "--pipeline-cores",
        "2",
        "--stage-layout",
        "slices",
        "--compare-batch-wait-s",
        "300",
        *GYM,
    )
    summary = result_of(run_bench(tmp_path, *args))
    setup = summary["setup"]
    assert setup["pods"] == 2 and setup["pipeline_cores"] == 2 and setup["pods_per_core"] == 1
    # Each pod's two envs: one on each stage.
    assert setup["stage_envs_by_layout"] == {"slices": [[1, 1], [1, 1]]}
    assert set(summary["loop"]) == {
        "stages=1",
        "stages=1/lockstep",
        "slices/stages=2",
        "slices/stages=2/batch_wait=300s",
    }
    # No two pods share a core, so none ever simulates beside another of its core.
    assert all(run["core_overlap"] == 0.0 for run in summary["loop"].values())
    # Waiting for the whole stage: each policy call takes an env of each pod, K actions each.
    waited = summary["loop"]["slices/stages=2/batch_wait=300s"]["time_split_ms"]
    assert waited["env_steps_per_policy_call"] == 2 * setup["chunk"]


@pytest.mark.timeout(180)
@pytest.mark.slow
def test_pipeline_also_runs_slices_in_three_stages_each_stage_a_third_of_every_pod(tmp_path):
    gym = [*GYM[:2], "--envs-per-task", "3", *GYM[4:]]
    args = (
        "--cpu-small",
        "--only",
        "pipeline",
        "--render-preset",
        "fast",
        "--pods-per-core",
        "1",
        "--pipeline-cores",
        "2",
        "--stage-layout",
        "slices",
        "--batch-wait-s",
        "300",
        "--compare-stages",
        "3",
        *gym,
    )
    summary = result_of(run_bench(tmp_path, *args))
    setup = summary["setup"]
    assert setup["compare_stages"] == [3]
    # Six envs, the k-th on stage k % 3: two a stage, one of each pod.
    assert setup["stage_envs_by_layout"]["slices/stages=3"] == [[1, 1], [1, 1], [1, 1]]
    assert set(summary["loop"]) == {"stages=1", "stages=1/lockstep", "slices/stages=2", "slices/stages=3"}
    assert set(summary["speedup_over_lockstep"]) == {"stages=1", "slices/stages=2", "slices/stages=3"}
    # Waiting for the whole stage: a policy call takes a stage's two envs, K actions each.
    waited = summary["loop"]["slices/stages=3"]["time_split_ms"]
    assert waited["env_steps_per_policy_call"] == 2 * setup["chunk"]
    assert summary["loop"]["slices/stages=3"]["trajectories"] == 6


@pytest.mark.timeout(60)
@pytest.mark.parametrize(
    "extra",
    [
        ("--compare-stages", "2"),
        ("--compare-stages", "3,x"),
        ("--compare-stages", "3", "--stage-layout", "pods"),
        ("--compare-stages", "5"),
    ],
)
def test_more_stages_the_pipeline_cannot_run_are_refused_naming_the_option(tmp_path, extra):
    done = run_bench(tmp_path, "--quick", *extra, timeout=50)
    # 5: the quick job's envs do not split into five equal stages.
    assert done.returncode in (1, 2) and "--compare-stages" in done.stderr and "RESULT" not in done.stdout


@pytest.mark.timeout(60)
@pytest.mark.parametrize(
    "extra", [("--pods-per-core", "3"), ("--pods-per-core", "0"), ("--pods-per-core", "1", "--pipeline-cores", "1")]
)
def test_a_pods_per_core_the_pipeline_cannot_lay_out_is_refused_naming_the_option(tmp_path, extra):
    done = run_bench(tmp_path, "--quick", *extra, timeout=50)
    assert done.returncode != 0 and "--pods-per-core" in done.stderr and "RESULT" not in done.stdout
