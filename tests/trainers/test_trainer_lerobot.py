"""LeRobot's own eval loop on LIBERO, through vecsim and through LeRobot's own LIBERO env.

The judge is the installed ``lerobot`` release (0.4.4, the one that installs beside this torch):
its ``eval_policy`` (``lerobot/scripts/lerobot_eval.py``) runs a scripted policy with LeRobot's
LIBERO env processors (``make_env_pre_post_processors``: ``LiberoProcessorStep`` flips the images
and builds ``observation.state``), once over :class:`LeRobotVectorEnv` on a real pod and once over
LeRobot's own ``create_libero_envs`` (a ``SyncVectorEnv`` of its ``LiberoEnv``). Per-episode
success, return and length (the frames its video writer wrote) are equal, and so is every
observation the policy was handed. One task, one env, 64x64 cameras, 12-step episodes.

LeRobot's modules import torchvision, which does not load beside this CPU torch; the eval loop
never uses it (``torchvision_absent``).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
from support.service_procs import assignment, standalone_pods

from vecsim.config import CameraConfig, LiberoProtocol
from vecsim.engine.tasks._libero import ensure_config
from vecsim.trainers.lerobot import LeRobotVectorEnv

pytestmark = pytest.mark.libero

torch = pytest.importorskip("torch")
from support import torchvision_absent  # noqa: E402

torchvision_absent.install()
ensure_config()  # LIBERO asks for its paths on stdin when it has no config
lerobot_eval = pytest.importorskip("lerobot.scripts.lerobot_eval")
from gymnasium.vector import SyncVectorEnv  # noqa: E402
from lerobot.configs.policies import PreTrainedConfig  # noqa: E402
from lerobot.envs.configs import LiberoEnv as LiberoEnvConfig  # noqa: E402
from lerobot.envs.factory import make_env_pre_post_processors  # noqa: E402
from lerobot.envs.libero import create_libero_envs  # noqa: E402
from lerobot.policies.pretrained import PreTrainedPolicy  # noqa: E402
from lerobot.processor import PolicyProcessorPipeline  # noqa: E402
from lerobot.processor.converters import policy_action_to_transition, transition_to_policy_action  # noqa: E402

SUITE, TASK_INDEX = "libero_spatial", 0
TASK = f"{SUITE}/{TASK_INDEX}"
SIZE = 64
EPISODE = 12
# Deterministic actions, one per step; LeRobot's actions are float32 in [-1, 1].
ACTIONS = np.random.default_rng(26).uniform(-1.0, 1.0, (EPISODE, 7)).astype(np.float32)


@PreTrainedConfig.register_subclass("vecsim_scripted")
@dataclasses.dataclass
class ScriptedConfig(PreTrainedConfig):
    """The least a LeRobot policy config is: no features, no optimiser."""

    def __post_init__(self) -> None:
        self.device = "cpu"

    @property
    def observation_delta_indices(self) -> None:
        return None

    @property
    def action_delta_indices(self) -> None:
        return None

    @property
    def reward_delta_indices(self) -> None:
        return None

    def get_optimizer_preset(self) -> None:
        return None

    def get_scheduler_preset(self) -> None:
        return None

    def validate_features(self) -> None:
        return None


class ScriptedPolicy(PreTrainedPolicy):
    """Plays :data:`ACTIONS` in order and keeps every observation batch it was handed."""

    config_class = ScriptedConfig
    name = "vecsim_scripted"

    def __init__(self) -> None:
        super().__init__(ScriptedConfig())
        self.seen: list[dict[str, object]] = []
        self._t = 0

    def reset(self) -> None:
        self._t = 0

    def select_action(self, batch: dict, **kwargs: object) -> torch.Tensor:
        self.seen.append({key: value.clone() if isinstance(value, torch.Tensor) else value for key, value in batch.items()})
        action = torch.from_numpy(ACTIONS[self._t % EPISODE]).expand(batch["observation.state"].shape[0], -1)
        self._t += 1
        return action.clone()

    def get_optim_params(self) -> dict:
        return {}

    def forward(self, batch: dict) -> tuple:
        raise NotImplementedError("evaluation only")

    def predict_action_chunk(self, batch: dict, **kwargs: object) -> torch.Tensor:
        raise NotImplementedError("evaluation only")


def _evaluate(env, videos: Path) -> tuple[dict, ScriptedPolicy]:
    """LeRobot's eval_policy over ``env`` with LeRobot's LIBERO processors; one video."""
    policy = ScriptedPolicy()
    env_pre, env_post = make_env_pre_post_processors(LiberoEnvConfig(task=SUITE), policy.config)
    # The policy's own processors are identities, built as lerobot.policies.factory builds them.
    pre = PolicyProcessorPipeline(steps=[])
    post = PolicyProcessorPipeline(steps=[], to_transition=policy_action_to_transition, to_output=transition_to_policy_action)
    info = lerobot_eval.eval_policy(
        env, policy, env_pre, env_post, pre, post,
        n_episodes=env.num_envs, max_episodes_rendered=1, videos_dir=videos, start_seed=0,
    )  # fmt: skip
    return info, policy


@pytest.fixture(scope="module")
def vecsim_run(tmp_path_factory):
    spec = assignment(
        "sim-0", [(TASK, 1)], job_id="lerobot", camera=CameraConfig(height=SIZE, width=SIZE),
        render=None, max_episode_steps=EPISODE, libero=LiberoProtocol(image_orientation="raw"),
    )  # fmt: skip
    videos = tmp_path_factory.mktemp("vecsim-videos")
    with standalone_pods([spec], tmp_path_factory.mktemp("pods")) as pods:
        env = LeRobotVectorEnv(pod_urls=[pods[0].url], timeout_s=120)
        try:
            info, policy = _evaluate(env, videos)
        finally:
            env.close()
    return info, policy


@pytest.fixture(scope="module")
def lerobot_run(tmp_path_factory):
    envs = create_libero_envs(
        task=SUITE, n_envs=1, env_cls=SyncVectorEnv, episode_length=EPISODE,
        gym_kwargs={"task_ids": [TASK_INDEX], "obs_type": "pixels_agent_pos", "observation_width": SIZE, "observation_height": SIZE},
    )  # fmt: skip
    env = envs[SUITE][TASK_INDEX]
    try:
        info, policy = _evaluate(env, tmp_path_factory.mktemp("lerobot-videos"))
    finally:
        env.close()
    return info, policy


def _frames(info: dict) -> int:
    return iio.imread(info["video_paths"][0], index=None).shape[0]


def test_eval_policy_gives_lerobots_per_episode_success_and_return(vecsim_run, lerobot_run):
    ours, theirs = vecsim_run[0]["per_episode"], lerobot_run[0]["per_episode"]
    assert len(ours) == len(theirs) == 1
    for mine, own in zip(ours, theirs):
        assert mine["success"] == own["success"]
        assert mine["sum_reward"] == pytest.approx(own["sum_reward"])
        assert mine["max_reward"] == pytest.approx(own["max_reward"])


def test_eval_policy_writes_a_video_as_long_as_lerobots(vecsim_run, lerobot_run):
    # eval_policy writes frames up to the episode's end: the video's length is the episode's.
    assert _frames(vecsim_run[0]) == _frames(lerobot_run[0]) > 0


def test_the_policy_is_handed_lerobots_observations(vecsim_run, lerobot_run):
    ours, theirs = vecsim_run[1].seen, lerobot_run[1].seen
    assert len(ours) == len(theirs) == EPISODE
    for t, (mine, own) in enumerate(zip(ours, theirs)):
        assert mine.keys() == own.keys(), t
        assert mine["task"] == own["task"], t
        np.testing.assert_allclose(mine["observation.state"], own["observation.state"], atol=1e-6, err_msg=f"step {t}")
        for key in ("observation.images.image", "observation.images.image2"):
            assert torch.equal(mine[key], own[key]), (t, key)
