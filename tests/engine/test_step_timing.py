"""Where a pod's step time goes: ``TaskGroupedVectorEnv.last_timing`` (worker seconds in physics
and in rendering, summed over the workers) and the pod's counters of them in ``/metrics``."""

from __future__ import annotations

import httpx
import numpy as np
import pytest
from support.service_procs import PodSpec, assignment

from vecsim import wire
from vecsim.config import Assignment, CameraConfig
from vecsim.engine import CallTiming, TaskGroupedVectorEnv

CHEETAH = "gym/HalfCheetah-v5"


def cheetahs(camera: CameraConfig, envs: int = 2) -> Assignment:
    return assignment("sim-0", [(CHEETAH, envs)], camera=camera, envs_per_worker=1, max_episode_steps=100)


def zeros(n: int) -> np.ndarray:
    return np.zeros((n, 6), np.float32)


def test_a_step_with_cameras_reports_physics_and_render_seconds():
    with TaskGroupedVectorEnv(cheetahs(CameraConfig(names=("render",), height=16, width=16))) as env:
        assert env.last_timing == CallTiming()  # nothing called yet
        env.step_envs([0, 1], zeros(2))
        assert env.last_timing.physics_s > 0 and env.last_timing.render_s > 0


@pytest.fixture
def pod_url(start_pods) -> str:
    """A standalone pod of two HalfCheetahs with a 16x16 camera; stopped at the end."""
    camera = CameraConfig(names=("render",), height=16, width=16)
    (pod,) = start_pods([PodSpec("sim-0", 0, [(CHEETAH, 2)], camera=camera, max_episode_steps=100, render=None)])
    return pod.url


def counter(url: str, name: str) -> float:
    for line in httpx.get(f"{url}/metrics", timeout=5).text.splitlines():
        if line.startswith(name + " "):
            return float(line.split()[1])
    raise AssertionError(f"{name} not in {url}/metrics")


@pytest.mark.timeout(120)
@pytest.mark.slow
def test_the_pod_counts_physics_and_render_seconds_of_its_steps(pod_url):
    names = ("vecsim_pod_physics_seconds_total", "vecsim_pod_render_seconds_total")
    before = {name: counter(pod_url, name) for name in names}
    body = wire.encode({"generation": 0, "env_indices": np.array([0, 1]), "actions": zeros(2)})
    response = httpx.post(f"{pod_url}/v1/step", content=body, headers={"Content-Type": wire.CONTENT_TYPE}, timeout=30)
    assert response.status_code == 200
    for name, value in before.items():
        assert counter(pod_url, name) > value, name
    # A CPU pod shares no GPU: it never waits for a turn at one.
    assert counter(pod_url, "vecsim_pod_gpu_turn_wait_seconds_total") == 0.0
