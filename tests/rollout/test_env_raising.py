"""An env that raises in a pipelined rollout costs only its own trajectory.

Two standalone pods (uvicorn on loopback), one per stage, serve two envs each of the tests'
fragile gymnasium env (``support.gym_fragile_env``: a step with an action of ``BREAK`` or more
raises; one of ``-BREAK`` or less raises and breaks the env's next reset too). Eight requests
run on four envs, so half of them wait for a free env. A rollout without a fault is the
reference. In the others a scripted policy breaks the env of one trajectory (``r0``, on sim-0,
picked by the tag in its observation) after a few actions: that trajectory is lost, naming the
env's exception, a waiting request starts on its env, and every other trajectory is
bit-identical to the reference, also when the policy acts in chunks.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import pytest
import torch
from support import gym_fragile_env
from support.service_procs import PodSpec, standalone_pods

from vecsim.client import StageClient
from vecsim.rollout import EnvLoop, RolloutResult, Trajectory

FRAGILE = f"gym/{gym_fragile_env.__name__}:{gym_fragile_env.ENV_ID}"
HORIZON = 8
# The struck trajectory's env raises at its action STRIKE_AT + 1: STRIKE_AT actions are applied.
STRIKE_AT = 4
CHUNK = 2  # actions per policy call of a chunked rollout (STRIKE_AT is a multiple of it)
# Request i runs on stage i % 2: r0, r2 start on sim-0, r4, r6 wait for its envs; r1, r3, r5, r7 on sim-1.
REQUESTS = [(FRAGILE, i) for i in range(8)]
KEYS = [f"r{i}" for i in range(8)]


class BreakingPolicy:
    """Steers each level towards 0, a function of each observation alone; sends ``action``
    instead to the trajectory tagged ``tag`` once it has applied ``STRIKE_AT`` actions. With
    ``chunk``, each trajectory gets its action ``chunk`` times in one call."""

    def __init__(self, tag: float | None = None, action: float = 0.0, chunk: int | None = None) -> None:
        self.tag, self.action, self.chunk = tag, action, chunk

    def __call__(self, obs: torch.Tensor, instructions: list[str], task_ids: list[str]) -> torch.Tensor:
        actions = torch.clamp(-0.5 * obs[:, 0:1], -1.0, 1.0)
        if self.tag is not None:
            actions[(obs[:, 2] == self.tag) & (obs[:, 1] == STRIKE_AT)] = self.action
        return actions if self.chunk is None else actions[:, None].expand(-1, self.chunk, -1)


def assert_identical(mine: Trajectory, reference: Trajectory) -> None:
    assert (mine.route.task_id, mine.route.state_id) == (reference.route.task_id, reference.route.state_id)
    assert torch.equal(mine.observations, reference.observations), mine.traj_key
    assert torch.equal(mine.actions, reference.actions), mine.traj_key
    assert torch.equal(mine.rewards, reference.rewards), mine.traj_key
    assert (mine.terminated, mine.truncated) == (reference.terminated, reference.truncated), mine.traj_key


def starts_beside_steps(result: RolloutResult, pod: str) -> int:
    """How many calls to ``pod`` reset one trajectory while stepping another: a waiting request
    starting on an env freed before its neighbour's trajectory ended."""
    return sum((on, resets, steps) == (pod, 1, 1) for _, on, _, _, resets, steps in result.stats.pod_calls)


@pytest.fixture(scope="module")
def pod_urls(tmp_path_factory) -> Iterator[list[str]]:
    specs = [PodSpec(f"sim-{i}", i, [(FRAGILE, 2)], max_episode_steps=None, envs_per_worker=2) for i in range(2)]
    with standalone_pods(specs, tmp_path_factory.mktemp("pods")) as running:
        yield [pod.url for pod in running]


def roll_out(pod_urls: list[str], policy: BreakingPolicy) -> RolloutResult:
    with StageClient.from_pods(pod_urls, timeout_s=60) as client:
        return EnvLoop(client, policy, horizon=HORIZON).run(REQUESTS, KEYS)


@pytest.fixture(scope="module")
def references(pod_urls) -> Callable[[int | None], RolloutResult]:
    """The rollout without a fault, by chunk (None: one action a call), made when first asked for."""
    made: dict[int | None, RolloutResult] = {}

    def reference(chunk: int | None) -> RolloutResult:
        if chunk not in made:
            result = roll_out(pod_urls, BreakingPolicy(chunk=chunk))
            assert result.lost == {} and list(result.trajectories) == KEYS
            assert all(t.length == HORIZON for t in result.trajectories.values())
            assert starts_beside_steps(result, "sim-0") == 0  # r0, r2 end together: r4, r6 start together
            made[chunk] = result
        return made[chunk]

    return reference


@pytest.fixture(scope="module")
def reference(references) -> RolloutResult:
    return references(None)


@pytest.fixture
def r0_tag(reference) -> float:
    """The tag of r0's observations, which no other trajectory of the batch has."""
    tags = {key: float(t.observations[0, 2]) for key, t in reference.trajectories.items()}
    assert list(tags.values()).count(tags["r0"]) == 1
    return tags["r0"]


def assert_lost_to_its_env(lost: Any, kind: str, call: str, message: str) -> None:
    assert lost.route.pod == "sim-0" and lost.route.state_id == int(lost.traj_key[1:])
    assert f"of pod 'sim-0' raised {kind} in its {call}: {message}" in lost.reason


@pytest.mark.parametrize("chunk", [None, CHUNK], ids=["one-action", "chunks"])
def test_an_env_raising_in_a_step_loses_its_trajectory_alone_and_frees_its_env(pod_urls, references, r0_tag, chunk):
    reference = references(chunk)
    result = roll_out(pod_urls, BreakingPolicy(r0_tag, gym_fragile_env.BREAK, chunk))
    assert list(result.lost) == ["r0"]
    lost = result.lost["r0"]
    assert lost.steps == STRIKE_AT
    assert_lost_to_its_env(lost, "ValueError", "step", "the fragile env refuses action 1.5")
    # r4 waited for an env of sim-0 and started on r0's while r2 still ran; it ran to its horizon.
    assert starts_beside_steps(result, "sim-0") >= 1
    r4 = result.trajectories["r4"]
    assert (r4.route.pod, r4.route.env_index) == (lost.route.pod, lost.route.env_index)
    assert r4.length == HORIZON
    assert list(result.trajectories) == [key for key in KEYS if key != "r0"]
    for key, trajectory in result.trajectories.items():
        assert_identical(trajectory, reference.trajectories[key])


def test_an_env_raising_in_its_reset_loses_the_request_started_there_and_the_next_one_runs(pod_urls, reference, r0_tag):
    # The breaking action raises in r0's step and in the next reset of its env: r4's.
    result = roll_out(pod_urls, BreakingPolicy(r0_tag, -gym_fragile_env.BREAK))
    assert list(result.lost) == ["r0", "r4"]
    assert result.lost["r0"].steps == STRIKE_AT
    assert_lost_to_its_env(result.lost["r0"], "ValueError", "step", "the fragile env breaks at action -1.5")
    failed_reset = result.lost["r4"]
    assert failed_reset.steps == 0
    assert failed_reset.route.env_index == result.lost["r0"].route.env_index
    assert_lost_to_its_env(failed_reset, "ValueError", "reset", "the fragile env is broken: it refuses this reset")
    # That reset cleared the failure: r6 starts on the same env and runs to its horizon.
    r6 = result.trajectories["r6"]
    assert (r6.route.pod, r6.route.env_index) == (failed_reset.route.pod, failed_reset.route.env_index)
    assert r6.length == HORIZON
    assert list(result.trajectories) == [key for key in KEYS if key not in ("r0", "r4")]
    for key, trajectory in result.trajectories.items():
        assert_identical(trajectory, reference.trajectories[key])
