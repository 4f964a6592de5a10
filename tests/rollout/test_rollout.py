"""EnvLoop over a real local job (controller + two pods): two stages, two tiny robot tasks, one
16x16 camera, 4-step episodes."""

from __future__ import annotations

from collections import Counter

import imageio.v3 as iio
import numpy as np
import pytest
import torch
from support.service_procs import job_config, local_job

from vecsim.client import CapacityError, StageClient
from vecsim.config import CameraConfig
from vecsim.rollout import EnvLoop, ExampleCNNPolicy, write_video
from vecsim.rollout.sampler import TaskBalancedSampler, TaskInstances, stage_of

LIFT, STACK = "tiny/lift", "tiny/stack"
GROUP_SIZE = 2
EPISODE = 4
CAMERA = CameraConfig(names=("agentview",), height=16, width=16)


@pytest.fixture(scope="module")
def job(tmp_path_factory):
    spec = {
        "job_id": "rollout-tests",
        "tasks": [LIFT, STACK],
        "group_size": GROUP_SIZE,
        "num_stages": 2,
        "camera": CAMERA.model_dump(mode="json"),
        "max_episode_steps": EPISODE,
    }
    with local_job(job_config(spec, replicas=2), tmp_path_factory.mktemp("job")) as running:
        yield running


@pytest.fixture
def client(job):
    with StageClient.from_controller(job.controller_url, timeout_s=60, token=job.token) as c:
        yield c


@pytest.fixture
def policy(client):
    return ExampleCNNPolicy(client.observation_space, client.action_space, hidden=16, noise_std=0.1)


def _sampler(batch_size: int = 8, seed: int = 0) -> tuple[TaskInstances, TaskBalancedSampler]:
    dataset = TaskInstances.from_tasks([LIFT, STACK], num_states=6)
    return dataset, TaskBalancedSampler(dataset, batch_size, group_size=GROUP_SIZE, num_stages=2, seed=seed)


def test_a_rollout_returns_one_trajectory_per_request_with_aligned_tensors(client, policy):
    dataset, sampler = _sampler()
    requests = [dataset[i] for i in next(iter(sampler))]
    result = EnvLoop(client, policy, horizon=3).run(requests)
    assert len(result.trajectories) == len(requests)
    for (task_id, state_id), trajectory in zip(requests, result.trajectories.values()):
        assert (trajectory.route.task_id, trajectory.route.state_id) == (task_id, state_id)
        assert trajectory.length == 3 and trajectory.truncated
        assert trajectory.observations["images"]["agentview"].shape == (4, 16, 16, 3)
        assert trajectory.observations["proprio"].shape[0] == 4
        assert trajectory.actions.shape == (3, 7) and trajectory.rewards.shape == (3,)
        assert trajectory.dones.tolist() == [False, False, True]
    assert result.stats.env_steps == 3 * len(requests)
    assert set(result.stats.success_per_task) == {LIFT, STACK}
    assert 0.0 <= result.stats.overlap_fraction <= 1.0


def test_episodes_end_at_the_pods_limit_and_are_not_stepped_again(client, policy):
    result = EnvLoop(client, policy, horizon=50, keep_obs=()).run([(LIFT, 0), (STACK, 1), (STACK, 2)])
    for trajectory in result.trajectories.values():
        assert trajectory.length == EPISODE
        assert trajectory.truncated and trajectory.observations == {}
    assert result.stats.env_steps == 3 * EPISODE


def test_given_state_ids_reproduce_bit_identical_first_observations(client, policy):
    requests = [(LIFT, 3), (STACK, 5), (STACK, 1), (LIFT, 4)]
    loop = EnvLoop(client, policy, horizon=1)
    first = loop.run(requests)
    # Reversed, every request runs on the other stage's pod.
    second = loop.run(requests[::-1])
    by_request = {(t.route.task_id, t.route.state_id): t for t in second.trajectories.values()}
    for trajectory in first.trajectories.values():
        twin = by_request[(trajectory.route.task_id, trajectory.route.state_id)]
        assert twin.route.pod != trajectory.route.pod
        for key in ("proprio",):
            assert torch.equal(trajectory.observations[key][0], twin.observations[key][0])
        assert torch.equal(
            trajectory.observations["images"]["agentview"][0], twin.observations["images"]["agentview"][0]
        )


def test_sampler_batches_route_within_capacity_and_never_share_an_env(client):
    dataset, sampler = _sampler(batch_size=8, seed=3)
    for batch in sampler:
        requests = [dataset[i] for i in batch]
        routes = client.reset_trajectories(requests)
        per_stage_task = Counter((r.stage_id, r.task_id) for r in routes.values())
        assert max(per_stage_task.values()) <= GROUP_SIZE
        assert len({(r.pod, r.env_index) for r in routes.values()}) == len(routes)
        assert [r.stage_id for r in routes.values()] == [stage_of(i, 2) for i in range(len(requests))]


def test_an_empty_batch_is_a_no_op(client, policy):
    result = EnvLoop(client, policy, horizon=3).run([])
    assert result.trajectories == {} and result.stats.env_steps == 0


def test_a_stage_without_trajectories_is_never_called(client, policy):
    result = EnvLoop(client, policy, horizon=2).run([(LIFT, 0)])
    (trajectory,) = result.trajectories.values()
    assert trajectory.route.stage_id == 0 and trajectory.length == 2


def test_a_batch_size_not_divisible_by_the_stages_is_refused_by_the_sampler():
    with pytest.raises(ValueError, match="batch_size=3 is not divisible by num_stages=2"):
        _sampler(batch_size=3)


def test_a_batch_not_a_multiple_of_the_stages_runs_with_stage_sizes_differing_by_one(client, policy):
    result = EnvLoop(client, policy, horizon=1).run([(LIFT, 0), (STACK, 0), (STACK, 1)])
    stages = Counter(t.route.stage_id for t in result.trajectories.values())
    assert stages == {0: 2, 1: 1}


def test_more_requests_than_envs_all_run_refilling_envs_whose_trajectories_ended(client, policy):
    # Three LIFT requests per stage for GROUP_SIZE = 2 LIFT envs per stage: one waits for an env.
    requests = [(LIFT, k) for k in range(6)] + [(STACK, 0), (STACK, 1)]
    result = EnvLoop(client, policy, horizon=2).run(requests, [f"r{i}" for i in range(len(requests))])
    assert list(result.trajectories) == [f"r{i}" for i in range(len(requests))] and result.lost == {}
    for i, ((task_id, state_id), trajectory) in enumerate(zip(requests, result.trajectories.values())):
        assert (trajectory.route.task_id, trajectory.route.state_id) == (task_id, state_id)
        assert trajectory.route.stage_id == stage_of(i, 2) and trajectory.length == 2
    lift_envs = Counter(
        (t.route.pod, t.route.env_index) for t in result.trajectories.values() if t.route.task_id == LIFT
    )
    assert sorted(lift_envs.values()) == [1, 1, 2, 2]  # per stage, one env ran two trajectories in turn


def test_a_refilled_trajectory_starts_from_the_same_observation_as_a_first_one(client, policy):
    requests = [(LIFT, 0), (LIFT, 1), (LIFT, 2), (LIFT, 3), (LIFT, 4)]  # (LIFT, 4) waits on stage 0
    refilled = EnvLoop(client, policy, horizon=1).run(requests).trajectories
    alone = EnvLoop(client, policy, horizon=1).run([(LIFT, 4)]).trajectories
    (first,) = alone.values()
    (late,) = [t for t in refilled.values() if t.route.state_id == 4]
    assert late.route.stage_id == first.route.stage_id == 0
    assert torch.equal(late.observations["proprio"][0], first.observations["proprio"][0])
    assert torch.equal(late.observations["images"]["agentview"][0], first.observations["images"]["agentview"][0])


def test_a_refill_reset_riding_in_a_step_request_starts_as_a_first_one_and_runs_its_horizon(client, policy):
    # Stage 0 runs r0 (one action) and r2 (three): r4 starts on r0's env in the request that
    # steps r2, the reset and the step in one /v1/step.
    requests = [(LIFT, 0), (LIFT, 1), (LIFT, 2), (LIFT, 3), (LIFT, 4)]
    keys = [f"r{i}" for i in range(5)]
    result = EnvLoop(client, policy, horizon=3).run(requests, keys, horizons=[1, 1, 3, 1, 2])
    (first,) = EnvLoop(client, policy, horizon=1).run([(LIFT, 4)]).trajectories.values()
    late = result.trajectories["r4"]
    assert late.route.env_index == result.trajectories["r0"].route.env_index and late.route.stage_id == 0
    assert late.length == 2 and late.observations["proprio"].shape[0] == 3 and result.lost == {}
    assert torch.equal(late.observations["proprio"][0], first.observations["proprio"][0])
    assert torch.equal(late.observations["images"]["agentview"][0], first.observations["images"]["agentview"][0])


def test_a_request_of_a_task_its_stage_has_no_env_of_is_refused_naming_task_and_stage(client, policy):
    with pytest.raises(CapacityError, match="stage 0 has 0 env\\(s\\) of task 'tiny/absent'"):
        EnvLoop(client, policy, horizon=1).run([("tiny/absent", 0)])


@pytest.mark.parametrize("video_format", ["mp4", "gif"])
def test_chosen_trajectories_are_recorded_as_videos(client, policy, tmp_path, video_format):
    loop = EnvLoop(client, policy, horizon=2, record=1, video_dir=tmp_path, video_format=video_format)
    result = loop.run([(LIFT, 0), (STACK, 0)])
    assert len(result.videos) == 1
    ((key, path),) = result.videos.items()
    frames = iio.imread(path) if video_format == "mp4" else iio.imread(path, index=None)
    assert frames.shape[0] == result.trajectories[key].length + 1
    assert frames.shape[1:3] == (16, 16)


def test_recording_a_camera_the_job_lacks_is_refused_before_anything_runs(client, policy, tmp_path):
    loop = EnvLoop(client, policy, horizon=1, record=1, camera="nope", video_dir=tmp_path)
    with pytest.raises(ValueError, match="cannot record camera 'nope'"):
        loop.run([(LIFT, 0)])
    assert list(tmp_path.iterdir()) == []


def test_write_video_refuses_frames_of_mixed_sizes(tmp_path):
    frames = [np.zeros((8, 8, 3), np.uint8), np.zeros((8, 9, 3), np.uint8)]
    with pytest.raises(ValueError, match="one size"):
        write_video(tmp_path / "x.mp4", frames)


def test_the_example_policy_maps_a_batch_to_bounded_actions(client):
    policy = ExampleCNNPolicy(client.observation_space, client.action_space, hidden=8)
    obs = {
        "images": {"agentview": torch.zeros((3, 16, 16, 3), dtype=torch.uint8)},
        "proprio": torch.zeros((3, client.observation_space["proprio"].shape[0])),
    }
    actions = policy(obs, ["lift the cube", "stack", ""], [LIFT, STACK, LIFT])
    assert actions.shape == (3, 7)
    assert bool((actions.abs() <= 1).all())
