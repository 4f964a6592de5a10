"""``envs_per_worker: auto`` (0): a pod packs its envs, of every kind of scene and across tasks,
into at most one worker process per core, and serves the same observations as with one env per
worker."""

from __future__ import annotations

import math
import os

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from pydantic import ValidationError

from vecsim.config import AUTO_ENVS_PER_WORKER, Assignment, CameraConfig, JobSpec, TaskBlock
from vecsim.engine import TaskGroupedVectorEnv, auto_envs_per_worker, available_cores, resolve_envs_per_worker

CHEETAH = "gym/HalfCheetah-v5"


def _workers(sizes: list[int], per_worker: int) -> int:
    return math.ceil(sum(sizes) / per_worker)


def test_one_block_is_split_evenly_over_the_cores() -> None:
    assert auto_envs_per_worker([32], cores=2) == 16


def test_fewer_envs_than_cores_get_a_worker_each() -> None:
    assert auto_envs_per_worker([3], cores=4) == 1


def test_task_blocks_pack_together_within_the_cores() -> None:
    assert auto_envs_per_worker([2, 2, 2], cores=2) == 3


def test_no_envs_means_one_env_per_worker() -> None:
    assert auto_envs_per_worker([], cores=2) == auto_envs_per_worker([0, 0], cores=2) == 1


@given(st.lists(st.integers(0, 64), max_size=6), st.integers(1, 32))
def test_auto_is_the_fewest_envs_per_worker_that_fit_the_cores(sizes: list[int], cores: int) -> None:
    per_worker = auto_envs_per_worker(sizes, cores)
    budget = cores
    assert per_worker >= 1
    assert _workers(sizes, per_worker) <= budget
    assert per_worker == 1 or _workers(sizes, per_worker - 1) > budget


def test_available_cores_are_at_most_the_affinity() -> None:
    assert 1 <= available_cores() <= len(os.sched_getaffinity(0))


def test_auto_is_spelled_auto_or_zero_in_config() -> None:
    spec = {"generation": 0, "pod": "sim-0", "stage_id": 0}
    assert Assignment(**spec, envs_per_worker="auto").envs_per_worker == AUTO_ENVS_PER_WORKER
    assert JobSpec(suite="tiny", envs_per_worker="auto").envs_per_worker == AUTO_ENVS_PER_WORKER
    with pytest.raises(ValidationError, match="envs_per_worker"):
        Assignment(**spec, envs_per_worker=-1)
    with pytest.raises(ValidationError, match="envs_per_worker"):
        JobSpec(suite="tiny", envs_per_worker="many")


def _assignment(
    envs_per_worker: int, task_id: str = CHEETAH, num_envs: int = 5, camera: CameraConfig = CameraConfig(names=())
) -> Assignment:
    return Assignment(
        generation=1,
        pod="sim-0",
        stage_id=0,
        tasks=(TaskBlock(task_id=task_id, env_start=0, num_envs=num_envs),),
        camera=camera,
        envs_per_worker=envs_per_worker,
    )


def _pod(envs_per_worker: int) -> TaskGroupedVectorEnv:
    return TaskGroupedVectorEnv(_assignment(envs_per_worker))


def test_auto_packs_cheap_gym_scenes_over_the_cores() -> None:
    assert resolve_envs_per_worker(_assignment(AUTO_ENVS_PER_WORKER, num_envs=32), cores=2) == 16


def test_auto_packs_robot_scenes_and_cameras_over_the_cores_too() -> None:
    robot = _assignment(AUTO_ENVS_PER_WORKER, task_id="tiny/lift", num_envs=8)
    rendered = _assignment(AUTO_ENVS_PER_WORKER, num_envs=8, camera=CameraConfig(height=8, width=8))
    assert resolve_envs_per_worker(robot, cores=2) == resolve_envs_per_worker(rendered, cores=2) == 4


def test_an_explicit_envs_per_worker_is_kept() -> None:
    assert resolve_envs_per_worker(_assignment(3, num_envs=32), cores=2) == 3


def test_an_auto_pod_runs_the_split_auto_picks_for_its_cores() -> None:
    with _pod(AUTO_ENVS_PER_WORKER) as pod:
        per_worker = auto_envs_per_worker([5], available_cores())
        assert pod.envs_per_worker == per_worker
        assert pod.num_workers == len(set(pod.worker_pids)) == math.ceil(5 / per_worker)


def test_an_auto_pod_serves_the_same_envs_as_one_env_per_worker() -> None:
    actions = np.random.default_rng(0).uniform(-1, 1, (3, 5, 6)).astype(np.float32)
    answers = []
    for envs_per_worker in (AUTO_ENVS_PER_WORKER, 1):
        with _pod(envs_per_worker) as pod:
            obs, _ = pod.reset_envs([4, 0, 2, 1, 3], [7, 1, 3, 0, 9])
            steps = [pod.step_envs([3, 1, 0, 4, 2], step) for step in actions]
            answers.append((obs, [(s[0], s[1]) for s in steps]))
    (auto_obs, auto_steps), (one_obs, one_steps) = answers
    assert np.array_equal(auto_obs, one_obs)
    for (auto_proprio, auto_reward), (one_proprio, one_reward) in zip(auto_steps, one_steps):
        assert np.array_equal(auto_proprio, one_proprio) and np.array_equal(auto_reward, one_reward)
