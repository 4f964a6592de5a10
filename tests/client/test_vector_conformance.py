"""gymnasium's documented VectorEnv behaviour, asserted alike on HTTPVectorEnv and gymnasium's own.

Every test taking ``make_vec`` runs twice: on :class:`HTTPVectorEnv` over real standalone pods
(two stages, one pod each) and on gymnasium's ``SyncVectorEnv`` built from the same task envs
(``vecsim.engine.tasks.make_env``). The async-protocol tests run on HTTPVectorEnv and gymnasium's
``AsyncVectorEnv`` instead (``SyncVectorEnv`` has no ``step_async``).

The task is ``gym/InvertedPendulum-v5`` without cameras and with 3-step episodes: under zero
actions the pole stays up, so every env truncates exactly 3 steps after its reset.
"""

from __future__ import annotations

import functools

import gymnasium
import numpy as np
import pytest
from gymnasium.error import AlreadyPendingCallError, ClosedEnvironmentError, NoAsyncCallError, ResetNeeded
from gymnasium.vector import AsyncVectorEnv, AutoresetMode, SyncVectorEnv
from gymnasium.vector.utils import batch_space
from support.service_procs import NO_CAMERA, PodSpec, standalone_pods

from vecsim.client import HTTPVectorEnv
from vecsim.config import CameraConfig
from vecsim.engine.tasks import make_env

TASK = "gym/InvertedPendulum-v5"
EPISODE = 3
NUM_ENVS = 4
MODES = [AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP, AutoresetMode.DISABLED]


# A partial of a library function pickles by reference, so AsyncVectorEnv's workers can take it.
_task_env = functools.partial(make_env, TASK, NO_CAMERA, "lean", EPISODE)


@pytest.fixture(scope="module")
def pod_urls(tmp_path_factory):
    specs = [
        PodSpec("sim-0", 0, [(TASK, 2)], max_episode_steps=EPISODE),
        PodSpec("sim-1", 1, [(TASK, 2)], max_episode_steps=EPISODE),
    ]
    with standalone_pods(specs, tmp_path_factory.mktemp("pods")) as pods:
        yield [pod.url for pod in pods]


@pytest.fixture(params=["http", "sync"])
def make_vec(request, pod_urls):
    made = []

    def factory(mode: AutoresetMode = AutoresetMode.NEXT_STEP):
        if request.param == "http":
            env = HTTPVectorEnv(pod_urls=pod_urls, autoreset_mode=mode, timeout_s=30)
        else:
            env = SyncVectorEnv([_task_env] * NUM_ENVS, autoreset_mode=mode)
        made.append(env)
        return env

    yield factory
    for env in made:
        env.close()


@pytest.fixture(params=["http", "async"])
def make_async_vec(request, pod_urls):
    made = []

    def factory():
        if request.param == "http":
            env = HTTPVectorEnv(pod_urls=pod_urls)
        else:
            env = AsyncVectorEnv([_task_env] * NUM_ENVS)
        made.append(env)
        return env

    yield factory
    for env in made:
        env.close()


def _zeros(env) -> np.ndarray:
    return np.zeros((env.num_envs, *env.single_action_space.shape), dtype=np.float32)


def _rows_equal(a: np.ndarray, b: np.ndarray, rows) -> bool:
    return np.array_equal(a[rows], b[rows])


def _resets(info: dict) -> np.ndarray:
    """Which envs of a call that answered every env answered with a reset: InvertedPendulum's
    step info has ``reward_survive``, its reset info no key at all."""
    return ~info.get("_reward_survive", np.zeros(NUM_ENVS, bool))


# -- spaces and batches --------------------------------------------------------------------------


def test_batched_spaces_are_the_single_spaces_batched(make_vec):
    env = make_vec()
    assert env.num_envs == NUM_ENVS
    assert env.single_observation_space == _task_env().observation_space
    assert env.observation_space == batch_space(env.single_observation_space, NUM_ENVS)
    assert env.action_space == batch_space(env.single_action_space, NUM_ENVS)


@pytest.mark.parametrize("mode", MODES)
def test_metadata_names_the_autoreset_mode(make_vec, mode):
    assert make_vec(mode).metadata["autoreset_mode"] == mode


def test_reset_returns_observations_in_the_space_and_masked_info(make_vec):
    env = make_vec()
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    assert info == {}  # InvertedPendulum's reset info is empty, and nothing is added to it


def test_step_returns_one_reward_termination_and_truncation_per_env(make_vec):
    env = make_vec()
    env.reset(seed=0)
    obs, reward, terminated, truncated, info = env.step(_zeros(env))
    assert env.observation_space.contains(obs)
    assert reward.shape == terminated.shape == truncated.shape == (NUM_ENVS,)
    assert np.issubdtype(reward.dtype, np.floating)
    assert terminated.dtype == truncated.dtype == np.bool_
    assert set(info) == {"reward_survive", "_reward_survive"} and info["_reward_survive"].all()  # the env's own, only


# -- seeding -------------------------------------------------------------------------------------


def test_the_same_seed_gives_the_same_observations(make_vec):
    env = make_vec()
    first, _ = env.reset(seed=11)
    env.step(_zeros(env))
    again, _ = env.reset(seed=11)
    assert _rows_equal(first, again, slice(None))


def test_a_list_of_seeds_seeds_each_env(make_vec):
    env = make_vec()
    by_int, _ = env.reset(seed=5)
    by_list, _ = env.reset(seed=[5, 6, 7, 8])
    assert _rows_equal(by_int, by_list, slice(None))


def test_a_list_of_seeds_of_the_wrong_length_is_a_value_error(make_vec):
    with pytest.raises(ValueError):
        make_vec().reset(seed=[1, 2])


def test_http_and_sync_agree_on_seeded_resets(pod_urls):
    http = HTTPVectorEnv(pod_urls=pod_urls)
    sync = SyncVectorEnv([_task_env] * NUM_ENVS)
    try:
        for seed in (0, 123):
            assert _rows_equal(http.reset(seed=seed)[0], sync.reset(seed=seed)[0], slice(None))
    finally:
        http.close()
        sync.close()


def test_np_random_seed_is_each_envs_seed_as_gymnasiums_vector_env_gives_it(pod_urls):
    # gymnasium's SyncVectorEnv of the gymnasium env itself is the judge (vecsim's task env
    # keeps its gymnasium env inside, where the pods read attributes).
    gym_id = TASK.removeprefix("gym/")
    http = HTTPVectorEnv(pod_urls=pod_urls)
    sync = SyncVectorEnv([lambda: gymnasium.make(gym_id)] * NUM_ENVS)
    try:
        for seed in (42, None):  # an unseeded reset keeps the seeds
            http.reset(seed=seed)
            sync.reset(seed=seed)
            assert http.np_random_seed == sync.np_random_seed == tuple(42 + i for i in range(NUM_ENVS))
    finally:
        http.close()
        sync.close()


def test_fixed_state_envs_draw_state_ids_from_their_own_seeded_generators(tmp_path):
    # A gym task with a camera resets to fixed states, as robot tasks do: each env draws its
    # state ids (its reset's, then its autoresets') from its own generator, seeded seed + i.
    spec = PodSpec(
        "sim-cam", 0, [(TASK, 3)], camera=CameraConfig(names=("render",), height=8, width=8), max_episode_steps=EPISODE
    )
    with standalone_pods([spec], tmp_path) as pods:
        env = HTTPVectorEnv(pod_urls=[pods[0].url])
        try:

            def draws(seed):
                _, info = env.reset(seed=seed)
                for _ in range(EPISODE + 1):  # the step after the episode's end autoresets
                    *_, step_info = env.step(_zeros(env))
                return list(info["state_id"]), list(step_info["state_id"]), env.np_random_seed

            first = draws(7)
            assert draws(7) == first and first[2] == (7, 8, 9)
            other = draws([7, 100, 9])
            assert [other[0][i] for i in (0, 2)] == [first[0][i] for i in (0, 2)]
            assert [other[1][i] for i in (0, 2)] == [first[1][i] for i in (0, 2)]
        finally:
            env.close()


def test_reset_options_no_env_reads_are_ignored_and_vecsims_own_still_checked(pod_urls):
    # LeRobot's rollout resets with options of its own; a gymnasium env ignores what it does not know.
    env = HTTPVectorEnv(pod_urls=pod_urls)
    try:
        ids = [4, 0, 4, 49]
        plain, _ = env.reset(options={"state_ids": ids})
        env.step(_zeros(env))
        extra, info = env.reset(options={"state_ids": ids, "lerobot_new_rollout": True})
        assert _rows_equal(plain, extra, slice(None)) and list(info["state_id"]) == ids
        with pytest.raises(ValueError, match=r"state id 50 for env 2"):
            env.reset(options={"state_ids": [0, 0, 50, 0], "lerobot_new_rollout": True})
    finally:
        env.close()


def test_max_episode_steps_is_served_by_timelimits_name(make_vec):
    # LeRobot's rollout reads call("_max_episode_steps")[0]; gymnasium's TimeLimit names it so.
    env = make_vec()
    assert env.get_attr("_max_episode_steps") == env.call("_max_episode_steps") == (EPISODE,) * NUM_ENVS


def test_set_attr_makes_an_attribute_no_layer_of_the_env_has_yet(make_vec):
    # gymnasium's set_wrapper_attr(force=True), which its vector envs' set_attr uses.
    env = make_vec()
    env.reset(seed=0)
    env.set_attr("max_count", [2, 3, 3, 4])
    assert env.get_attr("max_count") == (2, 3, 3, 4)


# -- partial resets ------------------------------------------------------------------------------


def test_reset_mask_resets_only_the_masked_envs(make_vec):
    env = make_vec()
    env.reset(seed=1)
    before, *_ = env.step(_zeros(env))
    mask = np.array([True, False, False, True])
    after, info = env.reset(seed=2, options={"reset_mask": mask})
    assert _rows_equal(before, after, ~mask)
    assert not _rows_equal(before, after, np.flatnonzero(mask)[:1])
    assert info == {}


@pytest.mark.parametrize(
    "mask, error",
    [
        ([True] * NUM_ENVS, TypeError),
        (np.ones(NUM_ENVS + 1, dtype=bool), ValueError),
        (np.ones(NUM_ENVS, dtype=np.int8), TypeError),
        (np.zeros(NUM_ENVS, dtype=bool), ValueError),
    ],
)
def test_a_bad_reset_mask_is_refused(make_vec, mask, error):
    env = make_vec()
    with pytest.raises(error):
        env.reset(options={"reset_mask": mask})


# -- autoreset modes -----------------------------------------------------------------------------


def _run_to_episode_end(env) -> tuple:
    for _ in range(EPISODE - 1):
        _, _, terminated, truncated, _ = env.step(_zeros(env))
        assert not (terminated | truncated).any()
    return env.step(_zeros(env))


def test_next_step_resets_on_the_step_after_the_episode_ends(make_vec):
    env = make_vec(AutoresetMode.NEXT_STEP)
    env.reset(seed=3)
    _, _, _, truncated, _ = _run_to_episode_end(env)
    assert truncated.all()
    obs, reward, terminated, truncated, info = env.step(_zeros(env))
    assert env.observation_space.contains(obs)
    assert (reward == 0).all() and not terminated.any() and not truncated.any()
    assert _resets(info).all()  # every env answered with its reset, not a step
    _, _, _, truncated, _ = _run_to_episode_end(env)
    assert truncated.all()


def test_next_step_steps_envs_that_did_not_end(make_vec):
    env = make_vec(AutoresetMode.NEXT_STEP)
    env.reset(seed=4)
    env.step(_zeros(env))
    late = np.array([False, True, False, False])
    env.reset(seed=9, options={"reset_mask": late})  # env 1's episode now ends a step later
    env.step(_zeros(env))
    _, _, _, truncated, _ = env.step(_zeros(env))
    assert np.array_equal(truncated, ~late)
    _, reward, _, truncated, info = env.step(_zeros(env))
    assert np.array_equal(truncated, late)
    assert np.array_equal(_resets(info), ~late)
    assert (reward[~late] == 0).all()


def test_same_step_resets_within_the_step_and_reports_the_final_observation(make_vec):
    env = make_vec(AutoresetMode.SAME_STEP)
    env.reset(seed=5)
    obs, reward, terminated, truncated, info = _run_to_episode_end(env)
    assert truncated.all()
    assert info["_final_obs"].all() and info["_final_info"].all()
    assert all(env.single_observation_space.contains(o) for o in info["final_obs"])
    assert info["final_info"]["_reward_survive"].all()
    assert _resets(info).all()  # the returned observation is the reset one
    assert env.observation_space.contains(obs)
    _, _, _, truncated, _ = _run_to_episode_end(env)
    assert truncated.all()


def test_same_step_reports_final_observations_only_for_envs_that_ended(make_vec):
    env = make_vec(AutoresetMode.SAME_STEP)
    env.reset(seed=6)
    env.step(_zeros(env))
    late = np.array([True, False, False, False])
    env.reset(seed=7, options={"reset_mask": late})
    env.step(_zeros(env))
    _, _, _, truncated, info = env.step(_zeros(env))
    assert np.array_equal(truncated, ~late)
    assert np.array_equal(info["_final_obs"], ~late)
    assert info["final_obs"][0] is None


def test_disabled_leaves_resets_to_the_caller(make_vec):
    env = make_vec(AutoresetMode.DISABLED)
    env.reset(seed=8)
    last, _, _, truncated, info = _run_to_episode_end(env)
    assert truncated.all() and "final_obs" not in info
    mask = np.array([True, True, False, False])
    obs, info = env.reset(options={"reset_mask": mask})
    assert _rows_equal(last, obs, ~mask) and not _rows_equal(last, obs, mask)
    assert info == {}


# -- the async protocol and misuse (HTTPVectorEnv and gymnasium's AsyncVectorEnv) ---------------


def test_step_async_then_step_wait_is_a_step(make_async_vec):
    env = make_async_vec()
    env.reset(seed=0)
    env.step_async(_zeros(env))
    obs, reward, terminated, truncated, _ = env.step_wait(timeout=60)
    assert env.observation_space.contains(obs) and reward.shape == (NUM_ENVS,)


def test_step_wait_without_step_async_raises_no_async_call_error(make_async_vec):
    env = make_async_vec()
    env.reset(seed=0)
    with pytest.raises(NoAsyncCallError):
        env.step_wait()


def test_a_second_step_async_raises_already_pending_call_error(make_async_vec):
    env = make_async_vec()
    env.reset(seed=0)
    env.step_async(_zeros(env))
    with pytest.raises(AlreadyPendingCallError):
        env.step_async(_zeros(env))
    env.step_wait(timeout=60)


def test_reset_async_while_a_step_is_pending_raises_already_pending_call_error(make_async_vec):
    env = make_async_vec()
    env.reset(seed=0)
    env.step_async(_zeros(env))
    with pytest.raises(AlreadyPendingCallError):
        env.reset_async()
    env.step_wait(timeout=60)


def test_a_closed_env_raises_closed_environment_error(make_async_vec):
    env = make_async_vec()
    env.reset(seed=0)
    env.close()
    with pytest.raises(ClosedEnvironmentError):
        env.step_async(_zeros(env))


# -- HTTPVectorEnv's own options and errors ------------------------------------------------------


def test_state_ids_option_gives_the_task_envs_own_initial_observations(pod_urls):
    env = HTTPVectorEnv(pod_urls=pod_urls)
    try:
        obs, info = env.reset(options={"state_ids": [4, 0, 4, 49]})
        assert list(info["state_id"]) == [4, 0, 4, 49]
        single = _task_env()
        for i, state_id in enumerate([4, 0, 4, 49]):
            expected, _ = single.reset(options={"state_id": state_id})
            assert np.array_equal(obs[i], expected)
    finally:
        env.close()


def test_a_state_id_out_of_range_is_a_value_error_naming_the_env(pod_urls):
    env = HTTPVectorEnv(pod_urls=pod_urls)
    try:
        with pytest.raises(ValueError, match=r"state id 50 for env 2"):
            env.reset(options={"state_ids": [0, 0, 50, 0]})
        env.reset(seed=0)  # nothing was pending: the env is usable
    finally:
        env.close()


def test_stepping_before_any_reset_raises_reset_needed(pod_urls):
    env = HTTPVectorEnv(pod_urls=pod_urls)
    try:
        with pytest.raises(ResetNeeded):
            env.step(_zeros(env))
    finally:
        env.close()


def test_disabled_refuses_to_step_an_env_that_ended_until_it_is_reset(pod_urls):
    env = HTTPVectorEnv(pod_urls=pod_urls, autoreset_mode=AutoresetMode.DISABLED)
    try:
        env.reset(seed=0)
        _run_to_episode_end(env)
        with pytest.raises(ResetNeeded, match=r"envs \[0, 1, 2, 3\] ended"):
            env.step(_zeros(env))
        env.reset(options={"reset_mask": np.ones(NUM_ENVS, dtype=bool)})
        env.step(_zeros(env))
    finally:
        env.close()


def test_actions_of_the_wrong_shape_are_a_value_error(pod_urls):
    env = HTTPVectorEnv(pod_urls=pod_urls)
    try:
        env.reset(seed=0)
        with pytest.raises(ValueError, match=r"actions must have shape \[4, 1\]"):
            env.step(np.zeros((3, 1), dtype=np.float32))
        env.step(_zeros(env))
    finally:
        env.close()


def test_make_vec_builds_it_from_the_registered_id(pod_urls):
    env = gymnasium.make_vec("vecsim/HTTPVectorEnv-v0", num_envs=None, pod_urls=pod_urls)
    try:
        assert isinstance(env.unwrapped, HTTPVectorEnv)
        assert env.num_envs == NUM_ENVS
    finally:
        env.close()


def test_envs_are_laid_out_stage_major(pod_urls):
    env = HTTPVectorEnv(pod_urls=pod_urls)
    try:
        layout = [(r.stage_id, r.pod, r.env_index) for r in env.routes.values()]
        assert layout == [(0, "sim-0", 0), (0, "sim-0", 1), (1, "sim-1", 0), (1, "sim-1", 1)]
    finally:
        env.close()
