"""Action chunks end to end, on real pods over loopback: the pod's ``POST /v1/step`` with actions
``[n, K, action dim]``, ``HTTPVectorEnv.chunk_step``, ``EnvLoop`` with a chunking policy.

The task is ``gym/HalfCheetah-v5`` (cheap physics) with one 8x8 camera (so renders can be counted
and frames compared) and 6-step episodes, so a chunk of 8 is cut short by truncation. Two
standalone pods, one per stage, four envs each over two workers. Every test resets the envs it
uses first.
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import Iterator
from typing import Any

import httpx
import numpy as np
import pytest
import torch
from gymnasium.vector import AutoresetMode
from PIL import Image
from support.service_procs import PodSpec, RunningPod, post_wire, standalone_pods
from support.wire_http import metric

from vecsim import wire
from vecsim.client import HTTPVectorEnv, StageClient, VLAEnv
from vecsim.config import CameraConfig
from vecsim.rollout import EnvLoop
from vecsim.engine import DEFAULT_MAX_CHUNK

TASK = "gym/HalfCheetah-v5"
EPISODE = 6
ACTION_DIM = 6
CAMERA = CameraConfig(height=8, width=8)
IMAGE = "render"  # a gym task's one camera image


@pytest.fixture(scope="module")
def pods(tmp_path_factory) -> Iterator[list[RunningPod]]:
    specs = [
        PodSpec(f"sim-{stage}", stage, [(TASK, 4)], camera=CAMERA, max_episode_steps=EPISODE, envs_per_worker=2)
        for stage in range(2)
    ]
    with standalone_pods(specs, tmp_path_factory.mktemp("pods")) as running:
        yield running


@pytest.fixture
def pod(pods) -> str:
    return pods[0].url


def _answer(response: httpx.Response) -> dict[str, Any]:
    assert response.status_code == 200, response.text
    if response.headers["content-type"].startswith("application/json"):
        return response.json()
    return wire.decode(response.content)


def _reset(url: str, env_indices: list[int], state_ids: list[int]) -> dict[str, Any]:
    body = {"generation": 0, "env_indices": np.array(env_indices), "state_ids": np.array(state_ids)}
    return _answer(post_wire(url, "reset", body, None))


def _step(url: str, env_indices: list[int], actions: np.ndarray, **extra: Any) -> dict[str, Any]:
    body = {"generation": 0, "env_indices": np.array(env_indices), "actions": np.asarray(actions, np.float32), **extra}
    return _answer(post_wire(url, "step", body, None))


def _chunk(n: int, k: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-1.0, 1.0, (n, k, ACTION_DIM)).astype(np.float32)


def _singles(url: str, env: int, actions: np.ndarray) -> tuple[list[dict[str, Any]], list[float], list[bool]]:
    """Step one env one action at a time; return each step's answer, rewards and truncations."""
    answers = [_step(url, [env], action[None]) for action in actions]
    return answers, [float(a["reward"][0]) for a in answers], [bool(a["truncated"][0]) for a in answers]


def _same_obs(a: dict[str, Any], row_a: int, b: dict[str, Any], row_b: int) -> bool:
    return np.array_equal(a["proprio"][row_a], b["proprio"][row_b]) and np.array_equal(
        a["images"][IMAGE][row_a], b["images"][IMAGE][row_b]
    )


# -- the pod -------------------------------------------------------------------------------------


def test_info_states_the_longest_chunk_a_step_takes(pod):
    assert httpx.get(f"{pod}/v1/info", timeout=10).json()["max_chunk"] == DEFAULT_MAX_CHUNK


def test_a_chunk_of_k_gives_bit_for_bit_what_k_single_steps_give(pod):
    chunk = _chunk(1, 4)
    _reset(pod, [0, 3], [5, 5])  # envs of two different workers
    answer = _step(pod, [0], chunk)
    singles, rewards, _ = _singles(pod, 3, chunk[0])
    assert answer["reward"].tolist() == [rewards]
    assert answer["num_steps"].tolist() == [4]
    assert not answer["terminated"].any() and not answer["truncated"].any()
    assert _same_obs(answer["obs"], 0, singles[-1]["obs"], 0)


def test_an_env_stops_at_its_truncation_inside_a_chunk_and_reports_its_steps(pod):
    chunk = _chunk(2, 8, seed=1)
    _reset(pod, [0, 1, 2], [0, 0, 0])
    _step(pod, [1], _chunk(1, 1, seed=9)[0])  # env 1 is one step into its episode: 5 steps left
    answer = _step(pod, [0, 1], chunk)
    assert answer["num_steps"].tolist() == [EPISODE, EPISODE - 1]
    assert answer["truncated"][0].tolist() == [False] * 5 + [True, False, False]
    assert answer["truncated"][1].tolist() == [False] * 4 + [True, False, False, False]
    assert (answer["reward"][0, EPISODE:] == 0).all() and (answer["reward"][1, EPISODE - 1 :] == 0).all()
    singles, rewards, truncated = _singles(pod, 2, chunk[0, :EPISODE])
    assert answer["reward"][0, :EPISODE].tolist() == rewards and truncated[-1]
    assert _same_obs(answer["obs"], 0, singles[-1]["obs"], 0)


def test_a_chunk_renders_each_env_once_and_counts_every_applied_action(pod):
    _reset(pod, [0, 1, 2], [1, 2, 3])
    renders, steps = metric(pod, "vecsim_pod_env_renders"), metric(pod, "vecsim_pod_env_steps")
    _step(pod, [0, 1, 2], _chunk(3, 4))
    assert metric(pod, "vecsim_pod_env_renders") - renders == 3
    assert metric(pod, "vecsim_pod_env_steps") - steps == 12


def test_recorded_envs_answer_every_actions_frame_and_only_they_render_more(pod):
    chunk = _chunk(2, 4, seed=2)
    _reset(pod, [0, 1, 2], [4, 4, 4])
    renders = metric(pod, "vecsim_pod_env_renders")
    answer = _step(pod, [0, 1], chunk, record_env_indices=np.array([1]))
    assert metric(pod, "vecsim_pod_env_renders") - renders == 2 + 3
    frames = answer["frames"][IMAGE]
    assert frames.shape == (1, 4, CAMERA.height, CAMERA.width, 3)
    singles, _, _ = _singles(pod, 2, chunk[1])
    for k, single in enumerate(singles):
        assert np.array_equal(frames[0, k], single["obs"]["images"][IMAGE][0])
    assert np.array_equal(frames[0, 3], answer["obs"]["images"][IMAGE][1])


def test_one_action_per_env_is_answered_as_before_chunks(pod):
    chunk = _chunk(1, 1, seed=3)
    _reset(pod, [0, 1], [6, 6])
    single = _step(pod, [0], chunk[0])
    as_chunk = _step(pod, [1], chunk)
    assert set(single) == {"env_indices", "obs", "reward", "terminated", "truncated", "info"}
    assert single["reward"].shape == (1,) and single["info"]["success"].shape == (1,)
    assert single["reward"].tolist() == as_chunk["reward"][:, 0].tolist()
    assert _same_obs(single["obs"], 0, as_chunk["obs"], 0)


def test_a_chunk_without_envs_is_a_no_op_answering_empty_per_action_arrays(pod):
    steps = metric(pod, "vecsim_pod_env_steps")
    answer = _step(pod, [], np.zeros((0, 4, ACTION_DIM)))
    assert answer["reward"].shape == (0, 4) and answer["num_steps"].shape == (0,)
    assert metric(pod, "vecsim_pod_env_steps") == steps


def test_a_chunk_of_no_actions_moves_nothing_and_answers_the_current_observation(pod):
    reset = _reset(pod, [0], [7])
    answer = _step(pod, [0], np.zeros((1, 0, ACTION_DIM)))
    assert answer["num_steps"].tolist() == [0] and answer["reward"].shape == (1, 0)
    assert _same_obs(answer["obs"], 0, reset["obs"], 0)


@pytest.mark.parametrize(
    "bad, named",
    [
        (lambda chunk: chunk.__setitem__((1, 2, 0), np.nan), ["env 1", "action 2 of the chunk"]),
        (lambda chunk: np.zeros((2, DEFAULT_MAX_CHUNK + 1, ACTION_DIM)), ["limit of 64"]),
        (lambda chunk: chunk[:, :, :3], ["expected a chunk of shape (2, K, 6)"]),
    ],
    ids=["nan", "too-long", "wrong-dim"],
)
def test_a_bad_chunk_is_refused_naming_what_is_wrong_and_changes_no_env(pod, bad, named):
    _reset(pod, [0, 1, 2], [8, 8, 8])
    chunk = _chunk(2, 4, seed=4)
    sent = bad(chunk)
    actions = np.asarray(chunk if sent is None else sent, np.float32)
    body = {"generation": 0, "env_indices": np.array([0, 1]), "actions": actions}
    response = post_wire(pod, "step", body, None)
    assert response.status_code == 422
    for word in named:
        assert word in response.json()["detail"]
    after = _step(pod, [0, 1, 2], np.zeros((3, 1, ACTION_DIM)))
    assert _same_obs(after["obs"], 0, after["obs"], 2) and _same_obs(after["obs"], 1, after["obs"], 2)


def test_json_and_wire_answer_a_chunk_alike(pod):
    chunk = _chunk(1, 3, seed=5)
    _reset(pod, [0, 1], [9, 9])
    via_wire = _step(pod, [0], chunk)
    body = {"generation": 0, "env_indices": np.array([1]), "actions": chunk}
    as_json = {"Content-Type": "application/json", "Accept": "application/json"}
    via_json = _answer(
        httpx.post(f"{pod}/v1/step", content=json.dumps(wire.to_jsonable(body)), headers=as_json, timeout=60)
    )
    assert via_json["reward"] == via_wire["reward"].tolist()
    assert via_json["num_steps"] == via_wire["num_steps"].tolist()
    assert via_json["obs"]["proprio"] == via_wire["obs"]["proprio"].tolist()


# -- the trainer side ----------------------------------------------------------------------------


def test_http_vector_env_chunk_step_matches_single_steps_and_stops_at_truncation(pods):
    urls = [p.url for p in pods]
    states = np.arange(8) % 3
    chunks = _chunk(8, 8, seed=6)
    with contextlib.closing(HTTPVectorEnv(pod_urls=urls, autoreset_mode=AutoresetMode.DISABLED)) as env:
        env.reset(options={"state_ids": states})
        rewards = np.stack([env.step(chunks[:, k])[1] for k in range(EPISODE)], axis=1)
        env.reset(options={"state_ids": states})
        obs, reward, terminated, truncated, info = env.chunk_step(chunks[:, :4])
        assert reward.shape == (8, 4) and info["num_steps"].tolist() == [4] * 8
        obs, reward2, terminated, truncated, info = env.chunk_step(chunks[:, 4:8])
    assert info["num_steps"].tolist() == [EPISODE - 4] * 8
    assert truncated[:, EPISODE - 5].all() and not truncated[:, EPISODE - 4 :].any()
    assert np.array_equal(np.concatenate([reward, reward2[:, : EPISODE - 4]], axis=1), rewards)


def test_http_vector_env_next_step_autoreset_resets_in_place_of_the_chunk_after_an_ending(pods):
    with contextlib.closing(HTTPVectorEnv(pod_urls=[p.url for p in pods])) as env:  # NEXT_STEP
        first, _ = env.reset(options={"state_ids": np.zeros(8, dtype=np.int64)})
        _, _, _, truncated, _ = env.chunk_step(np.zeros((8, 8, ACTION_DIM)))
        assert truncated[:, EPISODE - 1].all()
        obs, reward, _, truncated, info = env.chunk_step(np.zeros((8, 8, ACTION_DIM)))
    assert info["num_steps"].tolist() == [0] * 8 and info["_num_steps"].all()
    assert reward.shape == (8, 8) and not reward.any() and not truncated.any()
    assert info["_state_id"].all()  # each env was reset (to a drawn state) instead of stepped


def test_a_stage_steps_one_array_of_actions_as_it_steps_the_same_actions_by_traj_key(pods):
    chunks = _chunk(4, 3, seed=7)
    with StageClient.from_pods([pods[0].url]) as client:
        keys = list(client.reset_trajectories([(TASK, 0), (TASK, 1), (TASK, 2), (TASK, 0)]))
        answers = {}
        for form, actions in [
            ("chunks by key", dict(zip(keys, chunks))),
            ("chunks as one array", client.step_actions(keys, chunks)),
            ("actions by key", dict(zip(keys, chunks[:, 0]))),
            ("actions as one array", client.step_actions(keys, chunks[:, 0])),
        ]:
            client.reset_stage(0).result()
            answers[form] = client.step_stage(0, actions).result()
    for by_key, as_array, chunk in [
        ("chunks by key", "chunks as one array", 3),
        ("actions by key", "actions as one array", None),
    ]:
        a, b = answers[by_key], answers[as_array]
        assert a.chunk == b.chunk == chunk and a.traj_keys == b.traj_keys == keys
        for name in ("reward", "terminated", "truncated", "num_steps"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
        assert _same_obs(a.obs, 0, b.obs, 0) and _same_obs(a.obs, 3, b.obs, 3)
    assert answers["actions by key"].reward.shape == (4,) and answers["chunks by key"].reward.shape == (4, 3)


def test_env_loop_records_every_applied_action_of_a_chunking_policy(pods, tmp_path):
    def policy(obs: dict[str, torch.Tensor], instructions: list[str], task_ids: list[str]) -> torch.Tensor:
        return torch.zeros((len(task_ids), 4, ACTION_DIM))

    with StageClient.from_pods([p.url for p in pods]) as client:
        loop = EnvLoop(client, policy, horizon=5, record=1, video_dir=tmp_path, video_format="gif")
        result = loop.run([(TASK, 0), (TASK, 1), (TASK, 2), (TASK, 3)])
    assert len(result.trajectories) == 4
    for trajectory in result.trajectories.values():
        assert trajectory.length == 5 and trajectory.rewards.shape == (5,) and trajectory.truncated
        assert trajectory.num_steps.tolist() == [4, 1]
        assert trajectory.observations["proprio"].shape[0] == 3
    assert result.stats.env_steps == 20
    (video,) = result.videos.values()
    assert Image.open(video).n_frames == 1 + 5


# -- the VLA trainers' env -----------------------------------------------------------------------


def test_vla_env_resets_the_named_envs_to_the_named_states_and_leaves_the_others(pods):
    with VLAEnv(pod_urls=[p.url for p in pods], keys="lerobot") as env:
        first, _ = env.reset(state_ids=np.zeros(env.num_envs, dtype=np.int64))
        obs, info = env.reset(env_ids=[1, 5], state_ids=[2, 2])
        assert sorted(key for key in obs if key.startswith("observation.")) == [
            f"observation.images.{IMAGE}",
            "observation.state",
        ]
        assert obs["task"] == env.instructions and obs["task_id"] == [TASK] * env.num_envs
        state = obs["observation.state"]
        assert np.array_equal(state[1], state[5]) and not np.array_equal(state[1], first["observation.state"][1])
        others = [i for i in range(env.num_envs) if i not in (1, 5)]
        assert np.array_equal(state[others], first["observation.state"][others])
        assert info["state_id"][[1, 5]].tolist() == [2, 2]


def test_vla_env_chunk_step_answers_per_action_signals_of_every_env(pods):
    with VLAEnv(pod_urls=[p.url for p in pods]) as env:
        env.reset(state_ids=np.full(env.num_envs, 1))
        chunk = np.broadcast_to(_chunk(1, 8, seed=7), (env.num_envs, 8, ACTION_DIM))
        obs, rewards, terminations, truncations, infos = env.chunk_step(torch.from_numpy(chunk.copy()))
    assert rewards.shape == terminations.shape == truncations.shape == (env.num_envs, 8)
    assert infos["num_steps"].tolist() == [EPISODE] * env.num_envs
    assert truncations[:, EPISODE - 1].all() and not terminations.any()
    assert (rewards == rewards[0]).all()  # one state, one chunk: every env alike, bit for bit
    assert obs["proprio"].shape[0] == env.num_envs and obs["instruction"] == env.instructions


def test_vla_env_with_auto_reset_resets_envs_that_ended_inside_the_chunk(pods):
    with VLAEnv(pod_urls=[p.url for p in pods], auto_reset=True) as env:
        env.reset(state_ids=np.zeros(env.num_envs, dtype=np.int64), seed=0)
        obs, _, _, truncations, infos = env.chunk_step(np.zeros((env.num_envs, 8, ACTION_DIM)))
        assert truncations[:, EPISODE - 1].all()
        assert infos["_final_obs"].all() and set(infos["final_obs"][0]) == {"images", "proprio"}
        _, _, _, _, after = env.chunk_step(np.zeros((env.num_envs, 2, ACTION_DIM)))
    assert after["num_steps"].tolist() == [2] * env.num_envs  # fresh episodes


@pytest.mark.slow
def test_a_client_takes_a_long_recorded_chunk_whose_frames_outweigh_its_observations(start_pods):
    # 2 envs x 48 recorded 64x64 frames (~1.2 MB) are more than the default answer cap for one
    # observation per env: the cap grows with the call's K and recorded envs.
    spec = PodSpec("sim-0", 0, [(TASK, 2)], camera=CameraConfig(height=64, width=64), max_episode_steps=100)
    (running,) = start_pods([spec])
    with StageClient.from_pods([running.url]) as client:
        routes = client.reset_trajectories([(TASK, 0), (TASK, 1)])
        client.reset_stage(0).result()
        chunk = _chunk(2, 48, seed=6)
        batch = client.step_stage(0, dict(zip(routes, chunk)), record=list(routes)).result()
    assert batch.num_steps.tolist() == [48, 48]
    for key in routes:
        assert batch.frames[key][IMAGE].shape == (48, 64, 64, 3)
