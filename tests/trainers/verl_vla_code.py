"""verl-vla's own code, re-enacted line by line for the tests (verl-vla is not on the package index).

Read at github.com/verl-project/verl-vla commit 8a18e3fae431ca456395b3589bfe848d569503fe; every
block cites the file and lines it follows (paths under src/verl_vla/). Nothing here is vecsim's:

- verl's ``BaseConfig`` (github.com/verl-project/verl, verl/base_config.py at a910e270) and
  verl-vla's typed env config, ``SimulatorConfig`` and ``EnvWorkerConfig``
  (workers/env/config.py:33-96), as the dataclasses they are; their nested configs keep the
  fields a LIBERO run reads (envs/libero/config.py:24-44, envs/action_executor.py:31-65) or, for
  teleop, recorder, arena and piper, only ``enable``/``simulator_type`` (noted at each);
- ``BaseEnv`` (envs/base.py) as a training run uses it, teleop and recorder off, with its serial
  action executor (envs/action_executor.py);
- the env worker's simulator construction, ``reset_env`` and ``env_interact_step``
  (workers/env/env_worker.py), the env manager's command loop and stop/start
  (workers/env/env_manager.py), in this process instead of a spawned one;
- the env manager again as verl-vla runs it, the simulator in a spawned process
  (:class:`SpawnedEnvManager`, ``_simulator_worker``);
- ``TrainCluster.eval``'s loop and acceptance rule with its non-auto-reset records
  (train_cluster/cluster.py:542-598, 703-739).

:func:`install` registers the module names verl-vla's code is imported by (``verl.base_config``,
``verl_vla.envs.base``, ``verl_vla.workers.env.config``) so that hydra's ``instantiate`` and the
user instructions of docs/trainers.md run against these, as pasted.
"""

from __future__ import annotations

import collections.abc
import copy
import sys
import types
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from dataclasses import FrozenInstanceError, dataclass, field, fields
from types import SimpleNamespace
from typing import Any, Optional

import numpy as np
import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

# -- verl/base_config.py (verl a910e270) -----------------------------------------------------------


def _has_attribute_definition(obj: Any, key: str) -> bool:
    return key in obj.__dict__ or any(key in cls.__dict__ for cls in obj.__class__.__mro__)


@dataclass
class BaseConfig(collections.abc.Mapping):
    """verl's ``BaseConfig``: a frozen dataclass read as a mapping (base_config.py:24-93)."""

    _mutable_fields = set()
    _target_: str = ""

    def __setattr__(self, name: str, value: Any) -> None:
        if name in self.__dict__ and name not in getattr(self, "_mutable_fields", set()):
            raise FrozenInstanceError(f"Field '{name}' is frozen and cannot be modified")
        super().__setattr__(name, value)

    def get(self, key: str, default: Any = None) -> Any:
        try:
            return getattr(self, key)
        except AttributeError:
            return default

    def __getitem__(self, key: str) -> Any:
        try:
            return getattr(self, key)
        except AttributeError as e:
            if _has_attribute_definition(self, key):
                raise
            raise KeyError(key) from e

    def __iter__(self) -> Iterator[str]:
        for f in fields(self):
            yield f.name

    def __len__(self) -> int:
        return len(fields(self))


# -- verl-vla's typed env config ---------------------------------------------------------------------


@dataclass
class LiberoSimulatorConfig(BaseConfig):
    """envs/libero/config.py:24-44 (without its ``env_kwargs`` helper)."""

    simulator_type: str = "libero"
    max_episode_steps: int = 512
    seed: int = 42
    task_suite_name: str = "libero_spatial"
    task_ids: Optional[list[int]] = None
    num_trials_per_task: Optional[int] = None
    specific_reset_id: Optional[int] = None
    reset_warmup_steps: int = 10
    camera_depths: bool = False
    camera_heights: int = 256
    camera_widths: int = 256
    camera_names: list[str] = field(default_factory=lambda: ["agentview", "robot0_eye_in_hand"])


@dataclass
class ArenaSimulatorConfig(BaseConfig):
    """envs/arena/config.py:67: reduced to its simulator_type (a LIBERO run never reads it)."""

    simulator_type: str = "arena"


@dataclass
class PiperConfig(BaseConfig):
    """envs/piper/config.py:77: reduced to its simulator_type (a LIBERO run never reads it)."""

    simulator_type: str = "piper"


@dataclass
class ActionInterpolationConfig(BaseConfig):
    """envs/action_executor.py:31-35 (its range check left out)."""

    enable: bool = False
    factor: int = 2


@dataclass
class SerialActionSmoothingConfig(BaseConfig):
    """envs/action_executor.py:43-48 (its range checks left out)."""

    enable: bool = False
    execution_steps: int = 80
    blend_steps: int = 20


@dataclass
class ActionExecutionConfig(BaseConfig):
    """envs/action_executor.py:58-65 (its checks and instantiation of the nested two left out)."""

    mode: str = "serial"
    replan_after_steps: int = 1
    smooth_overlapping_actions: bool = False
    interpolation: ActionInterpolationConfig = field(default_factory=ActionInterpolationConfig)
    serial_smoothing: SerialActionSmoothingConfig = field(default_factory=SerialActionSmoothingConfig)


@dataclass
class TeleopConfig:
    """teleop/config.py: reduced to ``enable`` (off in a training run)."""

    enable: bool = False


@dataclass
class RecorderConfig:
    """recorder/config.py:46-52: reduced to ``enable``."""

    enable: bool = True


@dataclass
class SimulatorConfig(BaseConfig):
    """workers/env/config.py:33-50."""

    simulator_type: str = "libero"
    libero: LiberoSimulatorConfig = field(default_factory=LiberoSimulatorConfig)
    arena: ArenaSimulatorConfig = field(default_factory=ArenaSimulatorConfig)
    piper: PiperConfig = field(default_factory=PiperConfig)

    def __post_init__(self) -> None:
        if not isinstance(self.libero, LiberoSimulatorConfig):
            object.__setattr__(self, "libero", instantiate(self.libero))
        if not isinstance(self.arena, ArenaSimulatorConfig):
            object.__setattr__(self, "arena", instantiate(self.arena))
        if not isinstance(self.piper, PiperConfig):
            object.__setattr__(self, "piper", instantiate(self.piper))
        if self.simulator_type not in {"libero", "arena", "piper"}:
            raise ValueError(f"Unsupported simulator_type: {self.simulator_type}")


@dataclass
class EnvWorkerConfig(BaseConfig):
    """workers/env/config.py:53-96."""

    auto_reset: bool = False
    confirm_before_record: bool = False
    log_step_latency: bool = False
    target_step_hz: Optional[float] = None
    action_execution: ActionExecutionConfig = field(default_factory=ActionExecutionConfig)
    modes: list[str] = field(default_factory=lambda: ["train"])
    num_envs: int = 1
    simulator: SimulatorConfig = field(default_factory=SimulatorConfig)
    teleop: TeleopConfig = field(default_factory=TeleopConfig)
    recorder: RecorderConfig = field(default_factory=RecorderConfig)
    device: Optional[str] = None
    profiler: Optional[Any] = None
    simulator_start_timeout_s: int = 180

    def __post_init__(self) -> None:
        if not isinstance(self.action_execution, ActionExecutionConfig):
            action_execution = instantiate(self.action_execution)
            if not isinstance(action_execution, ActionExecutionConfig):
                raise TypeError(
                    "action execution config must instantiate to ActionExecutionConfig, "
                    f"got {type(action_execution).__name__}"
                )
            object.__setattr__(self, "action_execution", action_execution)
        if not isinstance(self.simulator, SimulatorConfig):
            simulator = instantiate(self.simulator)
            if not isinstance(simulator, SimulatorConfig):
                raise TypeError(f"simulator config must instantiate to SimulatorConfig, got {type(simulator).__name__}")
            object.__setattr__(self, "simulator", simulator)
        if not isinstance(self.teleop, TeleopConfig):
            object.__setattr__(self, "teleop", instantiate(self.teleop))
        if not isinstance(self.recorder, RecorderConfig):
            object.__setattr__(self, "recorder", instantiate(self.recorder))
        if self.num_envs <= 0:
            raise ValueError(f"num_envs must be positive, got {self.num_envs}")
        if self.target_step_hz is not None and self.target_step_hz <= 0:
            raise ValueError(f"target_step_hz must be positive when set, got {self.target_step_hz}")
        if self.simulator_start_timeout_s <= 0:
            raise ValueError(f"simulator_start_timeout_s must be positive, got {self.simulator_start_timeout_s}")
        if not set(self.modes).issubset({"train", "eval"}):
            raise ValueError(f"Unsupported env worker modes: {self.modes}")


def env_worker_config(env_worker: dict[str, Any]) -> EnvWorkerConfig:
    """The env worker's config from its yaml block, as ``EnvTrainConfig.__post_init__`` builds it
    (train_cluster/config.py:139-141: ``instantiate(self.env_worker, _recursive_=False)``)."""
    return instantiate(OmegaConf.create(env_worker), _recursive_=False)


# -- envs/base.py (BaseEnv) -------------------------------------------------------------------------------


class BaseEnv:
    """verl-vla's ``BaseEnv`` (base.py) as a training run uses it: teleop and recorder off."""

    def __init__(self, cfg, rank: int, world_size: int, stage_id: int = 0) -> None:
        # base.py:73-94
        self.cfg = cfg
        self.rank = rank
        self.world_size = world_size
        self.stage_id = stage_id
        self.num_envs = int(cfg.num_envs)
        self.auto_reset_enabled = bool(cfg.get("auto_reset", False))
        self.log_step_latency = bool(cfg.log_step_latency)
        self.target_step_hz = None if cfg.target_step_hz is None else float(cfg.target_step_hz)
        self._latest_obs = None
        self.env_init()
        self.teleops = []  # create_teleops with teleop.enable false (base.py:681-684)
        self.recorder = None  # create_recorder with recorder.enable false (base.py:809-812)
        self._execution_chunk_intervened = np.zeros(self.num_envs, dtype=bool)
        self._execution_merged_step_result = None
        self._execution_restart_episode = np.zeros(self.num_envs, dtype=bool)
        self._execution_done = np.zeros(self.num_envs, dtype=bool)

    def step(self, action, **kwargs):
        # base.py:106-114, then SerialActionExecutor.exchange (action_executor.py:143-165)
        # without smoothing or interpolation.
        action = self._to_numpy(action, copy=True)
        assert action.ndim == 3 and action.shape[1] > 0  # action_executor.py:317-320
        steps = [
            self._execute_action_step(action[:, k].copy(), np.zeros(self.num_envs, np.float32), k == 0)
            for k in range(action.shape[1])
        ]
        result, _reset_mask = self._finish_execution_slice(steps)
        return result

    def reset(self, *, seed=None, options=None):
        # base.py:117-139 (teleop, recorder and pacing calls are no-ops here)
        del seed
        self._execution_merged_step_result = None
        self._execution_restart_episode.fill(False)
        self._execution_done.fill(False)
        reset_kwargs = self._reset_kwargs_from_options(options)
        reset_eval = bool(reset_kwargs.pop("reset_eval", False))
        if self.auto_reset_enabled and self._latest_obs is not None and not reset_eval:
            return self._latest_obs, {}
        obs = self.env_reset(reset_eval=reset_eval, **reset_kwargs)
        self._latest_obs = obs
        return obs, {}

    def close(self):
        self.env_close()  # base.py:142-146

    def _execute_action_step(self, action, critic_value, chunk_started):
        # base.py:254-280
        if chunk_started:
            self._execution_chunk_intervened.fill(False)
        self._execution_merged_step_result, restart_episode, self._execution_chunk_intervened = (
            self.step_with_teleop_and_recording(
                action,
                critic_value=critic_value,
                chunk_intervened=self._execution_chunk_intervened,
                merged_step_result=self._execution_merged_step_result,
            )
        )
        self._execution_restart_episode |= restart_episode
        self._execution_done |= np.asarray(self._execution_merged_step_result["next.terminated"], dtype=bool)
        self._execution_done |= np.asarray(self._execution_merged_step_result["next.truncated"], dtype=bool)
        feedback = {
            key: np.asarray(self._execution_merged_step_result[key]).copy()
            for key in ("next.reward", "next.terminated", "next.truncated", "next.success")
        }
        return SimpleNamespace(feedback=feedback)

    def _finish_execution_slice(self, steps):
        # base.py:282-309
        reward_steps = torch.stack([torch.as_tensor(step.feedback["next.reward"]) for step in steps], dim=1)
        terminated_steps = torch.stack([torch.as_tensor(step.feedback["next.terminated"]) for step in steps], dim=1)
        truncated_steps = torch.stack([torch.as_tensor(step.feedback["next.truncated"]) for step in steps], dim=1)
        success_steps = torch.stack([torch.as_tensor(step.feedback["next.success"]) for step in steps], dim=1)
        done_mask = (terminated_steps.bool() | truncated_steps.bool()).any(dim=1).numpy()
        reset_mask = done_mask | self._execution_restart_episode
        merged_step_result = self._reset_done_envs(
            self._execution_merged_step_result, np.arange(self.num_envs), done_mask=reset_mask
        )
        if not self.auto_reset_enabled:
            reset_mask.fill(False)
        obs = {
            "observation": merged_step_result["observation"],
            "task": merged_step_result["task"],
            "task_id": merged_step_result["task_id"],
        }
        if "eval_episode_id" in merged_step_result:
            obs["eval_episode_id"] = merged_step_result["eval_episode_id"]
        self._latest_obs = obs
        self._execution_restart_episode.fill(False)
        self._execution_done.fill(False)
        result = copy.deepcopy(obs), reward_steps, terminated_steps, truncated_steps, success_steps
        return result, reset_mask

    def env_benchmark_size(self) -> int:
        return 1  # base.py:403-405

    def _reset_kwargs_from_options(self, options):
        # base.py:407-419
        options = options or {}
        env_ids = options.get("env_idx")
        reset_eval = bool(options.get("reset_eval", False))
        if env_ids is None or reset_eval:
            env_ids = np.arange(self.num_envs)
        reset_kwargs = {"env_ids": env_ids, "reset_eval": reset_eval}
        if "extra" in options:
            reset_kwargs["extra"] = options["extra"]
        return reset_kwargs

    def mask_step(self, action, execute_mask, is_intervention, critic_value, manual_reward=None, force_truncated=None):
        # base.py:452-493 (latency logging and teleop/record calls are no-ops here)
        env_ids = np.flatnonzero(execute_mask)
        action = action[env_ids]
        result = self.env_step(action, env_ids=env_ids)
        result = self._apply_manual_step_overrides(
            result, env_ids=env_ids, manual_reward=manual_reward, force_truncated=force_truncated
        )
        self._update_latest_obs(env_ids, result)
        return result

    def _apply_manual_step_overrides(self, result, *, env_ids, manual_reward=None, force_truncated=None):
        # base.py:495-517
        env_ids = np.asarray(env_ids, dtype=np.int64).reshape(-1)
        if manual_reward is not None:
            manual_reward = np.asarray(manual_reward, dtype=np.float32).reshape(-1)
            for local_id, env_id in enumerate(env_ids):
                if float(manual_reward[env_id]) > 0.0:
                    result["next.reward"][local_id] = float(manual_reward[env_id])
                    result["next.success"][local_id] = True
                    result["next.terminated"][local_id] = True
                    result["next.truncated"][local_id] = False
        if force_truncated is not None:
            force_truncated = np.asarray(force_truncated, dtype=bool).reshape(-1)
            for local_id, env_id in enumerate(env_ids):
                if force_truncated[env_id]:
                    result["next.reward"][local_id] = 0.0
                    result["next.success"][local_id] = False
                    result["next.terminated"][local_id] = False
                    result["next.truncated"][local_id] = True
        return result

    def step_with_teleop_and_recording(self, action, chunk_intervened, merged_step_result, critic_value=None):
        # base.py:526-585 with no teleop: the intervention loop breaks at once.
        if critic_value is None:
            critic_value = np.zeros(self.num_envs, dtype=np.float32)
        is_intervened = np.zeros(self.num_envs, dtype=bool)
        done = np.zeros(self.num_envs, dtype=bool)
        manual_reward = np.zeros(self.num_envs, dtype=np.float32)
        force_truncated = np.zeros(self.num_envs, dtype=bool)
        restart_episode = np.zeros(self.num_envs, dtype=bool)
        chunk_intervened = np.asarray(chunk_intervened, dtype=bool).copy()
        chunk_intervened_before_step = chunk_intervened.copy()
        execute_mask = ~done & (~chunk_intervened_before_step | is_intervened)
        if execute_mask.any():
            step_result = self.mask_step(
                action,
                execute_mask,
                is_intervention=is_intervened,
                critic_value=critic_value,
                manual_reward=manual_reward,
                force_truncated=force_truncated,
            )
            merged_step_result = self._update_step_result(merged_step_result, np.flatnonzero(execute_mask), step_result)
        return merged_step_result, restart_episode, chunk_intervened

    def _update_step_result(self, merged_step_result, env_ids, step_result):
        # base.py:587-620
        env_ids = np.asarray(env_ids, dtype=np.int64).reshape(-1)
        task_ids = self._to_numpy(step_result["task_id"])
        rewards = self._to_numpy(step_result["next.reward"])
        terminations = self._to_numpy(step_result["next.terminated"])
        truncations = self._to_numpy(step_result["next.truncated"])
        successes = self._to_numpy(step_result["next.success"])
        eval_episode_ids = self._to_numpy(step_result.get("eval_episode_id"))
        if merged_step_result is None:
            merged_step_result = {
                "observation": [None] * self.num_envs,
                "task": [None] * self.num_envs,
                "task_id": np.empty(self.num_envs, dtype=task_ids.dtype),
                "next.reward": np.empty(self.num_envs, dtype=rewards.dtype),
                "next.terminated": np.empty(self.num_envs, dtype=bool),
                "next.truncated": np.empty(self.num_envs, dtype=bool),
                "next.success": np.empty(self.num_envs, dtype=bool),
            }
            if eval_episode_ids is not None:
                merged_step_result["eval_episode_id"] = np.empty(self.num_envs, dtype=eval_episode_ids.dtype)
        for local_id, env_id in enumerate(env_ids):
            env_id = int(env_id)
            merged_step_result["observation"][env_id] = step_result["observation"][local_id]
            merged_step_result["task"][env_id] = step_result["task"][local_id]
            merged_step_result["task_id"][env_id] = task_ids[local_id]
            merged_step_result["next.reward"][env_id] = rewards[local_id]
            merged_step_result["next.terminated"][env_id] = terminations[local_id]
            merged_step_result["next.truncated"][env_id] = truncations[local_id]
            merged_step_result["next.success"][env_id] = successes[local_id]
            if eval_episode_ids is not None:
                merged_step_result["eval_episode_id"][env_id] = eval_episode_ids[local_id]
        return merged_step_result

    def _reset_done_envs(self, step_result, env_ids, done_mask):
        # base.py:622-642
        if not self.auto_reset_enabled:
            return step_result
        reset_local_ids = np.flatnonzero(done_mask)
        if len(reset_local_ids) == 0:
            return step_result
        reset_obs = self.env_reset(env_ids=env_ids[reset_local_ids])
        for key in ("observation", "task", "task_id", "eval_episode_id"):
            if key not in step_result or key not in reset_obs:
                continue
            for reset_idx, local_id in enumerate(reset_local_ids):
                step_result[key][local_id] = reset_obs[key][reset_idx]
        return step_result

    def _update_latest_obs(self, env_ids, step_result) -> None:
        # base.py:655-662
        env_ids = np.asarray(env_ids, dtype=np.int64).reshape(-1)
        for local_id, env_id in enumerate(env_ids):
            self._latest_obs["observation"][env_id] = step_result["observation"][local_id]
            self._latest_obs["task"][env_id] = step_result["task"][local_id]
            self._latest_obs["task_id"][env_id] = step_result["task_id"][local_id]
            if "eval_episode_id" in step_result and "eval_episode_id" in self._latest_obs:
                self._latest_obs["eval_episode_id"][env_id] = step_result["eval_episode_id"][local_id]

    @staticmethod
    def _to_numpy(value, *, copy: bool = False):
        # base.py:664-672
        if value is None:
            return None
        value = value.detach().cpu().numpy() if isinstance(value, torch.Tensor) else np.asarray(value)
        return value.copy() if copy else value


# -- workers/env/env_worker.py -----------------------------------------------------------------------


class EnvWorker:
    """The env worker of one rank, as its LIBERO path builds and drives simulators."""

    def __init__(
        self, env_worker_cfg: EnvWorkerConfig, pipeline_stage_num: int, rank: int = 0, world_size: int = 1
    ) -> None:
        # env_worker.py:119-130 (the device and profiler setup left out: a CPU worker)
        self.env_worker_cfg = env_worker_cfg
        self.simulator_type = self.env_worker_cfg.simulator.simulator_type
        self.simulator_cfg = OmegaConf.structured(self.env_worker_cfg)
        self.simulator_list: list[EnvManager] = []
        self.eval_simulator_list: list[EnvManager] = []
        self.stage_num = pipeline_stage_num
        self._rank, self._world_size = rank, world_size

    def _make_eval_env_cfg(self):
        # env_worker.py:155-162
        eval_cfg = copy.deepcopy(self.simulator_cfg)
        OmegaConf.set_readonly(eval_cfg, False)
        OmegaConf.set_struct(eval_cfg, False)
        if "teleop" in eval_cfg:
            OmegaConf.set_readonly(eval_cfg.teleop, False)
            eval_cfg.teleop.enable = False
        return eval_cfg

    def _simulators(self, mode: str):
        # env_worker.py:164-175 (LIBERO has a dedicated eval list)
        if mode == "eval":
            if self.eval_simulator_list:
                return self.eval_simulator_list
            raise RuntimeError("Eval simulator is not initialized. Add 'eval' to env.env_worker.modes.")
        return self.simulator_list

    def init_worker(self) -> None:
        # env_worker.py:177-212 (LIBERO branch), then each simulator started (EnvManager.start_simulator)
        from verl_vla.envs.libero.libero_env import LiberoEnv

        modes = list(self.env_worker_cfg.modes)
        if not set(modes).issubset({"train", "eval"}):
            raise ValueError(f"Unsupported LIBERO env modes: {modes}")
        eval_cfg = self._make_eval_env_cfg() if "eval" in modes else None
        for stage_id in range(self.stage_num):
            if "train" in modes:
                self.simulator_list.append(
                    EnvManager(
                        self.simulator_cfg,
                        rank=self._rank,
                        world_size=self._world_size,
                        env_cls=LiberoEnv,
                        stage_id=stage_id,
                        stage_num=self.stage_num,
                    )
                )
            if eval_cfg is not None:
                self.eval_simulator_list.append(
                    EnvManager(
                        eval_cfg,
                        rank=self._rank,
                        world_size=self._world_size,
                        env_cls=LiberoEnv,
                        stage_id=stage_id,
                        stage_num=self.stage_num,
                        only_eval=True,
                    )
                )
        for simulator in self.simulator_list + self.eval_simulator_list:
            simulator.start_simulator()

    def get_eval_benchmark_size(self) -> int:
        # env_worker.py:325-329
        simulator = self.eval_simulator_list[0] if self.eval_simulator_list else self.simulator_list[0]
        return int(simulator.env_benchmark_size())

    def reset_env(self, mode: str = "train", reset_eval: bool = False) -> dict[str, Any]:
        # env_worker.py:339-371 (DataProto as a dict of tensors and non-tensors)
        simulators = self._simulators(mode)
        result_list = []
        for stage_id in range(self.stage_num):
            options = {"env_idx": list(range(self.env_worker_cfg.num_envs)), "mode": mode}
            if reset_eval:
                options["reset_eval"] = True
            result_list.append(simulators[stage_id].reset(options=options))
        output: dict[str, Any] = {}
        observations = [observation for obs, _info in result_list for observation in obs["observation"]]
        for key in observations[0]:
            output[key] = torch.as_tensor(np.stack([observation[key] for observation in observations]))
        output["task"] = [task for obs, _info in result_list for task in obs["task"]]
        output["task_id"] = np.asarray(
            [t for obs, _info in result_list for t in obs.get("task_id", [])], dtype=np.int64
        )
        eval_episode_ids = [e for obs, _info in result_list for e in obs.get("eval_episode_id", [])]
        if eval_episode_ids:
            output["eval_episode_id"] = np.asarray(eval_episode_ids, dtype=np.int64)
        return output

    def env_interact_step(self, chunk_actions: torch.Tensor, stage_id: int = 0, mode: str = "train") -> dict[str, Any]:
        # env_worker.py:290-323 with create_env_batch_dataproto (76-111)
        simulators = self._simulators(mode)
        step_output = simulators[stage_id].step(chunk_actions, chunk_values=None)
        extracted_obs, chunk_rewards, chunk_terminations, chunk_truncations, chunk_successes = step_output
        batch = {
            f"obs.{key}": torch.as_tensor(np.stack([o[key] for o in extracted_obs["observation"]]))
            for key in extracted_obs["observation"][0]
        }
        batch.update(
            {
                "next.reward": chunk_rewards,
                "next.terminated": chunk_terminations,
                "next.truncated": chunk_truncations,
                "next.success": chunk_successes,
            }
        )
        batch["obs.task"] = extracted_obs["task"]
        batch["obs.task_id"] = np.asarray(extracted_obs["task_id"], dtype=np.int64)
        if extracted_obs.get("eval_episode_id") is not None:
            batch["obs.eval_episode_id"] = np.asarray(extracted_obs["eval_episode_id"], dtype=np.int64)
        return batch

    def close(self) -> None:
        for simulator in self.simulator_list + self.eval_simulator_list:
            simulator.stop_simulator()


# -- workers/env/env_manager.py ------------------------------------------------------------------------


class EnvManager:
    """The env manager: its command protocol and stop/start, with the simulator in this process
    (env_manager.py:151-331, and ``_simulator_worker``'s loop, 334-411, as one call per command)."""

    def __init__(
        self, cfg, rank, world_size, env_cls, stage_id: int = 0, stage_num: int = 1, only_eval: bool = False
    ) -> None:
        # env_manager.py:152-175
        self.cfg, self.rank, self.world_size = cfg, rank, world_size
        self.stage_id, self.stage_num, self.only_eval = stage_id, stage_num, only_eval
        self.env_cls = env_cls
        self.env = None
        self.state_buffer: Optional[bytes] = None
        self.errors: list[str] = []  # what _simulator_worker logs with logger.error (env_manager.py:393)

    def start_simulator(self) -> None:
        # _simulator_worker, env_manager.py:358-367
        try:
            env = self.env_cls(
                self.cfg,
                self.rank,
                self.world_size,
                stage_id=self.stage_id,
                stage_num=self.stage_num,
                only_eval=self.only_eval,
            )
        except TypeError:
            env = self.env_cls(self.cfg, self.rank, self.world_size)
        if self.state_buffer:
            env.load_state(self.state_buffer)
        self.env = env

    def _command(self, method_name: str, args=(), kwargs=None) -> dict[str, Any]:
        # env_manager.py:379-403
        kwargs = kwargs or {}
        try:
            if hasattr(self.env, method_name):
                method = getattr(self.env, method_name)
                assert callable(method), f"Method {method_name} is not callable"
                return {"status": "success", "data": method(*args, **kwargs)}
            self.errors.append(f"Method '{method_name}' not found")
            return {"status": "error", "error": f"Method '{method_name}' not found"}
        except Exception as e:
            return {"status": "error", "error": str(e)}

    def stop_simulator(self) -> None:
        # env_manager.py:235-260
        if self.env is None:
            return
        result = self._command("get_state")
        if result["status"] == "success":
            self.state_buffer = result["data"]
        self.env.close()  # the "shutdown" command (env_manager.py:375-377)
        self.env = None

    def __getattr__(self, name: str):
        # env_manager.py:280-294
        def method_proxy(*args, **kwargs):
            if self.__dict__.get("env") is None:
                raise RuntimeError("Simulator not running")
            result = self._command(name, args, kwargs)
            if result["status"] == "error":
                raise Exception(result["error"])
            return result["data"]

        return method_proxy


def _simulator_worker(
    cfg,
    rank,
    world_size,
    stage_id,
    stage_num,
    env_cls,
    only_eval,
    command_queue,
    result_queue,
    state_buffer,
    bind_numa=True,
) -> None:
    """The spawned simulator process's body (env_manager.py:334-411); NUMA binding (356) only
    where verl-vla asks it (``torch.cuda.is_available()``, 200), never here."""
    import logging
    import os

    pid = os.getpid()
    logger = logging.getLogger(f"simulator_worker_{rank}_{pid}")
    try:
        if bind_numa:
            raise NotImplementedError("NUMA binding is not re-enacted (env_manager.py:356): a CUDA machine's")
        try:
            env = env_cls(cfg, rank, world_size, stage_id=stage_id, stage_num=stage_num, only_eval=only_eval)
        except TypeError:
            env = env_cls(cfg, rank, world_size)
        if state_buffer:
            env.load_state(state_buffer)
        result_queue.put({"status": "ready"})
        while True:
            try:
                command = command_queue.get()
                if command["method"] == "shutdown":
                    env.close()
                    break
                method_name = command["method"]
                args = command.get("args", [])
                kwargs = command.get("kwargs", {})
                if method_name == "__setattr__":
                    attr_name, attr_value = args
                    setattr(env, attr_name, attr_value)
                    result_queue.put({"status": "success", "data": None})
                elif hasattr(env, method_name):
                    method = getattr(env, method_name)
                    assert callable(method), f"Method {method_name} is not callable"
                    result_queue.put({"status": "success", "data": method(*args, **kwargs)})
                else:
                    logger.error(f"Method '{method_name}' not found")
                    result_queue.put({"status": "error", "error": f"Method '{method_name}' not found"})
            except Exception as e:
                logger.exception(e)
                result_queue.put({"status": "error", "error": str(e)})
    except Exception as e:
        logger.exception(e)
        result_queue.put({"status": "error", "error": str(e)})
    finally:
        command_queue.close()
        result_queue.close()


class SpawnedEnvManager:
    """The env manager as verl-vla runs it: its simulator in a process of multiprocessing's
    ``spawn`` context, ``cfg`` and ``env_cls`` pickled into it (env_manager.py:151-331, without
    ``recursive_to_own``'s shared-tensor copies, 138-148: nothing here is in shared memory)."""

    def __init__(
        self,
        cfg,
        rank,
        world_size,
        env_cls,
        stage_id: int = 0,
        stage_num: int = 1,
        only_eval: bool = False,
        start_timeout_s: int = 180,
    ) -> None:
        # env_manager.py:152-175
        self.cfg, self.rank, self.world_size = cfg, rank, world_size
        self.stage_id, self.stage_num, self.only_eval = stage_id, stage_num, only_eval
        self.start_timeout_s = int(start_timeout_s)
        self.process = self.command_queue = self.result_queue = None
        self.state_buffer: Optional[bytes] = None
        self.env_cls = env_cls

    def start_simulator(self) -> None:
        # env_manager.py:177-233
        import queue
        import time

        import torch.multiprocessing as mp

        if self.process:
            return
        self.context = mp.get_context("spawn")
        self.command_queue = self.context.Queue()
        self.result_queue = self.context.Queue()
        self.process = self.context.Process(
            target=_simulator_worker,
            args=(
                self.cfg,
                self.rank,
                self.world_size,
                self.stage_id,
                self.stage_num,
                self.env_cls,
                self.only_eval,
                self.command_queue,
                self.result_queue,
                self.state_buffer,
                torch.cuda.is_available(),
            ),
        )
        self.process.start()
        deadline = time.monotonic() + self.start_timeout_s
        while True:
            remaining_s = deadline - time.monotonic()
            if remaining_s <= 0:
                raise RuntimeError(f"Simulator initialization timed out after {self.start_timeout_s}s")
            try:
                result = self.result_queue.get(timeout=min(1.0, remaining_s))
                break
            except queue.Empty:
                if not self.process.is_alive():
                    raise RuntimeError(
                        f"Simulator initialization process exited (exitcode={self.process.exitcode})"
                    ) from None
        if result["status"] != "ready":
            raise RuntimeError(f"Simulator initialization failed: {result}")

    def stop_simulator(self) -> None:
        # env_manager.py:235-260
        if not self.process:
            return
        self.command_queue.put({"method": "get_state", "args": [], "kwargs": {}})
        result = self.result_queue.get(timeout=180)
        if result["status"] == "success":
            self.state_buffer = result["data"]
        self.command_queue.put({"method": "shutdown"})
        self.command_queue.close()
        self.result_queue.close()
        self.command_queue = self.result_queue = None
        self.process.join(timeout=5)
        if self.process.is_alive():
            self.process.terminate()
            self.process.join()
        self.exitcode = self.process.exitcode
        self.process = None

    def __getattr__(self, name: str):
        # env_manager.py:262-294 (only called for names not set in __init__)
        def method_proxy(*args, **kwargs):
            if self.__dict__.get("process") is None:
                raise RuntimeError("Simulator not running")
            self.command_queue.put({"method": name, "args": args, "kwargs": kwargs})
            result = self.result_queue.get()
            if result["status"] == "error":
                raise Exception(result["error"])
            return result["data"]

        return method_proxy

    def __setattr__(self, name: str, value: Any) -> None:
        # env_manager.py:296-332: the manager's own names here, the others the simulator's
        if name in _MANAGER_NAMES:
            super().__setattr__(name, value)
            return
        if self.__dict__.get("process") is None:
            raise RuntimeError(f"Simulator not running to set attribute {name} to {value}")
        self.command_queue.put({"method": "__setattr__", "args": [name, value], "kwargs": {}})
        result = self.result_queue.get()
        if result["status"] == "error":
            raise Exception(result["error"])


# env_manager.py:298-311, and the exit code kept for the tests.
_MANAGER_NAMES = frozenset(
    {
        "cfg",
        "rank",
        "world_size",
        "stage_id",
        "stage_num",
        "only_eval",
        "process",
        "command_queue",
        "result_queue",
        "state_buffer",
        "env_cls",
        "context",
        "start_timeout_s",
        "exitcode",
    }
)


# -- train_cluster/cluster.py ---------------------------------------------------------------------------


def collect_non_auto_reset_records(batches: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One rollout's trajectory records without auto-reset: ``_collect_trajectory_records``
    (cluster.py:611-639) over the rollout's chunks, then cluster.py:703-739."""
    done_chunks = torch.stack([b["next.terminated"].bool() | b["next.truncated"].bool() for b in batches], dim=1)
    reward_chunks = torch.stack([b["next.reward"].float() for b in batches], dim=1)
    success_chunks = torch.stack([b["next.success"].bool() for b in batches], dim=1)
    chunk_steps = int(done_chunks.shape[-1])
    done_steps = done_chunks.reshape(done_chunks.shape[0], -1)
    reward_steps = reward_chunks.reshape(reward_chunks.shape[0], -1)
    success_steps = success_chunks.reshape(success_chunks.shape[0], -1)
    # The rollout's obs per chunk: the first chunk's are the reset's (env_loop collects them).
    eval_episode_id_steps = np.stack([b["obs.eval_episode_id"] for b in batches], axis=1)
    task_id_steps = np.stack([b["obs.task_id"] for b in batches], axis=1)
    records = []
    for batch_idx in range(done_steps.shape[0]):
        done_row = done_steps[batch_idx].reshape(-1)
        reward_row = reward_steps[batch_idx].reshape(-1)
        success_row = success_steps[batch_idx].reshape(-1)
        done_indices = torch.nonzero(done_row, as_tuple=False).flatten().tolist()
        done_idx = int(done_indices[0]) if done_indices else int(done_row.numel()) - 1
        segment = slice(0, done_idx + 1)
        records.append(
            {
                "length": int(done_idx + 1),
                "chunk_length": int(done_idx // chunk_steps + 1),
                "return": float(reward_row[segment].sum().item()),
                "success": bool(success_row[segment].any().item()),
                "task_id": int(task_id_steps[batch_idx, 0]),
                "eval_episode_id": int(eval_episode_id_steps[batch_idx, 0]),
            }
        )
    return records


def train_cluster_eval(
    worker: EnvWorker, rollout, max_episodes: Optional[int] = None, max_rollouts: int = 1_000
) -> tuple[list[dict[str, Any]], int]:
    """``TrainCluster.eval``'s loop and acceptance rule (cluster.py:550-589) without auto-reset;
    ``rollout(reset_output)`` stands for ``env_loop.generate_sequences(..., eval=True)`` and
    returns the rollout's chunk batches. Bounded by ``max_rollouts`` (verl-vla's loop is not):
    returns the accepted records and the rollouts it took."""
    benchmark_size = int(worker.get_eval_benchmark_size())
    target_episodes = benchmark_size if max_episodes is None else int(max_episodes)
    base_count = target_episodes // benchmark_size
    extra_count = target_episodes % benchmark_size
    target_eval_episode_counts = np.full(benchmark_size, base_count, dtype=np.int64)
    target_eval_episode_counts[:extra_count] += 1
    accepted_eval_episode_counts = np.zeros(benchmark_size, dtype=np.int64)
    eval_step = 0
    trajectory_records: list[dict[str, Any]] = []
    while len(trajectory_records) < target_episodes and eval_step < max_rollouts:
        reset_output = worker.reset_env(mode="eval", reset_eval=eval_step == 0)
        for record in collect_non_auto_reset_records(rollout(reset_output)):
            eval_episode_id = int(record.get("eval_episode_id", -1))
            if eval_episode_id < 0 or eval_episode_id >= benchmark_size:
                continue
            if accepted_eval_episode_counts[eval_episode_id] >= target_eval_episode_counts[eval_episode_id]:
                continue
            trajectory_records.append(record)
            accepted_eval_episode_counts[eval_episode_id] += 1
        eval_step += 1
    return trajectory_records, eval_step


# -- the module names verl-vla's code is imported by ----------------------------------------------------


def _provided() -> dict[str, dict[str, Any]]:
    """verl's and verl-vla's module names and what this module gives each."""
    return {
        "verl.base_config": {"BaseConfig": BaseConfig},
        "verl_vla.envs.base": {"BaseEnv": BaseEnv},
        "verl_vla.envs.libero.config": {"LiberoSimulatorConfig": LiberoSimulatorConfig},
        "verl_vla.envs.action_executor": {"ActionExecutionConfig": ActionExecutionConfig},
        "verl_vla.teleop.config": {"TeleopConfig": TeleopConfig},
        "verl_vla.recorder.config": {"RecorderConfig": RecorderConfig},
        "verl_vla.workers.env.config": {"SimulatorConfig": SimulatorConfig, "EnvWorkerConfig": EnvWorkerConfig},
    }


@contextmanager
def install() -> Iterator[None]:
    """Register this module's re-enactments under verl's and verl-vla's module names for the
    block (hydra's ``instantiate`` and docs/trainers.md's instructions import them by name)."""
    provided = _provided()
    names = sorted({".".join(name.split(".")[: i + 1]) for name in provided for i in range(name.count(".") + 1)})
    saved = {name: sys.modules.get(name) for name in names + ["verl_vla.envs.libero.libero_env"]}
    try:
        for name in names:
            module = types.ModuleType(name, "re-enacted for vecsim's tests")
            module.__dict__.update(provided.get(name, {}))
            sys.modules[name] = module
            parent, _, child = name.rpartition(".")
            if parent:
                setattr(sys.modules[parent], child, module)
        yield
    finally:
        for name, module in saved.items():
            if module is None:
                sys.modules.pop(name, None)
            else:
                sys.modules[name] = module


def write_packages(root: Path) -> None:
    """Write, under ``root``, the modules :func:`install` registers, as files that import this
    module's re-enactments: with ``root`` on ``sys.path``, a spawned process (which gets the
    parent's ``sys.path``, not its ``sys.modules``) imports verl-vla's names as if it were
    installed."""
    for name, provided in _provided().items():
        parts = name.split(".")
        for depth in range(1, len(parts)):
            package = root.joinpath(*parts[:depth])
            package.mkdir(parents=True, exist_ok=True)
            (package / "__init__.py").touch()
        (root.joinpath(*parts[:-1]) / f"{parts[-1]}.py").write_text(
            f"from verl_vla_code import {', '.join(provided)}\n"
        )
