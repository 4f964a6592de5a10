"""Partial failure of a stage call: one of a stage's two pods dies, the other's trajectories go on.

Two standalone pods serve the one stage (sim-0 and sim-1, two ``gym/Pendulum-v1`` envs each, the
job's token), so every stage call fans out to both. sim-1 is killed (SIGKILL of its process group)
in the middle; the call's error must name sim-1 and exactly its traj_keys, and hand over sim-0's
rows, which must be what sim-0's envs really hold: stepping on from them must give what a rollout
without any fault gives, bit for bit.
"""

from __future__ import annotations

import signal
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
import pytest
import torch
from support.service_procs import Server, assignment_file, pod_server, running

from vecsim.client import HTTPVectorEnv, PodUnavailableError, StageBatch, StageClient
from vecsim.rollout import EnvLoop

TOKEN = "partial-faults-token-0123456789abcdef"
PENDULUM = "gym/Pendulum-v1"
EPISODE = 30
KEYS = ["t0", "t1", "t2", "t3"]
REQUESTS = [(PENDULUM, k) for k in (3, 4, 5, 6)]
STRIKE_AT = 6  # policy calls: one stage, so one per step


def pod(name: str, workdir: Path) -> Server:
    path = assignment_file(workdir, name, [(PENDULUM, 2)], stage_id=0, max_episode_steps=EPISODE)
    return pod_server(name, workdir, args=["--assignment", str(path)], token=TOKEN)


@pytest.fixture
def pods(tmp_path) -> Iterator[tuple[Server, Server]]:
    """sim-0 and sim-1, both on stage 0; sim-1 is the one the tests kill."""
    first, second = pod("sim-0", tmp_path), pod("sim-1", tmp_path)
    with running(first, ready=True), running(second, ready=True):
        yield first, second


class Policy:
    """Deterministic (a function of each observation alone); runs ``fault`` at its ``at``-th call."""

    def __init__(self, fault=None, at: int = STRIKE_AT) -> None:
        self.fault, self.at, self.calls = fault, at, 0

    def __call__(self, obs, instructions, task_ids) -> torch.Tensor:
        self.calls += 1
        if self.calls == self.at and self.fault is not None:
            self.fault()
        return torch.clamp(-0.5 * obs[:, 2:3], -2.0, 2.0)


def on_pod(client: StageClient, name: str) -> list[str]:
    return [key for key, route in client.routes.items() if route.pod == name]


def actions(keys: Sequence[str], value: float) -> dict[str, np.ndarray]:
    return {key: np.array([value], np.float32) for key in keys}


def rows(batch: StageBatch, keys: Sequence[str]) -> np.ndarray:
    index = [batch.traj_keys.index(key) for key in keys]
    return np.concatenate([batch.obs[index], batch.reward[index, None]], axis=1)


@pytest.mark.slow
def test_a_killed_pod_fails_the_call_for_its_trajectories_alone_and_the_others_go_on(pods):
    _, doomed = pods
    with StageClient.from_pods([p.url for p in pods], timeout_s=10, token=TOKEN) as client:
        client.reset_trajectories(REQUESTS, KEYS)
        healthy, failed = on_pod(client, "sim-0"), on_pod(client, "sim-1")
        assert len(healthy) == len(failed) == 2
        # The reference: three steps of every trajectory, both pods alive.
        client.reset_stage(0).result(timeout=60)
        reference = [client.step_stage(0, actions(KEYS, a)).result(timeout=60) for a in (0.5, -1.0, 1.5)]

        client.reset_stage(0).result(timeout=60)
        client.step_stage(0, actions(KEYS, 0.5)).result(timeout=60)
        doomed.signal_group(signal.SIGKILL)
        with pytest.raises(PodUnavailableError) as caught:
            client.step_stage(0, actions(KEYS, -1.0)).result(timeout=60)
        error = caught.value
        assert error.pods == ["sim-1"] and sorted(error.traj_keys) == sorted(failed)
        assert "sim-1" in str(error) and "sim-0" not in str(error)
        # sim-0's rows of the failed call are delivered, and they are its envs' true state.
        assert error.answered.traj_keys == healthy
        assert np.array_equal(rows(error.answered, healthy), rows(reference[1], healthy))
        after = client.step_stage(0, actions(healthy, 1.5)).result(timeout=60)
        assert np.array_equal(rows(after, healthy), rows(reference[2], healthy))


@pytest.mark.slow
def test_a_rollout_loses_only_the_killed_pods_trajectories_and_finishes_the_rest_unchanged(pods):
    _, doomed = pods
    with StageClient.from_pods([p.url for p in pods], timeout_s=10, token=TOKEN) as client:
        loop = EnvLoop(client, Policy(), horizon=EPISODE)
        reference = loop.run(REQUESTS, KEYS)
        assert reference.lost == {} and set(reference.trajectories) == set(KEYS)
        healthy, failed = on_pod(client, "sim-0"), on_pod(client, "sim-1")

        loop.policy = Policy(lambda: doomed.signal_group(signal.SIGKILL))
        result = loop.run(REQUESTS, KEYS)
    assert sorted(result.lost) == sorted(failed)
    for lost in result.lost.values():
        assert lost.route.pod == "sim-1" and lost.steps < EPISODE and "sim-1" in lost.reason
    assert sorted(result.trajectories) == sorted(healthy)
    for key in healthy:
        mine, theirs = result.trajectories[key], reference.trajectories[key]
        assert mine.length == theirs.length == EPISODE
        assert torch.equal(mine.observations, theirs.observations)
        assert torch.equal(mine.actions, theirs.actions) and torch.equal(mine.rewards, theirs.rewards)


@pytest.mark.slow
def test_a_chunk_of_some_envs_fails_for_the_killed_pods_envs_alone(pods):
    _, doomed = pods
    env = HTTPVectorEnv(pod_urls=[p.url for p in pods], timeout_s=10, token=TOKEN)
    try:
        env.reset(seed=0)
        on_sim_0 = sorted(i for i, route in env.routes.items() if route.pod == "sim-0")
        on_sim_1 = sorted(i for i, route in env.routes.items() if route.pod == "sim-1")
        sent = [on_sim_0[0], *on_sim_1]  # sim-0's other env is left out of the call
        doomed.signal_group(signal.SIGKILL)
        with pytest.raises(PodUnavailableError) as caught:
            env.chunk_step(np.zeros((len(sent), 2, 1), np.float32), env_ids=sent)
        assert caught.value.failed_envs == on_sim_1
        assert caught.value.result[4]["num_steps"][on_sim_0].tolist() == [2, 0]
        _, reward, *_ = env.chunk_step(np.zeros((len(on_sim_0), 2, 1), np.float32), env_ids=on_sim_0)
    finally:
        env.close()
    assert reward.shape == (env.num_envs, 2)


def test_the_vector_env_raises_for_a_killed_pod_and_hands_over_the_other_pods_envs(pods):
    _, doomed = pods
    env = HTTPVectorEnv(pod_urls=[p.url for p in pods], timeout_s=10, token=TOKEN)
    try:
        env.reset(seed=0)
        failed = sorted(i for i, route in env.routes.items() if route.pod == "sim-1")
        on_sim_1 = [f"env{i}" for i in failed]
        doomed.signal_group(signal.SIGKILL)
        with pytest.raises(PodUnavailableError) as caught:
            env.step(np.zeros((env.num_envs, 1), np.float32))
        _reset, stepped = caught.value.answered
    finally:
        env.close()
    assert caught.value.pods == ["sim-1"] and sorted(caught.value.traj_keys) == on_sim_1
    assert caught.value.failed_envs == failed
    assert sorted(stepped.traj_keys) == sorted(set(f"env{i}" for i in range(env.num_envs)) - set(on_sim_1))
