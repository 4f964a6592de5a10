"""A served gymnasium env is the env itself: differential tests against local gymnasium.

Real pods over loopback serve gymnasium MuJoCo ids, CartPole (a Discrete action space) and the
tests' own custom env (``support.gym_custom_env:Custom-v0``: Dict/Tuple/Discrete/0-d observations, a
(2, 1) float64 action, rich info). Each HTTPVectorEnv is compared step by step with gymnasium's
``SyncVectorEnv`` of ``gymnasium.make(id)`` under the same seeds and actions: observations,
rewards, terminations, truncations and info (the env's own, nothing added) are identical in all
three autoreset modes. gymnasium's own vector wrappers run on it unchanged.
"""

from __future__ import annotations

import multiprocessing

import gymnasium
import numpy as np
import pytest
from gymnasium.error import ClosedEnvironmentError, NoAsyncCallError
from gymnasium.vector import AutoresetMode, SyncVectorEnv
from gymnasium.wrappers import vector as vw
from support.gym_compare import assert_same
from support.service_procs import PodSpec, standalone_pods

from vecsim.client import HTTPVectorEnv, PodRequestError
from vecsim.config import Assignment, CameraConfig, TaskBlock
from vecsim.engine import assignment_spaces
from vecsim.spaces import check_travels
from vecsim.engine.tasks import TaskSetupError, task_spaces

CUSTOM = "support.gym_custom_env:Custom-v0"
EPISODE = 8
# gymnasium id -> episode limit both sides use (None: the id's own; the custom env's is 7).
TASKS = {
    "HalfCheetah-v5": EPISODE,
    "Hopper-v5": EPISODE,
    "InvertedPendulum-v5": EPISODE,
    "CartPole-v1": EPISODE,
    CUSTOM: None,
}
NUM_ENVS = 3
STEPS = 20


@pytest.fixture(scope="module")
def pods(tmp_path_factory):
    specs = [
        PodSpec(f"sim-{i}", 0, [(f"gym/{gym_id}", NUM_ENVS)], max_episode_steps=limit, envs_per_worker=2)
        for i, (gym_id, limit) in enumerate(TASKS.items())
    ]
    specs.append(
        PodSpec("sim-kw", 0, [(f"gym/{CUSTOM}", 2)], max_episode_steps=None, make_kwargs={f"gym/{CUSTOM}": {"size": 3}})
    )
    with standalone_pods(specs, tmp_path_factory.mktemp("pods")) as running:
        yield {
            spec.tasks[0][0].removeprefix("gym/") if spec.name != "sim-kw" else "kwargs": pod.url
            for spec, pod in zip(specs, running)
        }


def _local(gym_id: str, mode: AutoresetMode = AutoresetMode.NEXT_STEP, n: int = NUM_ENVS) -> SyncVectorEnv:
    limit = TASKS[gym_id]
    kwargs = {} if limit is None else {"max_episode_steps": limit}
    return SyncVectorEnv([lambda: gymnasium.make(gym_id, **kwargs)] * n, autoreset_mode=mode)


@pytest.fixture
def served(pods):
    made = []

    def factory(gym_id: str, **kwargs) -> HTTPVectorEnv:
        env = HTTPVectorEnv(pod_urls=[pods[gym_id]], timeout_s=60, **kwargs)
        made.append(env)
        return env

    yield factory
    for env in made:
        env.close()


@pytest.mark.parametrize("mode", list(AutoresetMode), ids=lambda m: m.name.lower())
@pytest.mark.parametrize("gym_id", list(TASKS))
def test_served_env_steps_exactly_like_local_gymnasium(served, gym_id, mode):
    remote, local = served(gym_id, autoreset_mode=mode), _local(gym_id, mode)
    assert remote.single_observation_space == local.single_observation_space
    assert remote.single_action_space == local.single_action_space
    assert remote.observation_space == local.observation_space and remote.action_space == local.action_space
    obs, info = remote.reset(seed=11)
    expected = local.reset(seed=11)
    assert_same(obs, expected[0], "reset obs")
    assert_same(info, expected[1], "reset info")
    local.action_space.seed(5)
    ended = np.zeros(NUM_ENVS, dtype=bool)
    for t in range(STEPS):
        if mode == AutoresetMode.DISABLED and ended.any():
            obs, info = remote.reset(options={"reset_mask": ended.copy()})
            expected = local.reset(options={"reset_mask": ended.copy()})
            assert_same(obs, expected[0], f"step {t} masked reset obs")
            assert_same(info, expected[1], f"step {t} masked reset info")
        actions = local.action_space.sample()
        got, want = remote.step(actions), local.step(actions)
        for name, a, b in zip(("obs", "reward", "terminated", "truncated"), got[:4], want[:4]):
            assert_same(a, b, f"step {t} {name}")
        assert_same(got[4], want[4], f"step {t} info")
        ended = want[2] | want[3]
    local.close()


def test_a_served_env_resets_like_gymnasium_make_for_any_seed(served):
    remote = served("HalfCheetah-v5")
    env = gymnasium.make("HalfCheetah-v5")
    firsts = set()
    for seed in range(0, 30, 3):
        obs, _ = remote.reset(seed=[seed, seed + 1, None])
        assert np.array_equal(obs[0], env.reset(seed=seed)[0])
        assert np.array_equal(obs[1], env.reset(seed=seed + 1)[0])
        firsts.add(obs[0].tobytes())
    assert len(firsts) == 10


def test_reset_options_reach_the_env(served):
    remote, local = served(CUSTOM), _local(CUSTOM)
    obs, info = remote.reset(seed=1, options={"offset": 100.0})
    expected = local.reset(seed=1, options={"offset": 100.0})
    assert_same(obs, expected[0])
    assert_same(info, expected[1])
    assert (obs["level"] > 90).all() and (info["offset"] == 100.0).all()


def test_fixed_initial_states_stay_available_for_gym_tasks(served):
    remote = served("Hopper-v5")
    first, info = remote.reset(options={"state_ids": np.array([4, 4, 5])})
    again, _ = remote.reset(seed=123, options={"state_ids": np.array([4, 4, 5])})
    assert (
        np.array_equal(first, again) and np.array_equal(first[0], first[1]) and not np.array_equal(first[0], first[2])
    )
    assert info["state_id"].tolist() == [4, 4, 5]


def test_get_attr_call_and_set_attr_reach_the_envs(served):
    remote = served(CUSTOM)
    assert remote.get_attr("gain") == (1.0, 1.0, 1.0)
    remote.set_attr("gain", [1.0, 2.0, 3.0])
    assert remote.call("scaled", 2.0) == (2.0, 4.0, 6.0)
    assert remote.get_attr("size") == (5, 5, 5)
    remote.set_attr("gain", 1.0)
    assert remote.call("scaled", x=1.5) == (1.5, 1.5, 1.5)


@pytest.mark.parametrize(
    ("call", "error", "match"),
    [
        (lambda env: env.get_attr("_level"), PodRequestError, "not a public attribute"),
        (lambda env: env.call("close"), PodRequestError, "'close'"),
        (lambda env: env.set_attr("scaled", 3), ValueError, "JSON-valued attributes only"),
        (lambda env: env.get_attr("np_random_seed_missing"), AttributeError, "np_random_seed_missing"),
        (lambda env: env.get_attr("observation_space"), ValueError, "not JSON-serialisable"),
        (lambda env: env.set_attr("gain", [1.0, 2.0]), ValueError, "length equal to the number of environments"),
        (lambda env: env.set_attr("gain", float("nan")), ValueError, "values are not JSON"),
        (lambda env: env.call("scaled", object()), ValueError, "values are not JSON"),
    ],
)
def test_attribute_misuse_is_refused_and_changes_nothing(served, call, error, match):
    remote = served(CUSTOM)
    with pytest.raises(error, match=match):
        call(remote)
    assert remote.get_attr("gain") == (1.0, 1.0, 1.0)


def test_make_kwargs_of_the_job_reach_gymnasium_make(served):
    remote = served("kwargs")
    assert remote.single_observation_space["cell"] == gymnasium.spaces.Discrete(3)
    obs, _ = remote.reset(seed=2)
    local = SyncVectorEnv([lambda: gymnasium.make(CUSTOM, size=3)] * 2)
    assert_same(obs, local.reset(seed=2)[0])


def test_make_vec_honours_num_envs_and_autoreset_spellings(pods):
    url = pods["CartPole-v1"]
    env = gymnasium.make_vec("vecsim/HTTPVectorEnv-v0", num_envs=2, pod_urls=[url], autoreset_mode="same_step")
    try:
        assert env.num_envs == 2 and env.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
        assert env.reset(seed=0)[0].shape == (2, 4)
    finally:
        env.close()
    whole = gymnasium.make_vec("vecsim/HTTPVectorEnv-v0", num_envs=None, pod_urls=[url], autoreset_mode="Disabled")
    assert whole.num_envs == NUM_ENVS and whole.autoreset_mode == AutoresetMode.DISABLED
    whole.close()
    with pytest.raises(ValueError, match=f"num_envs=8 but the job has {NUM_ENVS} envs"):
        gymnasium.make_vec("vecsim/HTTPVectorEnv-v0", num_envs=8, pod_urls=[url])
    with pytest.raises(ValueError, match="unknown autoreset_mode 'sometimes'"):
        HTTPVectorEnv(pod_urls=[url], autoreset_mode="sometimes")


def test_vector_kwargs_are_refused_by_gymnasium_for_a_vector_entry_point(pods):
    with pytest.raises(gymnasium.error.Error, match="vector_kwargs"):
        gymnasium.make_vec(
            "vecsim/HTTPVectorEnv-v0",
            num_envs=1,
            pod_urls=[pods["CartPole-v1"]],
            vector_kwargs={"autoreset_mode": "same_step"},
        )


def test_misuse_raises_gymnasium_errors_with_its_wording(served):
    remote = served("CartPole-v1")
    with pytest.raises(NoAsyncCallError, match="Calling `step_wait` without any prior call to `step_async`"):
        remote.step_wait()
    remote.reset(seed=0)
    remote.step_async(np.zeros(NUM_ENVS, dtype=np.int64))
    with pytest.raises(multiprocessing.TimeoutError):
        remote.step_wait(timeout=0)
    remote.step_wait()
    with pytest.raises(PodRequestError, match=r"\(422\).*not in the action space Discrete"):
        remote.step(np.full(NUM_ENVS, 7))
    with pytest.raises(TypeError, match="chunks of Box actions"):
        remote.chunk_step(np.zeros((NUM_ENVS, 2), dtype=np.int64))
    remote.close()
    with pytest.raises(ClosedEnvironmentError, match="after a call to `close\\(\\)`"):
        remote.reset()


def test_gymnasium_vector_wrappers_work_unchanged(served):
    def wrap(env):
        env = vw.RecordEpisodeStatistics(env)
        env = vw.ClipAction(env)
        env = vw.NormalizeObservation(env)
        env = vw.TransformObservation(env, lambda o: np.clip(o, -10, 10), env.observation_space)
        return vw.NormalizeReward(env, gamma=0.99)

    remote, local = wrap(served("HalfCheetah-v5")), wrap(_local("HalfCheetah-v5"))
    assert_same(remote.reset(seed=4)[0], local.reset(seed=4)[0])
    rng = np.random.default_rng(0)
    for t in range(STEPS):
        actions = rng.uniform(-2, 2, (NUM_ENVS, 6)).astype(np.float32)
        got, want = remote.step(actions), local.step(actions)
        for a, b in zip(got[:4], want[:4]):
            assert_same(a, b, f"step {t}")
        # episode["t"] is wall time; the episode's return and length must agree.
        episode = {k: v for k, v in got[4].get("episode", {}).items() if k not in ("t", "_t")}
        assert_same(episode, {k: v for k, v in want[4].get("episode", {}).items() if k not in ("t", "_t")}, f"step {t}")
    local.close()


def test_flatten_observation_wraps_a_dict_and_tuple_observation(served):
    remote, local = vw.FlattenObservation(served(CUSTOM)), vw.FlattenObservation(_local(CUSTOM))
    assert remote.observation_space == local.observation_space
    assert_same(remote.reset(seed=9)[0], local.reset(seed=9)[0])
    actions = np.full((NUM_ENVS, 2, 1), 0.25)
    assert_same(remote.step(actions)[0], local.step(actions)[0])


def test_a_module_the_pod_cannot_import_is_an_error_naming_it():
    with pytest.raises(TaskSetupError, match="cannot import module 'no_such_pkg.envs'"):
        task_spaces("gym/no_such_pkg.envs:Thing-v0", CameraConfig(names=()))
    blocks = (TaskBlock(task_id="gym/no_such_pkg.envs:Thing-v0", env_start=0, num_envs=1),)
    with pytest.raises(TaskSetupError, match="no_such_pkg.envs"):
        assignment_spaces(Assignment(generation=0, pod="p", stage_id=0, tasks=blocks, camera=CameraConfig(names=())))


def test_a_space_that_cannot_travel_is_named():
    space = gymnasium.spaces.Dict({"name": gymnasium.spaces.Text(5), "x": gymnasium.spaces.Discrete(2)})
    with pytest.raises(ValueError, match=r"observation\.spaces\.name: Text is not supported"):
        check_travels(space, "observation")
