"""TaskGroupedVectorEnv, a pod's engine, on real worker processes and real scenes.

Most behaviour is shown on gymnasium's HalfCheetah (cheap physics, no rendering); the robot path
on the tiny suite with 8x8 cameras; one LIBERO task shows that a pod reproduces LIBERO's own
init state. Pods are shared per module where the tests reset what they use first.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from support.sim_envs import CAMERAS, TINY_CAMERA, env_rows, kill_worker, sim_assignment

from vecsim.config import CameraConfig
from vecsim.engine import (
    InvalidRequestError,
    SimBuildError,
    SimCrashedError,
    TaskGroupedVectorEnv,
    UnknownEnvError,
)
from vecsim.engine.tasks import UnknownTaskError, make_env

CHEETAH = "gym/HalfCheetah-v5"


def _batched(obs: dict[str, Any]) -> dict[str, Any]:
    """One env's observation as a batch of one."""
    return {key: _batched(value) if isinstance(value, dict) else value[None] for key, value in obs.items()}


def _actions(n: int, size: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-1.0, 1.0, (n, size)).astype(np.float32)


@pytest.fixture(scope="module")
def cheetahs() -> Iterator[TaskGroupedVectorEnv]:
    """Four HalfCheetahs, one per worker, with 2-step episodes."""
    with TaskGroupedVectorEnv(sim_assignment([(CHEETAH, 4)], max_episode_steps=2)) as pod:
        yield pod


@pytest.fixture(scope="module")
def tiny_pods() -> Iterator[tuple[TaskGroupedVectorEnv, TaskGroupedVectorEnv]]:
    """The tiny suite twice: two envs per worker (lift, lift | stack, door), and one."""
    blocks = [("tiny/lift", 2), ("tiny/stack", 1), ("tiny/door", 1)]
    with TaskGroupedVectorEnv(sim_assignment(blocks, TINY_CAMERA, envs_per_worker=2)) as packed:
        with TaskGroupedVectorEnv(sim_assignment(blocks, TINY_CAMERA, envs_per_worker=1)) as single:
            yield packed, single


def _unchanged_after(pod: TaskGroupedVectorEnv, action: Any) -> bool:
    """Run ``action(pod)`` between a reset and a step of every env; True if the step is as without it.

    The pod's episodes are 2 steps long, so a hidden step would also show as truncation.
    """
    ids = np.arange(pod.num_envs)
    states = ids + 1
    moves = _actions(pod.num_envs, 6)
    pod.reset_envs(ids, states)
    expected = pod.step_envs(ids, moves)
    pod.reset_envs(ids, states)
    action(pod)
    got = pod.step_envs(ids, moves)
    return env_rows(got[0]) == env_rows(expected[0]) and all(
        np.array_equal(a, b) for a, b in zip(got[1:4], expected[1:4])
    )


# Layout and spaces.


def test_env_indices_form_contiguous_task_blocks(tiny_pods: tuple[TaskGroupedVectorEnv, ...]) -> None:
    packed, single = tiny_pods
    assert packed.task_ids == ["tiny/lift", "tiny/lift", "tiny/stack", "tiny/door"]
    assert (packed.num_envs, packed.num_workers, single.num_workers) == (4, 2, 4)
    assert packed.single_observation_space["proprio"].shape == (23,)
    assert set(packed.single_observation_space["images"].spaces) == set(CAMERAS)
    assert packed.single_action_space.shape == (7,)


def test_a_block_of_five_with_two_envs_per_worker_uses_three_workers() -> None:
    with TaskGroupedVectorEnv(sim_assignment([(CHEETAH, 5)], envs_per_worker=2)) as packed:
        assert (packed.num_envs, packed.num_workers, len(set(packed.worker_pids))) == (5, 3, 3)
        with pytest.raises(UnknownEnvError):
            packed.step_envs([5], _actions(1, 6))
        with TaskGroupedVectorEnv(sim_assignment([(CHEETAH, 5)])) as single:
            for pod in (packed, single):
                pod.reset_envs([4, 0, 2, 1, 3], [4, 0, 2, 1, 3])
                pod.step_envs([4, 1], _actions(2, 6, seed=1))
            packed_out = packed.step_envs(np.arange(5), _actions(5, 6, seed=2))
            single_out = single.step_envs(np.arange(5), _actions(5, 6, seed=2))
    assert env_rows(packed_out[0]) == env_rows(single_out[0])
    assert np.array_equal(packed_out[1], single_out[1])


# Deterministic resets.


def test_reset_is_bit_identical_across_pods_orders_and_histories(
    tiny_pods: tuple[TaskGroupedVectorEnv, ...],
) -> None:
    packed, single = tiny_pods
    moves = _actions(4, 7, seed=3)
    packed.reset_envs([0, 1, 2, 3], [3, 3, 3, 3])
    packed.step_envs([0, 1, 2, 3], moves)
    packed.reset_envs([3, 2, 1, 0], [5, 5, 5, 5])
    used, _ = packed.reset_envs([2, 0, 3, 1], [3, 3, 3, 3])
    fresh, _ = single.reset_envs([2, 0, 3, 1], [3, 3, 3, 3])
    assert env_rows(used) == env_rows(fresh)
    order = [2, 0, 3, 1]
    used_step = packed.step_envs(order, moves[order])
    fresh_step = single.step_envs(order, moves[order])
    assert env_rows(used_step[0]) == env_rows(fresh_step[0])


def test_reset_matches_the_same_task_env_built_in_this_process(
    tiny_pods: tuple[TaskGroupedVectorEnv, ...],
) -> None:
    packed, _ = tiny_pods
    local = make_env("tiny/door", TINY_CAMERA, "lean", max_episode_steps=300)
    try:
        mine, _ = local.reset(options={"state_id": 8})
    finally:
        local.close()
    theirs, info = packed.reset_envs([3], [8])
    assert info["task_id"] == ["tiny/door"]
    assert env_rows(theirs) == env_rows(_batched(mine))


def test_two_envs_of_one_worker_render_their_own_scenes(tiny_pods: tuple[TaskGroupedVectorEnv, ...]) -> None:
    packed, single = tiny_pods
    for pod in tiny_pods:
        pod.reset_envs([0, 1], [1, 2])
    moves = _actions(2, 7, seed=4)
    assert env_rows(packed.step_envs([0, 1], moves)[0]) == env_rows(single.step_envs([0, 1], moves)[0])


# Only named envs change.


def test_stepping_some_envs_leaves_the_others_where_they_were(cheetahs: TaskGroupedVectorEnv) -> None:
    cheetahs.reset_envs([0, 1, 2, 3], [2, 2, 2, 2])
    cheetahs.step_envs([1], _actions(1, 6, seed=5))
    cheetahs.reset_envs([3], [2])
    same = np.repeat(_actions(1, 6, seed=6), 3, axis=0)
    obs, _, _, truncated, _ = cheetahs.step_envs([0, 2, 3], same)
    rows = env_rows(obs)
    assert rows[0] == rows[1] == rows[2]
    assert not truncated.any()


def test_resetting_some_envs_leaves_the_others_where_they_were(cheetahs: TaskGroupedVectorEnv) -> None:
    first = _actions(4, 6, seed=7)
    cheetahs.reset_envs([0, 1, 2, 3], [1, 1, 1, 1])
    one_step = env_rows(cheetahs.step_envs([0, 1, 2, 3], first)[0])
    cheetahs.reset_envs([2], [1])
    again = np.repeat(first[:1], 4, axis=0)
    obs, _, _, truncated, _ = cheetahs.step_envs([0, 1, 2, 3], again)
    rows = env_rows(obs)
    assert rows[2] == one_step[0]
    assert rows[0] != rows[2]
    assert truncated.tolist() == [True, True, False, True]


def test_frame_is_what_that_env_saw_last(tiny_pods: tuple[TaskGroupedVectorEnv, ...]) -> None:
    packed, _ = tiny_pods
    obs, _ = packed.reset_envs([2, 3], [4, 6])
    stepped = packed.step_envs([3], _actions(1, 7, seed=8))[0]
    assert np.array_equal(packed.frame(2, "agentview"), obs["images"]["agentview"][0])
    assert np.array_equal(packed.frame(3, "robot0_eye_in_hand"), stepped["images"]["robot0_eye_in_hand"][0])
    assert packed.frame(2, "agentview").dtype == np.uint8 and packed.frame(2, "agentview").shape == (8, 8, 3)


# Episodes.


def test_truncation_counts_steps_since_each_envs_own_reset(cheetahs: TaskGroupedVectorEnv) -> None:
    cheetahs.reset_envs([0, 1], [0, 0])
    cheetahs.step_envs([0, 1], _actions(2, 6))
    cheetahs.reset_envs([1], [0])
    _, _, terminated, truncated, info = cheetahs.step_envs([0, 1], _actions(2, 6))
    assert truncated.tolist() == [True, False]
    assert terminated.dtype == bool and info["success"].dtype == bool


def test_results_have_the_documented_types(tiny_pods: tuple[TaskGroupedVectorEnv, ...]) -> None:
    packed, _ = tiny_pods
    obs, info = packed.reset_envs(np.array([1, 3]), np.array([0, 0]))
    assert info["success"].dtype == bool and info["task_id"] == ["tiny/lift", "tiny/door"]
    assert obs["images"]["agentview"].shape == (2, 8, 8, 3) and obs["images"]["agentview"].dtype == np.uint8
    obs, reward, terminated, truncated, info = packed.step_envs([1, 3], _actions(2, 7))
    assert obs["proprio"].shape == (2, 23) and obs["proprio"].dtype == np.float32
    assert reward.dtype == np.float64 and reward.shape == (2,)
    assert terminated.dtype == truncated.dtype == info["success"].dtype == bool


# Bad input: the named error, and nothing changes.


def _bad(case_id: str, error: type[Exception], message: str, call: Any) -> Any:
    return pytest.param(error, message, call, id=case_id)


BAD_CALLS = [
    _bad("reset_unknown_env", UnknownEnvError, "env 4 does not exist", lambda p: p.reset_envs([0, 4], [0, 0])),
    _bad("reset_negative_env", UnknownEnvError, "env -1 does not exist", lambda p: p.reset_envs([-1], [0])),
    _bad("step_unknown_env", UnknownEnvError, "env 9 does not exist", lambda p: p.step_envs([9], _actions(1, 6))),
    _bad("reset_twice", InvalidRequestError, "env 1 is named more than once", lambda p: p.reset_envs([1, 1], [0, 0])),
    _bad("step_twice", InvalidRequestError, "env 2 is named", lambda p: p.step_envs([2, 0, 2], _actions(3, 6))),
    _bad(
        "float_env_indices", InvalidRequestError, "env_indices: expected integers", lambda p: p.reset_envs([0.0], [0])
    ),
    _bad("nested_env_indices", InvalidRequestError, "env_indices: expected a 1-d", lambda p: p.reset_envs([[0]], [0])),
    _bad("negative_state", InvalidRequestError, "state -1 for env 1", lambda p: p.reset_envs([0, 1], [0, -1])),
    _bad("state_too_large", InvalidRequestError, "state 50 for env 0 .* 0..49", lambda p: p.reset_envs([0], [50])),
    _bad("fewer_states", InvalidRequestError, "1 state ids for 2 env_indices", lambda p: p.reset_envs([0, 1], [0])),
    _bad("fewer_actions", InvalidRequestError, r"shape \(2, 6\)", lambda p: p.step_envs([0, 1], _actions(1, 6))),
    _bad("wide_actions", InvalidRequestError, r"shape \(1, 6\)", lambda p: p.step_envs([0], _actions(1, 7))),
    _bad("text_actions", InvalidRequestError, "expected numbers", lambda p: p.step_envs([0], [["a"] * 6])),
    _bad("bool_actions", InvalidRequestError, "expected numbers", lambda p: p.step_envs([0], np.ones((1, 6), bool))),
    _bad("ragged_actions", InvalidRequestError, "not a rectangular", lambda p: p.step_envs([0, 1], [[0.0] * 6, [0.0]])),
    _bad(
        "nan_action", InvalidRequestError, "env 3 is not finite", lambda p: p.step_envs([0, 3], [[0] * 6, [np.nan] * 6])
    ),
    _bad("inf_action", InvalidRequestError, "env 1 is not finite", lambda p: p.step_envs([1], np.full((1, 6), np.inf))),
    _bad("huge_action", InvalidRequestError, "env 0 is not finite", lambda p: p.step_envs([0], np.full((1, 6), 1e300))),
    _bad("actions_for_no_envs", InvalidRequestError, r"shape \(0, 6\)", lambda p: p.step_envs([], _actions(1, 6))),
    _bad("frame_unknown_env", UnknownEnvError, "env 7 does not exist", lambda p: p.frame(7, "render")),
    _bad("frame_unknown_camera", InvalidRequestError, "no camera 'agentview'", lambda p: p.frame(0, "agentview")),
]


@pytest.mark.parametrize(("error", "message", "call"), BAD_CALLS)
def test_bad_input_raises_its_named_error_and_changes_nothing(
    cheetahs: TaskGroupedVectorEnv, error: type[Exception], message: str, call: Any
) -> None:
    def rejected(pod: TaskGroupedVectorEnv) -> None:
        with pytest.raises(error, match=message):
            call(pod)

    assert _unchanged_after(cheetahs, rejected)


def test_empty_env_lists_are_no_ops_with_empty_results(cheetahs: TaskGroupedVectorEnv) -> None:
    answers: list[Any] = []

    def empty_calls(pod: TaskGroupedVectorEnv) -> None:
        answers.append(pod.reset_envs([], []))
        answers.append(pod.step_envs(np.zeros(0, np.int64), np.zeros((0, 6), np.float32)))
        answers.append(pod.step_envs([], []))

    assert _unchanged_after(cheetahs, empty_calls)
    (obs, info), (step_obs, reward, terminated, truncated, step_info), _ = answers
    assert obs.shape == step_obs.shape == (0, 17)  # HalfCheetah's own observation, no envs
    assert info == {"success": info["success"], "task_id": [], "env_info": [], "errors": []}
    assert info["success"].shape == (0,)
    assert reward.shape == terminated.shape == truncated.shape == step_info["success"].shape == (0,)


def test_a_spare_pod_has_no_envs_and_no_processes() -> None:
    with TaskGroupedVectorEnv(sim_assignment([])) as spare:
        assert (spare.num_envs, spare.num_workers, spare.worker_pids, spare.task_ids) == (0, 0, [], [])
        obs, info = spare.reset_envs([], [])
        assert obs == {} and info["task_id"] == []
        assert spare.step_envs([], [])[1].shape == (0,)
        with pytest.raises(UnknownEnvError, match="this pod has no envs"):
            spare.reset_envs([0], [0])


def test_a_task_block_of_zero_envs_builds_nothing_for_it() -> None:
    with TaskGroupedVectorEnv(sim_assignment([(CHEETAH, 0), (CHEETAH, 1)])) as pod:
        assert (pod.num_envs, pod.num_workers, pod.task_ids) == (1, 1, [CHEETAH])


def test_an_unknown_task_fails_before_any_process_starts() -> None:
    with pytest.raises(UnknownTaskError, match="'tiny/nope'"):
        TaskGroupedVectorEnv(sim_assignment([("tiny/nope", 1)]))


def test_tasks_with_different_spaces_cannot_share_a_pod() -> None:
    with pytest.raises(InvalidRequestError, match="gym/Hopper-v5"):
        TaskGroupedVectorEnv(sim_assignment([(CHEETAH, 1), ("gym/Hopper-v5", 1)]))


def test_a_failed_build_names_the_task_and_the_problem() -> None:
    camera = CameraConfig(names=("no_such_camera",), height=8, width=8)
    with pytest.raises(SimBuildError, match=r"tiny/door \(envs 0-0\).*no_such_camera"):
        TaskGroupedVectorEnv(sim_assignment([("tiny/door", 1)], camera))


def test_a_dead_worker_makes_every_call_raise_sim_crashed() -> None:
    with TaskGroupedVectorEnv(sim_assignment([(CHEETAH, 2)])) as pod:
        kill_worker(pod.worker_pids[1])
        with pytest.raises(SimCrashedError):
            pod.step_envs([0], _actions(1, 6))
        with pytest.raises(SimCrashedError, match="worker 1"):
            pod.reset_envs([0], [0])
        with pytest.raises(UnknownEnvError):
            pod.reset_envs([2], [0])


def test_calls_after_close_raise_sim_crashed() -> None:
    pod = TaskGroupedVectorEnv(sim_assignment([(CHEETAH, 1)]))
    pod.close()
    pod.close()
    with pytest.raises(SimCrashedError, match="closed"):
        pod.step_envs([0], _actions(1, 6))


# LIBERO.


@pytest.mark.libero
def test_a_libero_pod_reproduces_the_same_libero_scene_as_this_process() -> None:
    local = make_env("libero_10/0", TINY_CAMERA, "lean", max_episode_steps=300)
    try:
        mine = [local.reset(options={"state_id": 7})[0]]
        mine += [local.step(action)[0] for action in _actions(2, 7, seed=9)]
    finally:
        local.close()
    with TaskGroupedVectorEnv(sim_assignment([("libero_10/0", 1)], TINY_CAMERA, render="lean")) as pod:
        pod.step_envs([0], _actions(1, 7, seed=10))
        theirs = [pod.reset_envs([0], [7])[0]]
        theirs += [pod.step_envs([0], action[None])[0] for action in _actions(2, 7, seed=9)]
    assert [env_rows(_batched(obs)) for obs in mine] == [env_rows(obs) for obs in theirs]
