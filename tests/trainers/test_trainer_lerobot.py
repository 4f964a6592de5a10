"""LeRobot's own eval loop on LIBERO, through vecsim and through LeRobot's own LIBERO env.

The judge is the installed ``lerobot`` release (0.4.4, the one that installs beside this torch):
its ``eval_policy`` (``lerobot/scripts/lerobot_eval.py``) runs a scripted policy with LeRobot's
LIBERO env processors (``make_env_pre_post_processors``: ``LiberoProcessorStep`` flips the images
and builds ``observation.state``), once over :class:`LeRobotVectorEnv` on a real pod and once over
LeRobot's own ``create_libero_envs`` (a ``SyncVectorEnv`` of its ``LiberoEnv``). Two tasks whose
fixtures LeRobot's seeds move (libero_goal/7: cabinet, stove, rack; libero_10/8: stove, with an
open/close sampler, so each reset's draws also depend on how often the env was loaded), 2 envs,
2 episodes each (env ``i``'s resets seeded ``start_seed + i`` and ``start_seed + 2 + i``), 64x64
cameras, 8-step episodes. The job's ``libero`` block and the lines that build the env and run the
eval on vecsim are docs/trainers.md's, as pasted; the job names no seed of the eval's. Per-episode
success, return and length (the frames its video writer wrote) are equal, and so is every
observation the policy was handed, bit for bit: both images and ``observation.state``.

LeRobot's modules import torchvision, which does not load beside this CPU torch; the eval loop
never uses it (``torchvision_absent``).
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import yaml
from support.service_procs import assignment, standalone_pods

from vecsim.config import CameraConfig, LiberoProtocol
from vecsim.engine.tasks._libero import ensure_config

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

TASKS = [("libero_goal", 7), ("libero_10", 8)]
N_ENVS, EPISODES_PER_ENV = 2, 2
SIZE = 64
EPISODE = 8
# Deterministic actions, one per step; LeRobot's actions are float32 in [-1, 1].
ACTIONS = np.random.default_rng(26).uniform(-1.0, 1.0, (EPISODE, 7)).astype(np.float32)
DOCS = Path(__file__).resolve().parents[2] / "docs" / "trainers.md"


def _documented(language: str) -> str:
    """The first ``language`` block of docs/trainers.md's LeRobot section, as written there."""
    section = DOCS.read_text().split("## LeRobot", 1)[1]
    return re.findall(rf"```{language}\n(.*?)```", section, re.DOTALL)[0]


def documented_job() -> dict:
    """The job config of docs/trainers.md's LeRobot section."""
    return yaml.safe_load(_documented("yaml"))


START_SEED = int(re.search(r"start_seed=(\d+)", _documented("python")).group(1))  # the documented eval's


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
        self.seen.append(
            {key: value.clone() if isinstance(value, torch.Tensor) else value for key, value in batch.items()}
        )
        action = torch.from_numpy(ACTIONS[self._t % EPISODE]).expand(batch["observation.state"].shape[0], -1)
        self._t += 1
        return action.clone()

    def get_optim_params(self) -> dict:
        return {}

    def forward(self, batch: dict) -> tuple:
        raise NotImplementedError("evaluation only")

    def predict_action_chunk(self, batch: dict, **kwargs: object) -> torch.Tensor:
        raise NotImplementedError("evaluation only")


def _processors(suite: str) -> tuple[ScriptedPolicy, dict]:
    """The policy and the four processors eval_policy takes, with LeRobot's LIBERO env processors."""
    policy = ScriptedPolicy()
    env_pre, env_post = make_env_pre_post_processors(LiberoEnvConfig(task=suite), policy.config)
    # The policy's own processors are identities, built as lerobot.policies.factory builds them.
    pre = PolicyProcessorPipeline(steps=[])
    post = PolicyProcessorPipeline(
        steps=[], to_transition=policy_action_to_transition, to_output=transition_to_policy_action
    )
    return policy, {
        "env_preprocessor": env_pre,
        "env_postprocessor": env_post,
        "preprocessor": pre,
        "postprocessor": post,
    }


def _vecsim_run(suite: str, index: int, tmp_path_factory) -> tuple[dict, ScriptedPolicy]:
    """docs/trainers.md's LeRobot lines, as pasted, on a pod serving the documented job."""
    spec = assignment(
        "sim-0",
        [(f"{suite}/{index}", N_ENVS)],
        job_id="lerobot",
        camera=CameraConfig(height=SIZE, width=SIZE),
        render=None,
        max_episode_steps=EPISODE,
        libero=LiberoProtocol(**documented_job()["libero"]),
    )
    policy, processors = _processors(suite)
    with standalone_pods([spec], tmp_path_factory.mktemp("pods")) as pods:
        names = {
            "pod_urls": [pods[0].url],
            "policy": policy,
            **processors,
            "n_episodes": N_ENVS * EPISODES_PER_ENV,
            "videos_dir": tmp_path_factory.mktemp("vecsim-videos"),
        }
        exec(compile(_documented("python"), str(DOCS), "exec"), names)
    return names["info"], policy


def _lerobot_run(suite: str, index: int, tmp_path_factory) -> tuple[dict, ScriptedPolicy]:
    envs = create_libero_envs(
        task=suite,
        n_envs=N_ENVS,
        env_cls=SyncVectorEnv,
        episode_length=EPISODE,
        gym_kwargs={
            "task_ids": [index],
            "obs_type": "pixels_agent_pos",
            "observation_width": SIZE,
            "observation_height": SIZE,
        },
    )
    env = envs[suite][index]
    policy, processors = _processors(suite)
    try:
        info = lerobot_eval.eval_policy(
            env,
            policy,
            **processors,
            n_episodes=N_ENVS * EPISODES_PER_ENV,
            max_episodes_rendered=1,
            videos_dir=tmp_path_factory.mktemp("lerobot-videos"),
            start_seed=START_SEED,
        )
    finally:
        env.close()
    return info, policy


@pytest.fixture(scope="module", params=TASKS, ids=[f"{suite}/{index}" for suite, index in TASKS])
def runs(request, tmp_path_factory):
    """(vecsim's run, LeRobot's run) of one task: each an eval_policy info and the policy."""
    suite, index = request.param
    return _vecsim_run(suite, index, tmp_path_factory), _lerobot_run(suite, index, tmp_path_factory)


def _frames(info: dict) -> int:
    return iio.imread(info["video_paths"][0], index=None).shape[0]


def test_the_documented_job_leaves_the_seeds_to_the_eval():
    assert documented_job()["libero"] == {"image_orientation": "raw"}


def test_eval_policy_gives_lerobots_per_episode_success_and_return(runs):
    ours, theirs = runs[0][0]["per_episode"], runs[1][0]["per_episode"]
    assert len(ours) == len(theirs) == N_ENVS * EPISODES_PER_ENV
    for mine, own in zip(ours, theirs):
        assert mine["success"] == own["success"]
        assert mine["sum_reward"] == own["sum_reward"]
        assert mine["max_reward"] == own["max_reward"]


def test_eval_policy_writes_a_video_as_long_as_lerobots(runs):
    # eval_policy writes frames up to the episode's end: the video's length is the episode's.
    assert _frames(runs[0][0]) == _frames(runs[1][0]) > 0


def test_the_policy_is_handed_lerobots_observations_for_every_env_and_episode(runs):
    ours, theirs = runs[0][1].seen, runs[1][1].seen
    assert len(ours) == len(theirs) == EPISODES_PER_ENV * EPISODE
    for t, (mine, own) in enumerate(zip(ours, theirs)):
        assert mine.keys() == own.keys(), t
        assert mine["task"] == own["task"], t
        assert mine["observation.images.image"].shape[0] == N_ENVS
        for key in ("observation.images.image", "observation.images.image2"):
            assert torch.equal(mine[key], own[key]), (t, key)
        assert mine["observation.state"].dtype == own["observation.state"].dtype, t
        assert torch.equal(mine["observation.state"], own["observation.state"]), t
