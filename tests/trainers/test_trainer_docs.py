"""docs/trainers.md's RLinf instructions, run as pasted, then RLinf's own env worker on vecsim.

The python block is executed as written; the yaml block is read by OmegaConf as RLinf reads its
config and merged over the rest of a user's RLinf LIBERO env config, its ``controller_url``
replaced by the documented alternative ``pod_urls`` naming a real pod on loopback (libero_10/0,
two envs, 32x32 cameras). RLinf's own ``get_env_cls`` (``rlinf/envs/__init__.py``) then picks
vecsim's env for that block and RLinf's own LIBERO env without the ``vecsim`` key; RLinf's env
worker builds the chosen class (``EnvWorker._setup_env_and_wrappers``, env_worker.py:336-348),
resets it (``_init_env``, ``bootstrap_step``) and steps one chunk (``env_interact_step``).
Whether what it hands RLinf equals RLinf's own env is tests/trainers/test_trainer_rlinf.py's;
the verl-vla and LeRobot instructions run as pasted in their own test modules.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rlinf")
import torch  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402
from support.rlinf_worker import env_worker, rlinf_config  # noqa: E402
from support.service_procs import assignment, standalone_pods  # noqa: E402

import vecsim.trainers.rlinf  # noqa: E402
from vecsim.config import CameraConfig  # noqa: E402
from vecsim.engine.tasks._libero import ensure_config, libero_benchmark  # noqa: E402

DOCS = Path(__file__).resolve().parents[2] / "docs" / "trainers.md"
NUM_ENVS, K, SIZE = 2, 4, 32
# The rest of a user's RLinf LIBERO env config (keys RLinf's LiberoEnv reads), beside the
# documented block: one task of the suite, a GRPO group of both envs on a fixed reset id.
USER_KEYS = {
    "total_num_envs": NUM_ENVS,
    "seed": 0,
    "group_size": NUM_ENVS,
    "use_fixed_reset_state_ids": True,
    "use_ordered_reset_state_ids": False,
    "task_id_filter": [0],
    "ignore_terminations": False,
    "auto_reset": False,
    "use_rel_reward": True,
    "reward_coef": 5.0,
    "max_episode_steps": 20,
    "max_steps_per_rollout_epoch": 5 * K,
    "rollout_epoch": 1,
    "reset_gripper_open": True,
    "video_cfg": {"save_video": False},
    "init_params": {"camera_heights": SIZE, "camera_widths": SIZE},
}


def _blocks(section: str, language: str) -> list[str]:
    text = DOCS.read_text().split(f"## {section}", 1)[1].split("\n## ", 1)[0]
    return re.findall(rf"```{language}\n(.*?)```", text, re.DOTALL)


def documented_train(pod_url: str | None = None) -> object:
    """The documented ``env.train`` block over the user's other keys; ``pod_url`` in place of
    the controller, as the block's comment offers."""
    train = OmegaConf.merge(OmegaConf.create(USER_KEYS), OmegaConf.create(_blocks("RLinf", "yaml")[0]).env.train)
    if pod_url is not None:
        del train.vecsim["controller_url"]
        train.vecsim.pod_urls = [pod_url]
    return train


@pytest.fixture(scope="module")
def pod_url(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    suite = documented_train().task_suite_name
    spec = assignment(
        "docs-pod",
        [(f"{suite}/0", NUM_ENVS)],
        job_id="rlinf-docs",
        render="lean",
        max_episode_steps=None,
        camera=CameraConfig(names=("agentview", "robot0_eye_in_hand"), height=SIZE, width=SIZE),
    )
    with standalone_pods([spec], tmp_path_factory.mktemp("docs-pod")) as pods:
        yield pods[0].url


def test_the_rlinf_instructions_make_rlinfs_env_selection_pick_vecsims_env():
    for block in _blocks("RLinf", "python"):
        exec(compile(block, str(DOCS), "exec"), {})
    import rlinf.envs

    train = documented_train()
    assert rlinf.envs.get_env_cls(train.env_type, train) is vecsim.trainers.rlinf.VecsimLiberoEnv
    del train["vecsim"]
    ensure_config()  # RLinf's LIBERO env imports LIBERO, which asks for its paths on stdin without one
    assert rlinf.envs.get_env_cls(train.env_type, train).__module__ == "rlinf.envs.libero.libero_env"


@pytest.mark.libero
def test_rlinfs_env_worker_builds_resets_and_steps_the_documented_env(pod_url):
    for block in _blocks("RLinf", "python"):
        exec(compile(block, str(DOCS), "exec"), {})
    from rlinf.envs import get_env_cls

    cfg = rlinf_config(documented_train(pod_url), K)
    worker = env_worker(cfg, None, NUM_ENVS)
    worker._rank, worker._world_size, worker._worker_info = 0, 1, None  # one env process, no Ray
    train = cfg.env.train
    worker.env_list = worker._setup_env_and_wrappers(get_env_cls(train.env_type, train), train, NUM_ENVS)
    env = worker.env_list[0]
    assert isinstance(env, vecsim.trainers.rlinf.VecsimLiberoEnv)
    try:
        worker._init_env()
        first = worker.bootstrap_step()[0]
        chunk = torch.tensor(np.random.default_rng(3).uniform(-0.5, 0.5, (NUM_ENVS, K, 7)), dtype=torch.float32)
        output, _ = worker.env_interact_step(chunk, 0)
    finally:
        env.close()
    instruction = libero_benchmark(train.task_suite_name).get_task(0).language  # LIBERO's own
    for step in (first, output):
        assert step.obs["main_images"].shape == (NUM_ENVS, SIZE, SIZE, 3)
        assert step.obs["states"].shape == (NUM_ENVS, 8) and step.obs["states"].dtype == torch.float32
        assert list(step.obs["task_descriptions"]) == [instruction] * NUM_ENVS
    assert output.rewards.shape == (NUM_ENVS, K) and torch.isfinite(output.rewards).all()
    # The chunk moved the arm: the state after it is not the reset's.
    assert not torch.equal(first.obs["states"], output.obs["states"])
