"""A gymnasium env served by a pod is the env its id or factory builds, seeds and all.

gymnasium's own ``SyncVectorEnv`` over the same factories is the judge: real pods over loopback
serve CartPole by id, ``support.gym_served_envs:seeded_cartpole`` (a factory that seeds its
spaces and resets, as gymnasium's tests write them) and ``support.gym_served_envs:probe`` (bool
Box actions; ends after ``max_count`` steps once that attribute is set) and
``support.gym_served_envs:sleepy`` (float actions handed to ``time.sleep``; an rgb_array render). A robot job (tiny/lift)
checks the attributes gymnasium users read there: ``np_random_seed``, ``task``, ``spec``.
"""

from __future__ import annotations

import functools
import json

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from gymnasium.vector import SyncVectorEnv
from support import gym_served_envs
from support.service_procs import PodSpec, assignment, standalone_pods

from vecsim.client import HTTPVectorEnv
from vecsim.config import CameraConfig
from vecsim.engine import SpacesDifferError, assignment_spaces
from vecsim.engine.tasks import make_env

CARTPOLE = "gym/CartPole-v1"
SEEDED = "gym/support.gym_served_envs:seeded_cartpole"
PROBE = "gym/support.gym_served_envs:probe"
COMPOSED = "gym/support.gym_served_envs:composed"
SLEEPY = "gym/support.gym_served_envs:sleepy"
NUM_ENVS = 4


@pytest.fixture(scope="module")
def pods(tmp_path_factory):
    specs = [
        PodSpec("fresh-a", 0, [(CARTPOLE, NUM_ENVS)], max_episode_steps=None, envs_per_worker=2),
        PodSpec("fresh-b", 0, [(CARTPOLE, NUM_ENVS)], max_episode_steps=None, envs_per_worker=2),
        PodSpec("seeded", 0, [(SEEDED, 2)], max_episode_steps=None, make_kwargs={SEEDED: {"seed": 3}}),
        # vecsim's own TimeLimit (the job's limit) sits around the probe; attributes never see it.
        PodSpec("probe", 0, [(PROBE, 2)], max_episode_steps=50),
        PodSpec("robot", 0, [("tiny/lift", 2)], max_episode_steps=20),
        PodSpec("composed", 0, [(COMPOSED, 2)], max_episode_steps=None),
        PodSpec("sleepy", 0, [(SLEEPY, 2)], max_episode_steps=None),
    ]
    with standalone_pods(specs, tmp_path_factory.mktemp("pods")) as running:
        yield {spec.name: pod.url for spec, pod in zip(specs, running)}


@pytest.fixture
def vector(pods):
    made = []

    def factory(pod: str) -> HTTPVectorEnv:
        env = HTTPVectorEnv(pod_urls=[pods[pod]], timeout_s=60)
        made.append(env)
        return env

    yield factory
    for env in made:
        env.close()


def test_unseeded_envs_on_fresh_pods_start_differently_as_in_sync_vector_env(vector):
    # Fresh pods (module scope: nothing has reset their envs yet), as SyncVectorEnv's fresh envs.
    a, b = vector("fresh-a"), vector("fresh-b")
    sync = SyncVectorEnv([lambda: gymnasium.make("CartPole-v1")] * NUM_ENVS)
    firsts = [a.reset()[0], b.reset()[0], sync.reset()[0]]
    for obs in firsts:
        assert len({row.tobytes() for row in obs}) == NUM_ENVS
    assert len({obs.tobytes() for obs in firsts}) == 3
    assert len(set(a.np_random_seed) | set(b.np_random_seed)) == 2 * NUM_ENVS
    sync.close()


def test_seeded_resets_are_sync_vector_envs_bit_for_bit(vector):
    remote = vector("fresh-a")
    sync = SyncVectorEnv([lambda: gymnasium.make("CartPole-v1")] * NUM_ENVS)
    for seed in (7, [1, None, 3, 4]):
        obs, info = remote.reset(seed=seed)
        expected, expected_info = sync.reset(seed=seed)
        rows = [0, 2, 3] if isinstance(seed, list) else slice(None)
        assert obs.dtype == expected.dtype and np.array_equal(obs[rows], expected[rows])
        assert info == expected_info == {}  # CartPole's reset info: nothing is added to it
    assert remote.np_random_seed[:1] + remote.np_random_seed[2:] == sync.np_random_seed[:1] + sync.np_random_seed[2:]
    sync.close()


def test_a_factorys_seeds_and_seeded_spaces_are_the_vector_envs(vector):
    remote = vector("seeded")
    sync = SyncVectorEnv([functools.partial(gym_served_envs.seeded_cartpole, seed=3)] * 2)
    assert remote.np_random_seed == sync.np_random_seed == (3, 3)
    for _ in range(5):
        assert np.array_equal(remote.action_space.sample(), sync.action_space.sample())
        assert np.array_equal(remote.single_observation_space.sample(), sync.single_observation_space.sample())
    obs, _ = remote.reset()  # unseeded: each env goes on from its factory's seeding
    assert np.array_equal(obs, sync.reset()[0])
    sync.close()


def test_set_attr_reaches_the_env_the_factory_returns(vector):
    remote = vector("probe")
    sync = SyncVectorEnv([gym_served_envs.probe] * 2)
    for env in (remote, sync):
        env.set_attr("max_count", [2, 3])
        env.reset(seed=0)
    actions = np.ones((2, 3), dtype=bool)
    for _ in range(3):
        got, want = remote.step(actions), sync.step(actions)
        assert np.array_equal(got[2], want[2])
    assert remote.get_attr("max_count") == sync.get_attr("max_count") == (2, 3)
    sync.close()


def test_bool_box_actions_reach_the_env_as_bools(vector):
    remote = vector("probe")
    sync = SyncVectorEnv([gym_served_envs.probe] * 2)
    remote.reset(seed=0)
    sync.reset(seed=0)
    actions = np.array([[True, False, True], [False, False, True]])
    got, want = remote.step(actions), sync.step(actions)
    assert np.array_equal(got[0], want[0])
    assert list(got[4]["action_dtype"]) == list(want[4]["action_dtype"]) == ["|b1", "|b1"]
    sync.close()


def test_dict_and_tuple_actions_reach_the_env_as_its_own_space_gives_them(vector):
    remote = vector("composed")
    sync = SyncVectorEnv([gym_served_envs.composed] * 2)
    assert remote.single_action_space == sync.single_action_space and remote.action_space == sync.action_space
    remote.reset(seed=0)
    sync.reset(seed=0)
    sync.action_space.seed(1)
    for _ in range(5):
        actions = sync.action_space.sample()
        got, want = remote.step(actions), sync.step(actions)
        assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
        assert np.array_equal(got[4]["pick"], want[4]["pick"])
    sync.close()


def test_spec_comes_as_gymnasiums_own_json_view(vector):
    by_id, by_factory = vector("fresh-a"), vector("seeded")
    cartpole = json.loads(gymnasium.spec("CartPole-v1").to_json())
    for served in (by_id.get_attr("spec")[0], by_factory.get_attr("spec")[0]):
        assert {k: served[k] for k in ("id", "entry_point", "max_episode_steps")} == {
            k: cartpole[k] for k in ("id", "entry_point", "max_episode_steps")
        }


def test_a_robot_jobs_np_random_seed_is_the_same_by_property_and_get_attr(vector):
    remote = vector("robot")
    assert remote.get_attr("np_random_seed") == remote.np_random_seed
    remote.reset(seed=5)
    assert remote.get_attr("np_random_seed") == remote.np_random_seed == (5, 6)


def test_a_robot_tasks_spec_comes_as_a_dict_of_its_fields(vector):
    remote = vector("robot")
    tasks = remote.call("task")
    assert [task["task_id"] for task in tasks] == ["tiny/lift"] * 2
    assert tasks[0]["num_states"] == remote.client.num_states["tiny/lift"]


@pytest.mark.parametrize("gym_id", ["HalfCheetah-v5", "Pendulum-v1", "CartPole-v1"])
def test_gymnasiums_check_env_passes_on_the_env_a_pod_serves(gym_id):
    env = make_env(f"gym/{gym_id}", CameraConfig(names=()), "lean", None)
    try:
        check_env(env, skip_render_check=True)
    finally:
        env.close()


def test_float_actions_reach_the_env_in_the_dtype_sent(vector):
    remote = vector("sleepy")
    sync = SyncVectorEnv([gym_served_envs.sleepy] * 2)
    remote.reset(seed=0)
    sync.reset(seed=0)
    actions = np.array([0.001, 0.002])  # float64, in a float32 space: time.sleep takes them
    got, want = remote.step(actions), sync.step(actions)
    assert got[0].dtype == want[0].dtype and np.array_equal(got[0], want[0])
    assert list(got[4]["action_type"]) == list(want[4]["action_type"]) == ["float64"] * 2
    for env in (remote, sync):  # float32 ones reach the env as float32: time.sleep refuses them
        with pytest.raises(TypeError, match="numpy.float32"):
            env.step(actions.astype(np.float32))
    sync.close()


def test_render_gives_each_envs_own_frame_as_gymnasium(vector):
    remote, plain = vector("sleepy"), vector("fresh-a")
    sync = SyncVectorEnv([gym_served_envs.sleepy] * 2)
    assert remote.render_mode == sync.render_mode == "rgb_array"
    assert plain.render_mode is None
    remote.reset(seed=0)
    sync.reset(seed=0)
    for env in (remote, sync):
        env.step(np.zeros(2))
    got, want = remote.render(), sync.render()
    assert isinstance(got, tuple) and len(got) == 2
    for frame, expected in zip(got, want):
        assert frame.dtype == expected.dtype == np.uint8 and np.array_equal(frame, expected)
    sync.close()


def test_envs_whose_spaces_differ_are_refused_as_gymnasium_refuses_them():
    # CartPole (Box observations) beside FrozenLake (Discrete ones), as gymnasium's own test.
    factories = [functools.partial(gymnasium.make, "CartPole-v1"), functools.partial(gymnasium.make, "FrozenLake-v1")]
    with pytest.raises(RuntimeError):
        gymnasium.vector.AsyncVectorEnv(factories)
    tasks = [("gym/CartPole-v1", 1), ("gym/FrozenLake-v1", 1)]
    with pytest.raises(
        RuntimeError, match="'gym/FrozenLake-v1' and 'gym/CartPole-v1' have different observation spaces"
    ) as refused:
        assignment_spaces(assignment("mixed", tasks, camera=CameraConfig(names=())))
    assert isinstance(refused.value, SpacesDifferError)
