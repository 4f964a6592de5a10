"""Where a pod's step time goes: ``TaskGroupedVectorEnv.last_timing`` (worker seconds in physics
and in rendering, summed over the workers) and the pod's counters of them in ``/metrics``."""

from __future__ import annotations

import contextlib
import json
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest

from vecsim import wire
from vecsim.config import Assignment, CameraConfig, TaskBlock
from vecsim.sim import CallTiming, TaskGroupedVectorEnv

CHEETAH = "gym/HalfCheetah-v5"


def cheetahs(camera: CameraConfig, envs: int = 2) -> Assignment:
    return Assignment(
        generation=0, pod="sim-0", stage_id=0, tasks=(TaskBlock(task_id=CHEETAH, env_start=0, num_envs=envs),),
        camera=camera, envs_per_worker=1, max_episode_steps=100,
    )  # fmt: skip


def zeros(n: int) -> np.ndarray:
    return np.zeros((n, 6), np.float32)


def test_a_step_with_cameras_reports_physics_and_render_seconds():
    with TaskGroupedVectorEnv(cheetahs(CameraConfig(names=("render",), height=16, width=16))) as env:
        assert env.last_timing == CallTiming()  # nothing called yet
        env.step_envs([0, 1], zeros(2))
        assert env.last_timing.physics_s > 0 and env.last_timing.render_s > 0


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@pytest.fixture
def pod_url(tmp_path: Path) -> Iterator[str]:
    """A standalone pod of two HalfCheetahs with a 16x16 camera; killed at the end."""
    path = tmp_path / "assignment.json"
    path.write_text(json.dumps(cheetahs(CameraConfig(names=("render",), height=16, width=16)).model_dump(mode="json")))
    port = free_port()
    with (tmp_path / "pod.log").open("wb") as log:
        process = subprocess.Popen(
            [sys.executable, "-m", "vecsim.cli", "pod", "--assignment", str(path), "--name", "sim-0",
             "--host", "127.0.0.1", "--port", str(port)],
            stdout=log, stderr=subprocess.STDOUT,
        )  # fmt: skip
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            with contextlib.suppress(httpx.TransportError):
                if httpx.get(f"{url}/readyz", timeout=5).status_code == 200:
                    break
            time.sleep(0.2)
        else:
            pytest.fail(f"pod not ready in 60 s:\n{(tmp_path / 'pod.log').read_text()[-2000:]}")
        yield url
    finally:
        process.kill()
        process.wait(timeout=10)


def counter(url: str, name: str) -> float:
    for line in httpx.get(f"{url}/metrics", timeout=5).text.splitlines():
        if line.startswith(name + " "):
            return float(line.split()[1])
    raise AssertionError(f"{name} not in {url}/metrics")


@pytest.mark.timeout(120)
def test_the_pod_counts_physics_and_render_seconds_of_its_steps(pod_url):
    names = ("vecsim_pod_physics_seconds_total", "vecsim_pod_render_seconds_total")
    before = {name: counter(pod_url, name) for name in names}
    body = wire.encode({"generation": 0, "env_ids": np.array([0, 1]), "actions": zeros(2)})
    response = httpx.post(f"{pod_url}/v1/step", content=body, headers={"Content-Type": wire.CONTENT_TYPE}, timeout=30)
    assert response.status_code == 200
    for name, value in before.items():
        assert counter(pod_url, name) > value, name
