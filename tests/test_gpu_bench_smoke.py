"""The GPU-machine benchmark keeps working here: ``bench/bench_gpu_scale.py --cpu-small`` on a
cheap gym scene runs a real job (controller, a pinned pod, a standalone extra pod), the vision
policy through the pipelined EnvLoop, and the software-rendering pod, and prints one
``RESULT {json}`` line with every figure docs/benchmarks.md's GPU section is built from.

It runs as a person would run it, from a copy of ``bench/`` in a temporary directory (so that its
JSON and plots land there, not over the recorded ones), with the repository on ``PYTHONPATH``.
No timing is asserted: the figures depend on the machine and its load.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

REPO = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def result(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict[str, Any], Path]:
    root = tmp_path_factory.mktemp("gpu-bench")
    shutil.copytree(REPO / "bench", root / "bench", ignore=shutil.ignore_patterns("__pycache__"))
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"), "PYTHONPATH": str(REPO)}
    env.pop("VECSIM_TOKEN", None)
    done = subprocess.run(
        [sys.executable, str(root / "bench" / "bench_gpu_scale.py"), "--cpu-small", "--tasks", "gym/HalfCheetah-v5",
         "--size", "16", "--horizon", "3", "--rounds", "1", "--no-heavy"],
        cwd=root, env=env, capture_output=True, text=True, timeout=170,
    )  # fmt: skip
    assert done.returncode == 0, f"bench_gpu_scale.py failed:\n{done.stderr[-3000:]}"
    lines = [line for line in done.stdout.splitlines() if line.startswith("RESULT ")]
    assert len(lines) == 1, f"printed {len(lines)} RESULT lines:\n{done.stdout[-2000:]}"
    return json.loads(lines[0].removeprefix("RESULT ")), root


@pytest.mark.timeout(180)
def test_the_result_names_its_targets_and_the_machine(result):
    summary, root = result
    assert summary["name"] == "bench_gpu_scale_cpu" and summary["quick"] is True and summary["dry"] is False
    assert isinstance(summary["ratio"], float) and summary["ratio"] > 0
    assert isinstance(summary["ratio_pipelining"], float) and summary["ratio_pipelining"] > 0
    assert set(summary["met"]) == {"scaling", "pipelining", "pipelining_heavy_policy"}
    assert {"date", "cores", "load_avg_1m"} <= set(summary["machine"])
    assert json.loads((root / "out" / "bench" / "bench_gpu_scale_cpu.json").read_text())["name"] == summary["name"]


@pytest.mark.timeout(180)
def test_scaling_covers_every_pod_count_with_a_pinned_job_pod_and_an_extra_pod(result):
    summary, _ = result
    assert set(summary["scaling"]["env_steps_per_s"]) == {"pods=1", "pods=2"}
    assert all(v["median"] > 0 for v in summary["scaling"]["env_steps_per_s"].values())
    assert summary["setup"]["extra_standalone_pods"] == ["sim-1"]
    assert len(summary["setup"]["pods_pinned_to"]) == 2


@pytest.mark.timeout(180)
def test_the_time_split_has_policy_physics_render_and_serving(result):
    summary, _ = result
    split = summary["scaling"]["time_split_ms"]["pods=2"]
    assert split["policy_ms"] > 0 and split["physics_ms_per_pod"] > 0 and split["render_ms_per_pod"] > 0
    assert split["serving_ms"] >= 0 and split["pods_per_call"] == 2


@pytest.mark.timeout(180)
def test_pipelining_compares_one_and_two_stages_with_the_vision_policy(result):
    summary, _ = result
    assert set(summary["stages"]["env_steps_per_s"]) == {"stages=1", "stages=2"}
    assert summary["policy"]["name"].startswith("ResNet-18") and summary["policy"]["parameters_m"] > 10


@pytest.mark.timeout(180)
def test_rendering_reports_the_gl_renderer_and_the_software_pod(result):
    summary, root = result
    assert summary["gl"]["backend"] == "egl" and summary["gl"]["renderer"]
    software = summary["software_rendering"]
    assert ("env_steps_per_s" in software) == summary["mesa_egl"]["present"], software
    assert {Path(p).name for p in summary["plots"]} == {
        "gpu_scale_cpu_pods.png", "gpu_scale_cpu_stages.png", "gpu_scale_cpu_split.png",
    }  # fmt: skip
    assert all((root / p).is_file() for p in summary["plots"])
