"""RLinf's own env worker, made without its Ray base, and the config it reads (RLinf 0.3.0)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any


def rlinf_config(train: Mapping[str, Any], chunk: int) -> Any:
    """An RLinf config as its EnvWorker reads it: ``train`` as ``env.train``, an openpi actor
    acting in chunks of ``chunk`` 7-d actions, one pipeline stage."""
    from omegaconf import OmegaConf

    return OmegaConf.create(
        {
            "env": {"train": dict(train)},
            "actor": {"model": {"model_type": "openpi", "num_action_chunks": chunk, "action_dim": 7}},
            "rollout": {"pipeline_stage_num": 1},
            "runner": {},
        }
    )


def env_worker(cfg: Any, env: Any, num_envs: int) -> Any:
    """RLinf's EnvWorker without its Ray base: only the attributes its four methods read.

    ``EnvWorker.__init__`` needs a Ray cluster (``Worker.__init__``, ``HybridComponentPlacement``),
    so the object is made with ``__new__`` and given what ``_init_env``, ``bootstrap_step``,
    ``env_interact_step`` and ``finish_rollout`` read (env_worker.py:55-160 sets them alike):
    the config, one pipeline stage holding ``env`` (``num_envs`` envs), training on and eval and
    offload off, the model's chunk size, no external reward model; ``_timer_metrics`` and
    ``_accelerator_type`` for the ``Worker.timer`` decorator around them (no accelerator: no
    profiling ranges).
    """
    from rlinf.scheduler.hardware.accelerators.accelerator import AcceleratorType
    from rlinf.workers.env.env_worker import EnvWorker

    worker = EnvWorker.__new__(EnvWorker)
    worker.cfg = cfg
    worker.model_cfg = cfg.actor.model
    worker.stage_num = 1
    worker.enable_train, worker.enable_eval = True, False
    worker.train_enable_offload = worker.eval_enable_offload = False
    worker.train_num_envs_per_stage = num_envs
    worker.use_external_reward_model = False
    worker.env_list, worker.eval_env_list = [env], []
    worker.last_obs_list, worker.last_intervened_info_list = [], []
    worker._timer_metrics = {}
    worker._accelerator_type = AcceleratorType.NO_ACCEL
    return worker
