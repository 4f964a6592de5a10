"""A LIBERO env's LeRobot reset (the reset option ``LEROBOT_RESETS``) against LeRobot's own env.

LeRobot's ``LiberoEnv`` (lerobot 0.4.4, ``envs/libero.py``) runs ``env.seed(seed); env.reset()``
(a hard reset: the model reloaded, the fixtures and arm pose drawn anew) and sets init state
``init_state_id % 50``, which moves on by ``n_envs`` at every reset. Here one of its envs is built
as its vector env builds env 1 of 25 (``episode_index=1, n_envs=25``), so its third reset wraps
round to init state 1 after loading its model four times; it is reset three times under seeds no
job knows, on libero_10/8 (a stove and an open/close sampler, whose draws grow with every load).
A real pod serving that task (one env) takes each reset as the env's own seeded reset with the
options ``{LEROBOT_RESETS: {str(s): {"state_id": k, "resets_before": r}}}``, sent through the
client's ``StageClient.call``: both cameras are equal bit for bit after each reset, and so is the
float64 robot state LeRobot reads. The plan's bad entries are refused, naming the field; and
``LeRobotVectorEnv`` (over a cheap robosuite pod) refuses, before sending anything, seeds LIBERO
cannot take, resets that seed some envs and not others, and one seed for two envs.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest

from support.service_procs import assignment, standalone_pods

from support.service_procs import PodSpec
from support.wire_http import metric

from vecsim.client import HTTPVectorEnv
from vecsim.config import LEROBOT_RESETS, CameraConfig, LiberoProtocol
from vecsim.engine.tasks._libero import ensure_config, libero_benchmark
from vecsim.trainers.lerobot import LeRobotVectorEnv

ensure_config()  # LIBERO asks for its paths on stdin when it has no config
pytest.importorskip("torch")
from support import torchvision_absent  # noqa: E402

torchvision_absent.install()
lerobot_libero = pytest.importorskip("lerobot.envs.libero")

SUITE, INDEX = "libero_10", 8
SIZE = 64
EPISODE_INDEX, N_ENVS = 1, 25
SEEDS = [4_000_000_000, 17, 123_456]  # one per reset; the first near numpy's 2**32 limit


@pytest.fixture(scope="module")
def envs(tmp_path_factory):
    """(vecsim's HTTPVectorEnv over a real pod, LeRobot's LiberoEnv) of the task."""
    spec = assignment(
        "sim-0",
        [(f"{SUITE}/{INDEX}", 1)],
        job_id="lerobot-resets",
        camera=CameraConfig(height=SIZE, width=SIZE),
        render=None,
        max_episode_steps=520,
        libero=LiberoProtocol(image_orientation="raw", fixture_rule="first_reset"),
    )
    with standalone_pods([spec], tmp_path_factory.mktemp("pods")) as pods:
        theirs = lerobot_libero.LiberoEnv(
            libero_benchmark(SUITE),
            INDEX,
            SUITE,
            obs_type="pixels_agent_pos",
            observation_width=SIZE,
            observation_height=SIZE,
            episode_index=EPISODE_INDEX,
            n_envs=N_ENVS,
        )
        ours = HTTPVectorEnv(pod_urls=[pods[0].url], timeout_s=120)
        yield ours, theirs
        ours.close()
        theirs.close()


def _lerobot_reset(env: HTTPVectorEnv, seed: int | None, plan: object):
    """The pod's env reset with ``seed`` and the plan: its observation and the env's error, if any."""
    batch, _ = env.client.call(seeds={"env0": seed}, options={LEROBOT_RESETS: plan}).result(300)
    return batch.obs, batch.errors


@pytest.mark.libero
def test_each_reset_is_lerobots_for_its_seed_and_count(envs):
    ours, theirs = envs
    for r, seed in enumerate(SEEDS):
        state_id = (EPISODE_INDEX + r * N_ENVS) % 50
        assert theirs.init_state_id % 50 == state_id
        own, _ = theirs.reset(seed=seed)
        batch, errors = _lerobot_reset(ours, seed, {str(seed): {"state_id": state_id, "resets_before": r}})
        assert errors == []
        mine = {
            "images": {camera: image[0] for camera, image in batch["images"].items()},
            "proprio": batch["proprio"][0],
        }
        for camera, key in (("agentview", "image"), ("robot0_eye_in_hand", "image2")):
            assert np.array_equal(mine["images"][camera], own["pixels"][key]), (r, camera)
        state = own["robot_state"]
        # proprio's eef pos, eef quat and gripper qpos (vecsim.engine.tasks._robot.PROPRIO_KEYS).
        assert mine["proprio"].dtype == np.float64
        assert np.array_equal(mine["proprio"][14:17], state["eef"]["pos"]), r
        assert np.array_equal(mine["proprio"][17:21], state["eef"]["quat"]), r
        assert np.array_equal(mine["proprio"][21:23], state["gripper"]["qpos"]), r


@pytest.mark.libero
@pytest.mark.parametrize(
    ("seed", "plan", "named"),
    [
        (None, {"1": {"state_id": 0, "resets_before": 0}}, "needs a seed"),
        (2**32, {str(2**32): {"state_id": 0, "resets_before": 0}}, "outside 0..4294967295"),
        (5, {"6": {"state_id": 0, "resets_before": 0}}, "['5']"),
        (5, {"5": {"state_id": 50, "resets_before": 0}}, "state_id must be an int in 0..49"),
        (5, {"5": {"state_id": 0, "resets_before": -1}}, "resets_before must be an int"),
        (5, {"5": {"state_id": 0}}, "{state_id, resets_before}"),
        (5, [1], "must map seeds"),
    ],
)
def test_a_bad_plan_is_refused_naming_it(envs, seed, plan, named):
    _, errors = _lerobot_reset(envs[0], seed, plan)
    assert len(errors) == 1
    _key, type_name, message = errors[0]
    assert type_name == "ValueError" and named in message and LEROBOT_RESETS in message


@pytest.fixture(scope="module")
def robot_pod(tmp_path_factory) -> Iterator[str]:
    spec = PodSpec("robot-0", 0, [("tiny/lift", 2)], camera=CameraConfig(height=8, width=8))
    with standalone_pods([spec], tmp_path_factory.mktemp("robot-pod")) as pods:
        yield pods[0].url


@pytest.mark.parametrize(
    ("seed", "named"),
    [
        ([2**32, 1], "seed for env 0 is 4294967296"),
        ([1, None], "envs [1] have no seed"),
        ([5, 5], "seed 5 is given to envs"),
    ],
)
def test_lerobot_vector_env_refuses_seeds_it_cannot_place_before_sending(robot_pod, seed, named):
    env = LeRobotVectorEnv(pod_urls=[robot_pod])
    try:
        before = metric(robot_pod, "vecsim_pod_env_resets")
        with pytest.raises(ValueError) as caught:
            env.reset(seed=seed)
        assert named in str(caught.value)
        assert metric(robot_pod, "vecsim_pod_env_resets") == before
        env.reset(seed=None)  # the env is still usable
        assert metric(robot_pod, "vecsim_pod_env_resets") == before + 2
    finally:
        env.close()
