"""The client pieces every trainer adapter shares: numbering conventions, stepping ended envs
(raise / step / freeze) in StageClient and HTTPVectorEnv, and VLAEnv's subset chunk steps,
suite-global reset ids, camera keys, reward dtype and LIBERO's 8-float state."""

from __future__ import annotations

import re
from collections.abc import Iterator
from contextlib import closing

import numpy as np
import pytest
from gymnasium.error import ResetNeeded
from support.service_procs import PodSpec, RunningPod, post_wire, standalone_pods
from support.wire_http import metric

from vecsim import wire
from vecsim.client import HTTPVectorEnv, StageClient, VLAEnv
from vecsim.client.conventions import CAMERA_KEYS, StateNumbering, camera_key_map, suite_task_index
from vecsim.config import CameraConfig

TASK = "gym/HalfCheetah-v5"
EPISODE = 6  # episode limit: a chunk of 8 ends every fresh episode in its middle
K = 8
ACTION_DIM = 6
CAMERA = CameraConfig(height=8, width=8)


# -- conventions (pure) --------------------------------------------------------------------------


def test_suite_task_index_is_the_integer_after_the_suite():
    assert suite_task_index("libero_spatial/3") == 3
    assert suite_task_index("libero_90/41") == 41


@pytest.mark.parametrize("task_id", ["gym/HalfCheetah-v5", "libero_spatial", "/3", "libero_10/-1"])
def test_suite_task_index_names_an_id_without_an_integer_index(task_id):
    with pytest.raises(ValueError, match=re.escape(repr(task_id))):
        suite_task_index(task_id)


def test_global_state_ids_count_each_task_after_the_tasks_before_it():
    libero = StateNumbering([50] * 10)
    assert libero.global_state_id(3, 7) == 3 * 50 + 7
    assert libero.split_global_state_id(157) == (3, 7)
    uneven = StateNumbering([50, 20, 30])
    assert [uneven.global_state_id(t, 0) for t in range(3)] == [0, 50, 70]
    assert uneven.split_global_state_id(69) == (1, 19) and uneven.split_global_state_id(70) == (2, 0)
    assert all(
        uneven.split_global_state_id(uneven.global_state_id(t, r)) == (t, r)
        for t in range(3)
        for r in range(uneven.counts[t])
    )


def test_global_state_ids_out_of_range_are_named():
    numbering = StateNumbering([50, 20])
    with pytest.raises(ValueError, match="global state id 70 is outside 0..69"):
        numbering.split_global_state_id(70)
    with pytest.raises(ValueError, match="state row 20 of task 1"):
        numbering.global_state_id(1, 20)
    with pytest.raises(ValueError, match="task index 2"):
        numbering.global_state_id(2, 0)


def test_state_numbering_from_a_job_fills_unserved_tasks_only_when_counts_agree():
    numbering = StateNumbering.from_num_states(
        {"libero_goal/2": 50, "libero_goal/4": 50, "libero_10/0": 50}, "libero_goal"
    )
    assert numbering.counts == (50,) * 5
    with pytest.raises(ValueError, match=r"libero_goal/1"):
        StateNumbering.from_num_states({"libero_goal/0": 50, "libero_goal/2": 30}, "libero_goal")


def test_camera_key_presets_name_each_trainers_libero_inputs():
    # verl-vla src/verl_vla/envs/libero/libero_env.py:290-291.
    assert camera_key_map("verl_vla") == {
        "agentview": "observation.images.image",
        "robot0_eye_in_hand": "observation.images.wrist_image",
    }
    assert set(CAMERA_KEYS) == {"verl_vla", "lerobot", "rlinf"}
    assert camera_key_map({"agentview": "front"}) == {"agentview": "front"}


@pytest.mark.parametrize(
    ("camera_keys", "message"),
    [
        ("verl", "unknown preset 'verl'"),
        ({"agentview": "x", "robot0_eye_in_hand": "x"}, r"keys \['x'\]"),
        ({"agentview": ""}, "agentview"),
    ],
)
def test_camera_keys_that_are_no_mapping_are_refused(camera_keys, message):
    with pytest.raises(ValueError, match=message):
        camera_key_map(camera_keys)


# -- a job of two pods ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def pods(tmp_path_factory) -> Iterator[list[RunningPod]]:
    specs = [PodSpec(f"sim-{i}", 0, [(TASK, 2)], camera=CAMERA, max_episode_steps=EPISODE) for i in range(2)]
    with standalone_pods(specs, tmp_path_factory.mktemp("pods")) as running:
        yield running


def _step_requests(pods: list[RunningPod]) -> list[float]:
    """Each pod's count of step requests (its step-time histogram's count)."""
    return [metric(p.url, "vecsim_pod_step_seconds_count") for p in pods]


def _chunk(n: int, k: int = K, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-1.0, 1.0, (n, k, ACTION_DIM)).astype(np.float32)


def _reset(url: str, envs: list[int]) -> dict:
    body = {
        "generation": 0,
        "env_indices": np.array(envs, dtype=np.int64),
        "state_ids": np.zeros(len(envs), dtype=np.int64),
    }
    answer = post_wire(url, "reset", body, None)
    assert answer.status_code == 200, answer.text
    return wire.decode(answer.content)


def test_a_pod_steps_an_env_past_its_end_when_asked(pods):
    url = pods[0].url
    _reset(url, [0, 1])
    body = {"generation": 0, "env_indices": np.array([0, 1], dtype=np.int64), "actions": _chunk(2)}
    stopped = wire.decode(post_wire(url, "step", body, None).content)
    _reset(url, [0, 1])
    past = wire.decode(post_wire(url, "step", {**body, "step_past_end": True}, None).content)
    assert stopped["num_steps"].tolist() == [EPISODE, EPISODE]
    assert past["num_steps"].tolist() == [K, K]
    # Up to the end both are one trajectory; after it the episode limit keeps counting and the
    # physics go on (rewards of the extra actions are the scene's, not zeros).
    assert np.array_equal(past["reward"][:, :EPISODE], stopped["reward"][:, :EPISODE])
    assert past["truncated"][:, EPISODE - 1 :].all() and not past["truncated"][:, : EPISODE - 1].any()
    assert (past["reward"][:, EPISODE:] != 0).all()
    assert not np.array_equal(past["obs"]["proprio"], stopped["obs"]["proprio"])


def test_a_pod_refuses_step_past_end_for_one_action_steps_and_changes_nothing(pods):
    url = pods[0].url
    before = _reset(url, [0])
    body = {
        "generation": 0,
        "env_indices": np.array([0], dtype=np.int64),
        "actions": _chunk(1)[:, 0],
        "step_past_end": True,
    }
    answer = post_wire(url, "step", body, None)
    assert answer.status_code == 422 and "step_past_end" in answer.text
    after = wire.decode(
        post_wire(
            url, "step", {**body, "step_past_end": False, "actions": np.zeros((1, ACTION_DIM), np.float32)}, None
        ).content
    )
    reference = _reset(url, [0])
    again = wire.decode(
        post_wire(
            url, "step", {**body, "step_past_end": False, "actions": np.zeros((1, ACTION_DIM), np.float32)}, None
        ).content
    )
    assert np.array_equal(after["obs"]["proprio"], again["obs"]["proprio"])  # the refused call moved nothing
    assert np.array_equal(before["obs"]["proprio"], reference["obs"]["proprio"])


# -- StageClient ---------------------------------------------------------------------------------


def _stage_client(pods, ended_envs: str) -> tuple[StageClient, list[str]]:
    client = StageClient.from_pods([p.url for p in pods], ended_envs=ended_envs)
    routes = client.reset_trajectories([(TASK, 0)] * 4)
    client.reset_stage(0).result(60)
    return client, list(routes)


def test_stage_client_refuses_to_step_an_ended_trajectory_before_sending_anything(pods):
    client, keys = _stage_client(pods, "raise")
    with client:
        first = client.step_stage(0, dict(zip(keys, _chunk(4)))).result(60)
        assert first.num_steps.tolist() == [EPISODE] * 4 and client.ended_traj_keys == sorted(keys)
        sent = _step_requests(pods)
        with pytest.raises(ResetNeeded, match=re.escape(keys[0])):
            client.step_stage(0, dict(zip(keys, _chunk(4))))
        assert _step_requests(pods) == sent
        client.reset_stage(0, keys[:1]).result(60)
        assert client.step_stage(0, {keys[0]: _chunk(1)[0]}).result(60).num_steps.tolist() == [EPISODE]


def test_stage_client_steps_ended_trajectories_on_through_whole_chunks(pods):
    client, keys = _stage_client(pods, "step")
    with client:
        first = client.step_stage(0, dict(zip(keys, _chunk(4, seed=1)))).result(60)
        second = client.step_stage(0, dict(zip(keys, _chunk(4, seed=2)))).result(60)
    assert first.num_steps.tolist() == second.num_steps.tolist() == [K] * 4
    assert first.truncated[:, EPISODE - 1].all() and second.truncated.all()  # the limit keeps counting
    assert (second.reward != 0).all()


def test_stage_client_freezes_ended_trajectories_without_a_request(pods):
    client, keys = _stage_client(pods, "freeze")
    with client:
        first = client.step_stage(0, dict(zip(keys, _chunk(4, seed=1)))).result(60)
        sent = _step_requests(pods)
        frozen = client.step_stage(0, dict(zip(keys, _chunk(4, seed=2)))).result(60)
        assert _step_requests(pods) == sent  # every trajectory ended: no pod was asked
    assert first.num_steps.tolist() == [EPISODE] * 4
    assert frozen.num_steps.tolist() == [0] * 4 and not frozen.reward.any()
    assert frozen.truncated.all() and not frozen.terminated.any()  # flags held as at the end
    assert np.array_equal(frozen.obs["proprio"], first.obs["proprio"])


def test_stage_client_freezes_only_the_ended_trajectories_of_a_call(pods):
    client, keys = _stage_client(pods, "freeze")
    with client:
        client.step_stage(0, dict(zip(keys, _chunk(4, seed=1)))).result(60)
        routes = client.routes
        on_first = [k for k in keys if routes[k].pod == "sim-0"]
        client.reset_stage(0, on_first).result(60)
        sent = _step_requests(pods)
        batch = client.step_stage(0, dict(zip(keys, _chunk(4, seed=2)))).result(60)
        assert _step_requests(pods) == [sent[0] + 1, sent[1]]  # only the pod with live trajectories
    steps = dict(zip(batch.traj_keys, batch.num_steps.tolist()))
    assert all(steps[k] == EPISODE for k in on_first) and all(steps[k] == 0 for k in keys if k not in on_first)
    assert client.ended_traj_keys == sorted(keys)  # the reset ones ended again in this chunk


def test_ended_envs_must_be_a_known_mode(pods):
    with pytest.raises(ValueError, match="ended_envs must be one of"):
        StageClient.from_pods([pods[0].url], ended_envs="skip")


# -- HTTPVectorEnv -------------------------------------------------------------------------------


@pytest.mark.parametrize("ended_envs", ["step", "freeze"])
def test_vector_env_without_autoreset_goes_on_after_an_episode_ends_mid_chunk(pods, ended_envs):
    with closing(
        HTTPVectorEnv(pod_urls=[p.url for p in pods], autoreset_mode="disabled", ended_envs=ended_envs)
    ) as env:
        env.reset(seed=0, options={"state_ids": np.zeros(4, dtype=np.int64)})
        first = env.chunk_step(_chunk(4, seed=1))
        obs, reward, _, truncated, info = env.chunk_step(_chunk(4, seed=2))
    assert first[4]["num_steps"].tolist() == ([K] if ended_envs == "step" else [EPISODE]) * 4
    assert truncated.all()
    if ended_envs == "step":
        assert info["num_steps"].tolist() == [K] * 4 and (reward != 0).all()
    else:
        assert info["num_steps"].tolist() == [0] * 4 and not reward.any()
        assert np.array_equal(obs["proprio"], first[0]["proprio"])


def test_vector_env_chunk_step_of_a_subset_sends_nothing_to_pods_without_its_envs(pods):
    with closing(HTTPVectorEnv(pod_urls=[p.url for p in pods], autoreset_mode="disabled")) as env:
        before, _ = env.reset(seed=0, options={"state_ids": np.zeros(4, dtype=np.int64)})
        sent = _step_requests(pods)
        obs, reward, _, _, info = env.chunk_step(_chunk(1, k=3), env_ids=[1])
        assert _step_requests(pods) == [sent[0] + 1, sent[1]]  # env 1 is the first pod's
    assert info["num_steps"].tolist() == [0, 3, 0, 0] and info["_num_steps"].tolist() == [False, True, False, False]
    assert not reward[[0, 2, 3]].any() and reward[1].all()
    assert np.array_equal(obs["proprio"][[0, 2, 3]], before["proprio"][[0, 2, 3]])
    assert not np.array_equal(obs["proprio"][1], before["proprio"][1])


# -- VLAEnv --------------------------------------------------------------------------------------


def test_vla_env_steps_a_subset_in_one_request_per_pod_that_holds_it(pods):
    with VLAEnv(pod_urls=[p.url for p in pods], reward_dtype=np.float32) as env:
        env.reset(state_ids=np.zeros(4, dtype=np.int64))
        sent = _step_requests(pods)
        obs, rewards, terminations, truncations, infos = env.chunk_step(_chunk(2, k=4), env_ids=[3, 0])
        assert _step_requests(pods) == [sent[0] + 1, sent[1] + 1]
    assert rewards.dtype == np.float32 and rewards.shape == terminations.shape == truncations.shape == (2, 4)
    assert obs["proprio"].shape[0] == 2 and obs["task_id"] == [TASK, TASK]
    assert infos["num_steps"].tolist() == [4, 4]


def test_vla_env_refuses_a_subset_chunk_of_the_wrong_shape_and_steps_nothing(pods):
    with VLAEnv(pod_urls=[p.url for p in pods]) as env:
        env.reset(state_ids=np.zeros(4, dtype=np.int64))
        sent = _step_requests(pods)
        with pytest.raises(ValueError, match=r"chunk actions must have shape \[2, 'K', 6\]"):
            env.chunk_step(_chunk(3), env_ids=[0, 1])
        with pytest.raises(ValueError, match="env_ids must be distinct env indices 0..3"):
            env.chunk_step(_chunk(2), env_ids=[0, 4])
        with pytest.raises(ValueError, match="env_ids must be distinct"):
            env.chunk_step(_chunk(2), env_ids=[1, 1])
        assert _step_requests(pods) == sent


def test_vla_env_task_indices_name_the_task_without_an_integer_index(pods):
    with VLAEnv(pod_urls=[p.url for p in pods]) as env:
        with pytest.raises(ValueError, match=re.escape(repr(TASK))):
            env.task_indices  # noqa: B018 - the property raises


def test_vla_env_refuses_an_unknown_reward_dtype_or_camera_preset(pods):
    with pytest.raises(ValueError, match="reward_dtype"):
        VLAEnv(pod_urls=[pods[0].url], reward_dtype=np.int32)
    with pytest.raises(ValueError, match="camera_keys"):
        VLAEnv(pod_urls=[pods[0].url], camera_keys="openvla")


# -- LIBERO: the 8-float state, int task indices, suite-global ids, camera keys -------------------


@pytest.fixture(scope="module")
def libero_pod(tmp_path_factory) -> Iterator[RunningPod]:
    spec = PodSpec(
        "libero-0",
        0,
        [("libero_spatial/0", 1), ("libero_spatial/3", 1)],
        camera=CameraConfig(height=32, width=32),
        max_episode_steps=20,
    )
    with standalone_pods([spec], tmp_path_factory.mktemp("libero")) as running:
        yield running[0]


@pytest.mark.libero
def test_vla_env_hands_libero_state_to_the_policy_under_the_trainers_keys(libero_pod):
    with VLAEnv(pod_urls=[libero_pod.url], keys="lerobot", camera_keys="verl_vla") as env:
        obs, _ = env.reset(state_ids=[0, 0])
        raw = env.vector_env.reset(
            options={"reset_mask": np.ones(2, dtype=bool), "state_ids": np.zeros(2, dtype=np.int64)}
        )[0]
    assert env.task_indices == [0, 3]
    assert obs["observation.state"].shape == (2, 8) and np.array_equal(obs["observation.state"], raw["state"])
    assert set(k for k in obs if k.startswith("observation.images.")) == {
        "observation.images.image",
        "observation.images.wrist_image",
    }
    assert np.array_equal(obs["observation.images.image"], raw["images"]["agentview"])


@pytest.mark.libero
def test_vla_env_vecsim_keys_carry_state_beside_proprio(libero_pod):
    with VLAEnv(pod_urls=[libero_pod.url]) as env:
        obs, _ = env.reset(state_ids=[1, 1])
    assert obs["state"].shape == (2, 8) and obs["proprio"].shape[1] != 8


@pytest.mark.libero
def test_vla_env_resets_to_suite_global_state_ids_of_each_envs_own_task(libero_pod):
    with VLAEnv(pod_urls=[libero_pod.url]) as env:
        by_row, info_row = env.reset(state_ids=[7, 9])
        by_global, info_global = env.reset(global_state_ids=[0 * 50 + 7, 3 * 50 + 9])
        assert info_global["state_id"].tolist() == [7, 9]
        assert np.array_equal(by_row["state"], by_global["state"])
        with pytest.raises(
            ValueError, match=r"id 57 of env 0 is a state of task libero_spatial/1, but env 0 runs libero_spatial/0"
        ):
            env.reset(global_state_ids=[57, 150])
        with pytest.raises(ValueError, match="env 1 .*global state id 500 is outside 0..199"):
            env.reset(global_state_ids=[7, 500])
        unchanged, _ = env.reset(env_ids=[])
    assert np.array_equal(unchanged["state"], by_global["state"])  # the refused resets changed no env
