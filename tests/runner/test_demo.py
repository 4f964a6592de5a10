"""The README's first command: ``vecsim demo`` starts a job, rolls out, reports, and cleans up."""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import sys
import time
import uuid
from collections import Counter
from pathlib import Path

import psutil
import pytest
from support import ROOT


def run_demo(out: Path, *args: str) -> tuple[subprocess.CompletedProcess[str], str]:
    """Run ``vecsim demo`` with a marker in its environment, which every process it starts
    inherits: the test then finds its own processes, whatever else runs on the machine."""
    marker = uuid.uuid4().hex
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"), MARK: marker}
    env.pop("VECSIM_TOKEN", None)
    done = subprocess.run(
        [sys.executable, "-m", "service.cli", "demo", "--out", str(out), *args],
        cwd=out.parent,
        env=env,
        capture_output=True,
        text=True,
        timeout=380,
    )
    return done, marker


MARK = "VECSIM_TEST_DEMO_RUN"


@pytest.mark.slow
@pytest.mark.timeout(400)
def test_the_demo_rolls_out_on_a_local_job_writes_its_pictures_and_leaves_nothing_running(tmp_path: Path) -> None:
    out = tmp_path / "demo"
    done, marker = run_demo(out, "--horizon", "4", "--videos", "1", "--ready-timeout", "300")
    assert done.returncode == 0, done.stderr[-3000:]
    # Run outside the checkout: the default job ships inside the package. The warm-up shows.
    assert "warming up" in done.stderr and "sim-0" in done.stderr

    assert "env-steps/s" in done.stdout and "policy time overlapped" in done.stdout
    summary = json.loads((out / "summary.json").read_text())
    # The defaults: a batch of one request per env (tiny: 2 pods x 6 envs), two batches at once,
    # so each env runs two trajectories, the second refilled when the first ends.
    assert summary["stats"]["num_trajectories"] == 24
    assert summary["stats"]["env_steps"] == 24 * 4
    assert summary["lost"] == {}
    routes = summary["routes"]
    assert {r["stage_id"] for r in routes.values()} == {0, 1}
    envs = Counter((r["pod"], r["env_index"]) for r in routes.values())
    assert len(envs) == 12 and set(envs.values()) == {2}
    assert (out / "timeline.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # The first step against the median, per pod: each pod stepped its envs 4 times a trajectory.
    costs = summary["step_costs"]
    assert {p["pod"] for p in costs["per_pod"]} == {r["pod"] for r in routes.values()}
    assert all(p["calls"] == 2 * 4 for p in costs["per_pod"])
    assert costs["first_over_median"] == max(p["ratio"] for p in costs["per_pod"])
    assert "first step / median step" in done.stdout
    assert summary["policy_warmup_s"] > 0
    (video,) = summary["videos"].values()
    assert Path(video).stat().st_size > 0
    assert _processes_marked(marker) == [], "the demo left processes running"


@pytest.mark.slow
@pytest.mark.timeout(400)
def test_the_demo_says_so_and_exits_non_zero_when_it_loses_trajectories(tmp_path: Path) -> None:
    # Once the rollout starts, every pod is stopped (SIGSTOP) for longer than the client's
    # timeout: every trajectory is lost. The pods are let go again afterwards, so the demo can
    # shut them down.
    out = tmp_path / "demo"
    marker = uuid.uuid4().hex
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"), MARK: marker}
    env.pop("VECSIM_TOKEN", None)
    command = [
        sys.executable,
        "-m",
        "service.cli",
        "demo",
        "--out",
        str(out),
        "--batch",
        "4",
        "--horizon",
        "50",
        "--videos",
        "0",
        "--timeout-s",
        "8",
        "--ready-timeout",
        "300",
    ]
    demo = subprocess.Popen(command, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    stopped: list[psutil.Process] = []
    try:
        assert demo.stderr is not None
        for line in demo.stderr:  # bounded: the demo ends, and the test's timeout bounds it
            if "rolling out" in line:
                stopped = [p for p in _marked(marker) if "service.cli pod" in " ".join(p.cmdline())]
                for pod in stopped:
                    pod.suspend()
                break
        assert stopped, "the demo never started its rollout"
        time.sleep(12)  # not synchronisation: how long the pods stay stopped, past the 8 s timeout
    finally:
        for pod in stopped:
            with contextlib.suppress(psutil.NoSuchProcess):
                pod.resume()
    stdout, stderr = demo.communicate(timeout=300)
    assert demo.returncode == 1, (stdout[-2000:], stderr[-3000:])
    # Two batches of 4 (the default --waves 2), all on envs at once: every one of the 8 is lost.
    assert "FAILED: 8 of 8 trajectories were lost" in stdout
    summary = json.loads((out / "summary.json").read_text())
    assert len(summary["lost"]) == 8
    assert all("TimeoutError" in lost["reason"] for lost in summary["lost"].values()), summary["lost"]
    assert _processes_marked(marker) == [], "the demo left processes running"


def _marked(marker: str) -> list[psutil.Process]:
    """Live processes whose environment carries ``marker`` (a demo and everything it started:
    controller, pods, their env workers), found whatever else runs on the machine."""
    found = []
    for proc in psutil.process_iter(["status"]):
        try:
            if proc.info["status"] != psutil.STATUS_ZOMBIE and proc.environ().get(MARK) == marker:
                found.append(proc)
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            continue
    return found


def test_the_packaged_default_job_is_configs_tiny():
    from service.demo import DEFAULT_CONFIG
    from vecsim.config import load_job_config

    assert load_job_config(DEFAULT_CONFIG) == load_job_config(ROOT / "configs" / "tiny.yaml")


def _processes_marked(marker: str) -> list[str]:
    """Command lines of the live processes :func:`_marked` finds."""
    found = []
    for proc in _marked(marker):
        with contextlib.suppress(psutil.NoSuchProcess):
            found.append(" ".join(proc.cmdline()))
    return found


def test_step_costs_compare_each_pods_first_stepping_call_with_its_median_and_skip_resets() -> None:
    from service.demo import step_costs

    # (stage_id, pod, begin_s, end_s, resets, steps): sim-0's reset-only call is no step; its
    # first step took 1.5 s against a median of 0.5 s; sim-1 stepped once after a mixed call.
    calls = [
        (0, "sim-0", 0.0, 3.0, 2, 0),
        (0, "sim-0", 3.0, 4.5, 0, 2),
        (1, "sim-1", 0.0, 0.4, 1, 1),
        (0, "sim-0", 4.6, 5.1, 0, 2),
        (0, "sim-0", 5.2, 5.6, 0, 2),
        (0, "sim-0", 5.7, 6.3, 0, 2),
    ]
    costs = step_costs(calls)
    by_pod = {p["pod"]: p for p in costs["per_pod"]}
    assert by_pod["sim-0"]["calls"] == 4
    assert by_pod["sim-0"]["first_s"] == pytest.approx(1.5)
    assert by_pod["sim-0"]["median_s"] == pytest.approx(0.55)
    assert by_pod["sim-1"]["ratio"] == pytest.approx(1.0)
    assert costs["first_over_median"] == pytest.approx(1.5 / 0.55)
    assert step_costs([(0, "sim-0", 0.0, 1.0, 3, 0)]) == {"first_over_median": None, "per_pod": []}
