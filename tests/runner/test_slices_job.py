"""The ``slices`` stage layout over a real local job: a controller and two pods on loopback, each
pod holding envs of both stages (two tiny robot tasks, one 16x16 camera, 4-step episodes).

Every trajectory's explicit route is checked against the controller's routing table; a dead pod
loses its own trajectories of every stage and nothing else.
"""

from __future__ import annotations

import contextlib
import os
import signal
from collections.abc import Iterator
from typing import Any

import httpx
import numpy as np
import pytest
import torch
from support.service_procs import job_config, local_job, wait_until

from service.runner import LocalJob
from vecsim.client import HTTPVectorEnv, StageClient
from vecsim.client.routing import routed_envs
from vecsim.config import CameraConfig, RoutingTable
from vecsim.rollout import EnvLoop
from vecsim.rollout.sampler import TaskBalancedSampler, TaskInstances, stage_of

LIFT, STACK = "tiny/lift", "tiny/stack"
GROUP_SIZE = 2
EPISODE = 4
SPEC = {
    "job_id": "slices-tests",
    "tasks": [LIFT, STACK],
    "group_size": GROUP_SIZE,
    "num_stages": 2,
    "pods_per_stage": 2,
    "stage_layout": "slices",
    "camera": CameraConfig(names=("agentview",), height=16, width=16).model_dump(mode="json"),
    "max_episode_steps": EPISODE,
}


@pytest.fixture(scope="module")
def job(tmp_path_factory) -> Iterator[LocalJob]:
    with local_job(job_config(SPEC, replicas=2), tmp_path_factory.mktemp("slices")) as running:
        yield running


def routing(job: LocalJob) -> RoutingTable:
    return RoutingTable.model_validate(httpx.get(f"{job.controller_url}/v1/routing", timeout=5).json())


class StillPolicy:
    """Zero actions (a function of nothing but the batch size); runs ``fault`` once at call ``at``."""

    def __init__(self, action_dim: int, fault: Any = None, at: int = 0) -> None:
        self.action_dim, self.fault, self.at, self.calls = action_dim, fault, at, 0

    def __call__(self, obs: dict[str, Any], instructions: list[str], task_ids: list[str]) -> torch.Tensor:
        self.calls += 1
        if self.calls == self.at and self.fault is not None:
            self.fault()
        return torch.zeros(len(task_ids), self.action_dim)


def full_batch() -> list[tuple[str, int]]:
    """As many requests as the job has envs: group_size of each task on each stage."""
    dataset = TaskInstances.from_tasks([LIFT, STACK], num_states=6)
    sampler = TaskBalancedSampler(dataset, 2 * 2 * GROUP_SIZE, group_size=GROUP_SIZE, num_stages=2, seed=0)
    return [dataset[i] for i in next(iter(sampler))]


def test_every_pod_serves_every_stage_with_env_ids_of_its_own(job):
    table = routing(job)
    assert [sorted(p.pod for p in stage.pods) for stage in table.stages] == [["sim-0", "sim-1"]] * 2
    for name in ("sim-0", "sim-1"):
        info = httpx.get(f"{job.pod_url(name)}/v1/info", timeout=5).json()
        assert info["stage_id"] is None
        by_stage = {
            stage.stage_id: {
                env
                for p in stage.pods
                if p.pod == name
                for b in p.tasks
                for env in range(b.env_start, b.env_start + b.num_envs)
            }
            for stage in table.stages
        }
        assert by_stage[0] and by_stage[1] and not by_stage[0] & by_stage[1]
        assert by_stage[0] | by_stage[1] == set(range(info["num_envs"]))
        # What the pod says of its blocks is what the table says.
        for block in info["tasks"]:
            envs = set(range(block["env_start"], block["env_start"] + block["num_envs"]))
            assert envs <= by_stage[block["stage_id"]]


def test_a_two_stage_rollout_runs_every_trajectory_on_an_env_of_its_stage_in_the_table(job):
    requests = full_batch()
    table = routing(job)
    envs = {(e.stage_id, e.pod, e.env_index): e.task_id for e in routed_envs(table)}
    with StageClient.from_controller(job.controller_url, timeout_s=60, token=job.token) as client:
        policy = StillPolicy(client.action_space.shape[0])
        result = EnvLoop(client, policy, horizon=EPISODE).run(requests)
    assert result.lost == {} and len(result.trajectories) == len(requests)
    routes = [t.route for t in result.trajectories.values()]
    for i, ((task_id, state_id), route) in enumerate(zip(requests, routes)):
        assert (route.task_id, route.state_id, route.stage_id) == (task_id, state_id, stage_of(i, 2))
        assert envs[(route.stage_id, route.pod, route.env_index)] == task_id
    assert len({(r.pod, r.env_index) for r in routes}) == len(routes)
    # Both pods served both stages.
    assert {(r.stage_id, r.pod) for r in routes} == {(s, p) for s in (0, 1) for p in ("sim-0", "sim-1")}
    assert all(t.length == EPISODE for t in result.trajectories.values())


def test_an_empty_batch_is_a_no_op(job):
    with StageClient.from_controller(job.controller_url, timeout_s=60, token=job.token) as client:
        result = EnvLoop(client, StillPolicy(client.action_space.shape[0]), horizon=EPISODE).run([])
    assert result.trajectories == {} and result.lost == {} and result.stats.env_steps == 0


def test_a_stage_without_trajectories_is_a_no_op_on_pods_that_hold_it(job):
    with StageClient.from_controller(job.controller_url, timeout_s=60, token=job.token) as client:
        client.reset_trajectories([(LIFT, 1)])
        reset, step = client.call(reset=[], step={}).result()
        assert reset.n == 0 and step.n == 0
        assert client.reset_stage(1).result().n == 0  # stage 1 holds no trajectory
        assert client.step_stage(1, {}).result().n == 0
        result = EnvLoop(client, StillPolicy(client.action_space.shape[0]), horizon=2).run([(LIFT, 1)])
    (trajectory,) = result.trajectories.values()
    assert trajectory.route.stage_id == 0 and trajectory.length == 2


def test_a_vector_env_over_a_slices_job_has_every_env_of_both_stages_once_in_stage_major_order(job):
    table = routing(job)
    env = HTTPVectorEnv(job.controller_url, timeout_s=60, token=job.token)
    try:
        assert env.num_envs == table.num_envs
        env.reset(seed=0)
        placed = [(r.stage_id, r.pod, r.env_index, r.task_id) for _, r in sorted(env.routes.items())]
        assert placed == [(e.stage_id, e.pod, e.env_index, e.task_id) for e in routed_envs(table)]
        assert [stage for stage, *_ in placed] == sorted(stage for stage, *_ in placed)
        _, reward, _, truncated, _ = env.step(np.zeros((env.num_envs, *env.single_action_space.shape)))
        assert reward.shape == (table.num_envs,) and not truncated.any()
    finally:
        env.close()


def test_a_dead_pod_loses_only_its_own_trajectories_of_every_stage(job):
    # Last in this file: the runner starts sim-1 again and the job moves to a new generation.
    process = job.processes["sim-1"]
    before = routing(job)
    requests = full_batch()
    with StageClient.from_controller(job.controller_url, timeout_s=20, token=job.token) as client:
        policy = StillPolicy(client.action_space.shape[0], fault=lambda: os.killpg(process.pid, signal.SIGKILL), at=2)
        result = EnvLoop(client, policy, horizon=EPISODE).run(requests)
    assert result.lost, "the pod died before its trajectories ended"
    assert {lost.route.pod for lost in result.lost.values()} == {"sim-1"}
    assert {lost.route.stage_id for lost in result.lost.values()} == {0, 1}
    assert all(lost.steps < EPISODE for lost in result.lost.values())
    # sim-1 holds the job's STACK envs of both stages: every STACK trajectory is lost, no other.
    assert sorted(lost.route.task_id for lost in result.lost.values()) == sorted(t for t, _ in requests if t == STACK)
    for trajectory in result.trajectories.values():
        assert trajectory.route.pod == "sim-0" and trajectory.length == EPISODE
    assert {t.route.stage_id for t in result.trajectories.values()} == {0, 1}
    # The runner starts sim-1 again under its name; it takes its slot, envs of both stages, back.
    wait_until(lambda: process.restarts > 0, "sim-1 restarted")

    def ready_again() -> RoutingTable | None:
        with contextlib.suppress(httpx.HTTPError, ValueError):
            table = routing(job)
            return table if table.ready and table.generation > before.generation else None
        return None

    after = wait_until(ready_again, "the job ready at a new generation", timeout_s=180)
    assert [[(p.pod, p.tasks) for p in s.pods] for s in after.stages] == [
        [(p.pod, p.tasks) for p in s.pods] for s in before.stages
    ]
