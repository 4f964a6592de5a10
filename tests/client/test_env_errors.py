"""An env that raises costs only its own env: the others go on from the call's ``result``.

Two real pods (uvicorn on loopback) serve the tests' custom gymnasium env
(``support.gym_custom_env``: an action of 42 raises in its step, seed 4242 in its reset), two envs
each, so a call's rows come from both pods and a pod's answer holds envs that raised beside envs
that did not. gymnasium's ``SyncVectorEnv`` of the same env under the same seeds and actions is
the judge: the rows of the envs that did not raise are its rows, and once the envs that raised
are reset with a ``reset_mask``, every env steps on exactly as in it.
"""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
from gymnasium.error import ResetNeeded
from gymnasium.vector import AutoresetMode, SyncVectorEnv
from support import gym_custom_env
from support.gym_compare import assert_same, env_rows
from support.service_procs import PodSpec, standalone_pods

from vecsim.client import HTTPVectorEnv

CUSTOM = f"gym/{gym_custom_env.__name__}:{gym_custom_env.ENV_ID}"
NUM_ENVS = 4  # two pods of two envs
K = 3  # actions of a chunk


@pytest.fixture(scope="module")
def pod_urls(tmp_path_factory):
    specs = [PodSpec(f"sim-{i}", 0, [(CUSTOM, 2)], max_episode_steps=None, envs_per_worker=2) for i in range(2)]
    with standalone_pods(specs, tmp_path_factory.mktemp("pods")) as running:
        yield [pod.url for pod in running]


@pytest.fixture
def envs(pod_urls):
    """``make(mode)``: the served vector env and gymnasium's of the same env, closed after the test."""
    made = []

    def make(mode: AutoresetMode) -> tuple[HTTPVectorEnv, SyncVectorEnv]:
        remote = HTTPVectorEnv(pod_urls=pod_urls, autoreset_mode=mode, timeout_s=60)
        local = SyncVectorEnv([lambda: gymnasium.make(gym_custom_env.ENV_ID)] * NUM_ENVS, autoreset_mode=mode)
        made.extend([remote, local])
        return remote, local

    yield make
    for env in made:
        env.close()


def small_actions(rng: np.random.Generator, *shape: int) -> np.ndarray:
    """Actions small enough that no episode ends by its level within a few steps."""
    return rng.uniform(-0.1, 0.1, (NUM_ENVS, *shape, 2, 1))


def mask_of(envs: list[int]) -> np.ndarray:
    return np.isin(np.arange(NUM_ENVS), envs)


def assert_steps_alike(remote: HTTPVectorEnv, local: SyncVectorEnv, rng: np.random.Generator, steps: int) -> None:
    """``steps`` steps of both under the same actions give the same results, envs resetting
    themselves (or, DISABLED, reset with a mask) as their episodes end."""
    ended = np.zeros(NUM_ENVS, dtype=bool)
    for t in range(steps):
        if remote.autoreset_mode == AutoresetMode.DISABLED and ended.any():
            assert_same(remote.reset(options={"reset_mask": ended}), local.reset(options={"reset_mask": ended}))
        actions = rng.uniform(-1, 1, (NUM_ENVS, 2, 1))
        got, want = remote.step(actions), local.step(actions)
        assert_same(got, want, f"step {t}")
        ended = want[2] | want[3]


@pytest.mark.parametrize("mode", list(AutoresetMode), ids=lambda m: m.name.lower())
def test_an_env_raising_in_its_step_costs_only_that_env(envs, mode):
    remote, local = envs(mode)
    assert_same(remote.reset(seed=3), local.reset(seed=3))
    rng = np.random.default_rng(0)
    for _ in range(2):
        actions = small_actions(rng)
        assert_same(remote.step(actions), local.step(actions))
    actions = small_actions(rng)
    want = local.step(actions)
    actions[2, 0, 0] = gym_custom_env.BOOM  # env 2, on pod sim-1, beside env 3 that steps
    with pytest.raises(ValueError, match="the custom env refuses 42") as raised:
        remote.step(actions)
    assert raised.value.failed_envs == [2]
    others = [0, 1, 3]
    assert_same(env_rows(raised.value.result, others), env_rows(want, others))
    info = raised.value.result[4]
    assert info["_steps"].tolist() == [True, True, False, True]  # env 2's row is not an answer
    with pytest.raises(ResetNeeded, match=r"envs \[2\] got no answer"):
        remote.step(small_actions(rng))
    assert_same(
        remote.reset(seed=8, options={"reset_mask": mask_of([2])}),
        local.reset(seed=8, options={"reset_mask": mask_of([2])}),
    )
    assert_steps_alike(remote, local, rng, 12)  # past every env's truncation at 7 steps


def test_envs_raising_on_both_pods_raise_one_exception_naming_them_all(envs):
    remote, local = envs(AutoresetMode.NEXT_STEP)
    assert_same(remote.reset(seed=5), local.reset(seed=5))
    rng = np.random.default_rng(1)
    actions = small_actions(rng)
    want = local.step(actions)
    actions[[0, 3], 0, 0] = gym_custom_env.BOOM
    with pytest.raises(ValueError, match="the custom env refuses 42") as raised:
        remote.step(actions)
    assert raised.value.failed_envs == [0, 3]
    assert raised.value.__notes__ == ["envs [0, 3] raised; the others: env 3 ValueError: the custom env refuses 42"]
    assert_same(env_rows(raised.value.result, [1, 2]), env_rows(want, [1, 2]))
    assert_same(
        remote.reset(seed=2, options={"reset_mask": mask_of([0, 3])}),
        local.reset(seed=2, options={"reset_mask": mask_of([0, 3])}),
    )
    assert_steps_alike(remote, local, rng, 4)


def test_an_env_raising_inside_its_chunk_costs_only_that_env(envs):
    remote, local = envs(AutoresetMode.DISABLED)
    assert_same(remote.reset(seed=4), local.reset(seed=4))
    rng = np.random.default_rng(2)
    chunk = small_actions(rng, K)
    steps = [local.step(chunk[:, k]) for k in range(K)]
    assert not any((s[2] | s[3]).any() for s in steps)  # no episode ends inside: one chunk is K steps
    chunk[1, 1, 0, 0] = gym_custom_env.BOOM  # env 1's second action
    with pytest.raises(ValueError, match="the custom env refuses 42") as raised:
        remote.chunk_step(chunk)
    assert raised.value.failed_envs == [1]
    obs, reward, terminated, truncated, info = raised.value.result
    others = [0, 2, 3]
    assert_same(env_rows(obs, others), env_rows(steps[-1][0], others))
    for got, k in ((reward, 1), (terminated, 2), (truncated, 3)):
        assert_same(got[others], np.stack([s[k][others] for s in steps], axis=1))
    assert info["num_steps"].tolist() == [K, 0, K, K] and info["_num_steps"].tolist() == [True, False, True, True]
    with pytest.raises(ResetNeeded, match=r"envs \[1\] got no answer"):
        remote.chunk_step(small_actions(rng, K))
    assert_same(
        remote.reset(seed=6, options={"reset_mask": mask_of([1])}),
        local.reset(seed=6, options={"reset_mask": mask_of([1])}),
    )
    chunk = small_actions(rng, K)
    obs, reward, *_ = remote.chunk_step(chunk)
    steps = [local.step(chunk[:, k]) for k in range(K)]
    assert_same(obs, steps[-1][0])
    assert_same(reward, np.stack([s[1] for s in steps], axis=1))


def test_an_env_raising_in_its_reset_costs_only_that_env(envs):
    remote, local = envs(AutoresetMode.NEXT_STEP)
    seeds = [10, gym_custom_env.BOOM_SEED, 12, 13]
    want = local.reset(seed=[10, 11, 12, 13])
    with pytest.raises(ValueError, match="the custom env refuses seed 4242") as raised:
        remote.reset(seed=seeds)
    assert raised.value.failed_envs == [1]
    others = [0, 2, 3]
    assert_same(env_rows(raised.value.result, others), env_rows(want, others))
    assert raised.value.result[1]["_offset"].tolist() == [True, False, True, True]
    with pytest.raises(ResetNeeded, match=r"envs \[1\] were never reset"):
        remote.step(np.zeros((NUM_ENVS, 2, 1)))
    assert_same(
        remote.reset(seed=[None, 11, None, None], options={"reset_mask": mask_of([1])}),
        local.reset(seed=[None, 11, None, None], options={"reset_mask": mask_of([1])}),
    )
    assert_steps_alike(remote, local, np.random.default_rng(3), 4)
