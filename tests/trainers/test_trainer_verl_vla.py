"""verl-vla's own env code drives vecsim's verl-vla env over a real LIBERO job.

verl-vla (github.com/verl-project/verl-vla) is not on the package index, so ``BaseEnv`` below
re-enacts, line by line, what its ``BaseEnv`` does around the subclass hooks at commit
8a18e3fae431ca456395b3589bfe848d569503fe (src/verl_vla/envs/base.py; its serial action executor,
src/verl_vla/envs/action_executor.py), with teleop and the recorder off, as a training run has
them; ``reset_env``/``interact_step`` re-enact its env worker (src/verl_vla/workers/env/env_worker.py).
Each block cites the lines it follows. vecsim's adapter sits in front of it, as a user would
put it in front of verl-vla's own ``BaseEnv``.
"""

from __future__ import annotations

import copy
from collections.abc import Iterator
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
import torch
from gymnasium.error import ClosedEnvironmentError
from support.service_procs import PodSpec, RunningPod, standalone_pods
from support.wire_http import metric

from vecsim.config import CameraConfig
from vecsim.trainers.verl_vla import VecsimLiberoEnv

pytestmark = pytest.mark.libero

LIMIT = 20  # the job's episode limit: the third chunk of 8 ends every episode at its 4th action
K = 8
TASKS = ("libero_spatial/0", "libero_spatial/3")


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
        steps = [self._execute_action_step(action[:, k].copy(), np.zeros(self.num_envs, np.float32), k == 0) for k in range(action.shape[1])]
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
        self._execution_merged_step_result, restart_episode, self._execution_chunk_intervened = self.step_with_teleop_and_recording(
            action, critic_value=critic_value, chunk_intervened=self._execution_chunk_intervened, merged_step_result=self._execution_merged_step_result
        )
        self._execution_restart_episode |= restart_episode
        self._execution_done |= np.asarray(self._execution_merged_step_result["next.terminated"], dtype=bool)
        self._execution_done |= np.asarray(self._execution_merged_step_result["next.truncated"], dtype=bool)
        feedback = {key: np.asarray(self._execution_merged_step_result[key]).copy() for key in ("next.reward", "next.terminated", "next.truncated", "next.success")}
        return SimpleNamespace(feedback=feedback)

    def _finish_execution_slice(self, steps):
        # base.py:282-309
        reward_steps = torch.stack([torch.as_tensor(step.feedback["next.reward"]) for step in steps], dim=1)
        terminated_steps = torch.stack([torch.as_tensor(step.feedback["next.terminated"]) for step in steps], dim=1)
        truncated_steps = torch.stack([torch.as_tensor(step.feedback["next.truncated"]) for step in steps], dim=1)
        success_steps = torch.stack([torch.as_tensor(step.feedback["next.success"]) for step in steps], dim=1)
        done_mask = (terminated_steps.bool() | truncated_steps.bool()).any(dim=1).numpy()
        reset_mask = done_mask | self._execution_restart_episode
        merged_step_result = self._reset_done_envs(self._execution_merged_step_result, np.arange(self.num_envs), done_mask=reset_mask)
        if not self.auto_reset_enabled:
            reset_mask.fill(False)
        obs = {"observation": merged_step_result["observation"], "task": merged_step_result["task"], "task_id": merged_step_result["task_id"]}
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
        result = self._apply_manual_step_overrides(result, env_ids=env_ids, manual_reward=manual_reward, force_truncated=force_truncated)
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
                action, execute_mask, is_intervention=is_intervened, critic_value=critic_value,
                manual_reward=manual_reward, force_truncated=force_truncated,
            )  # fmt: skip
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


class Env(VecsimLiberoEnv, BaseEnv):
    """What a verl-vla user writes: vecsim's hooks ahead of ``BaseEnv``."""


def reset_env(env: Env, reset_eval: bool = False) -> dict[str, Any]:
    """env_worker.py:339-371 for one stage: its reset options and the batch it builds."""
    options = {"env_idx": list(range(env.num_envs)), "mode": "train"}
    if reset_eval:
        options["reset_eval"] = True
    obs, _info = env.reset(options=options)
    out = {key: torch.as_tensor(np.stack([o[key] for o in obs["observation"]])) for key in obs["observation"][0]}
    out["task"] = list(obs["task"])
    out["task_id"] = np.asarray(list(obs.get("task_id", [])), dtype=np.int64)  # env_worker.py:362-363
    out["eval_episode_id"] = np.asarray(list(obs.get("eval_episode_id", [])), dtype=np.int64)
    return out


def interact_step(env: Env, chunk: torch.Tensor) -> dict[str, Any]:
    """env_worker.py:306-323 and create_env_batch_dataproto (76-111) for one stage."""
    step_output = env.step(chunk, chunk_values=None)
    extracted_obs, chunk_rewards, chunk_terminations, chunk_truncations, chunk_successes = step_output
    batch = {f"obs.{key}": torch.as_tensor(np.stack([o[key] for o in extracted_obs["observation"]])) for key in extracted_obs["observation"][0]}
    batch.update({"next.reward": chunk_rewards, "next.terminated": chunk_terminations, "next.truncated": chunk_truncations, "next.success": chunk_successes})
    batch["obs.task"] = extracted_obs["task"]
    batch["obs.task_id"] = np.asarray(extracted_obs["task_id"], dtype=np.int64)  # env_worker.py:106
    if extracted_obs.get("eval_episode_id") is not None:
        batch["obs.eval_episode_id"] = np.asarray(extracted_obs["eval_episode_id"], dtype=np.int64)
    return batch


# -- the job -------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def pods(tmp_path_factory) -> Iterator[list[RunningPod]]:
    camera = CameraConfig(height=32, width=32)
    specs = [PodSpec(f"sim-{i}", 0, [(task, 1)], camera=camera, max_episode_steps=LIMIT) for i, task in enumerate(TASKS)]
    with standalone_pods(specs, tmp_path_factory.mktemp("pods")) as running:
        yield running


def config(pods, *, auto_reset: bool = False, whole_chunks: bool = True, num_envs: int = 2) -> SimpleNamespace:
    """The env config verl-vla hands its env (the keys BaseEnv reads, base.py:73-94)."""
    vecsim = {"pod_urls": [p.url for p in pods], "seed": 3, "whole_chunks": whole_chunks}
    cfg = {"num_envs": num_envs, "auto_reset": auto_reset, "log_step_latency": False, "target_step_hz": None,
           "simulator": {"vecsim": vecsim}, "action_execution": {"mode": "serial"}}  # fmt: skip
    return _Node(cfg)


class _Node(SimpleNamespace):
    """A config node read as OmegaConf's DictConfig is: attributes and ``get``."""

    def __init__(self, values: dict[str, Any]) -> None:
        super().__init__(**{k: _Node(v) if isinstance(v, dict) else v for k, v in values.items()})

    def get(self, name: str, default: Any = None) -> Any:
        return getattr(self, name, default)


def step_requests(pods) -> list[float]:
    return [metric(p.url, "vecsim_pod_step_seconds_count") for p in pods]


def resets(pods) -> list[float]:
    return [metric(p.url, "vecsim_pod_env_resets") for p in pods]


def chunks(n: int, seed: int = 0) -> list[torch.Tensor]:
    rng = np.random.default_rng(seed)
    return [torch.as_tensor(rng.uniform(-0.3, 0.3, (2, K, 7)).astype(np.float32)) for _ in range(n)]


@pytest.fixture
def env(pods) -> Iterator[Env]:
    made = Env(config(pods), rank=0, world_size=1)
    yield made
    made.close()


# -- what verl-vla reads -------------------------------------------------------------------------


def test_reset_answers_per_env_dicts_with_verl_vla_keys_and_int_task_ids(env):
    batch = reset_env(env)
    assert batch["observation.images.image"].shape == (2, 32, 32, 3)
    assert batch["observation.images.wrist_image"].shape == (2, 32, 32, 3)
    assert batch["observation.state"].shape == (2, 8)  # LIBERO's 8-float state
    assert batch["task_id"].tolist() == [0, 3] and batch["task_id"].dtype == np.int64
    assert batch["task"] == env.vla.instructions and batch["eval_episode_id"].tolist() == [-1, -1]


def test_eval_resets_walk_each_tasks_states_in_order_and_name_them(pods):
    made = Env(config(pods), rank=0, world_size=1, only_eval=True)
    try:
        first = reset_env(made, reset_eval=True)
        second = reset_env(made)
        again = reset_env(made, reset_eval=True)
        assert made.env_benchmark_size() == 100
    finally:
        made.close()
    assert first["eval_episode_id"].tolist() == [0, 150] and second["eval_episode_id"].tolist() == [1, 151]
    assert again["eval_episode_id"].tolist() == [0, 150]
    assert torch.equal(first["observation.state"], again["observation.state"])


# -- chunks --------------------------------------------------------------------------------------


def test_a_chunk_is_one_request_per_pod_and_equals_verl_vlas_own_step_loop(pods):
    runs = {}
    for whole in (True, False):
        made = Env(config(pods, whole_chunks=whole), rank=0, world_size=1)
        try:
            made._latest_obs = _reset_to(made, [7, 159])
            before = step_requests(pods)
            runs[whole] = [interact_step(made, c) for c in chunks(2, seed=5)]
            sent = [a - b for a, b in zip(step_requests(pods), before)]
        finally:
            made.close()
        assert sent == ([2, 2] if whole else [2 * K, 2 * K])
    for chunk, loop in zip(runs[True], runs[False]):
        assert chunk.keys() == loop.keys()
        for key, value in chunk.items():
            if isinstance(value, torch.Tensor):
                assert torch.equal(value, loop[key]), key
            else:
                assert np.array_equal(np.asarray(value), np.asarray(loop[key])), key


def _reset_to(env: Env, global_ids: list[int]) -> dict[str, Any]:
    """A reset of both envs to chosen states, through the hook verl-vla's replay uses (extra)."""
    obs = [env.env_reset(env_ids=[i], extra={"info.reset_state_id": np.array([gid])}) for i, gid in enumerate(global_ids)]
    return {key: [item for o in obs for item in o[key]] for key in obs[0]}


def test_an_episode_that_ends_mid_chunk_is_stepped_on_without_auto_reset(env, pods):
    env._latest_obs = _reset_to(env, [7, 159])
    batches = [interact_step(env, c) for c in chunks(4, seed=1)]
    truncated = torch.cat([b["next.truncated"] for b in batches], dim=1)
    # The limit of 20 comes at action 20 (index 19) and holds after it, as verl-vla's own
    # LIBERO env counts (libero_env.py:380-383); no env is reset, none refused.
    assert not truncated[:, : LIMIT - 1].any() and truncated[:, LIMIT - 1 :].all()
    assert batches[-1]["obs.observation.state"].shape == (2, 8)


def test_with_auto_reset_an_env_that_ends_mid_chunk_is_reset_once_after_the_chunk(pods):
    made = Env(config(pods, auto_reset=True), rank=0, world_size=1)
    try:
        made._latest_obs = _reset_to(made, [7, 159])
        before = resets(pods)
        for chunk in chunks(2, seed=1):
            interact_step(made, chunk)
        ending = interact_step(made, chunks(1, seed=2)[0])
        after_end = resets(pods)
        fresh = interact_step(made, chunks(1, seed=3)[0])
    finally:
        made.close()
    assert [a - b for a, b in zip(after_end, before)] == [1, 1]  # one reset each, after the chunk
    assert ending["next.truncated"][:, LIMIT - 2 * K - 1 :].all()  # the chunk stayed in the old episode
    assert not fresh["next.truncated"].any()  # a fresh episode's first chunk


def test_base_env_steps_a_subset_of_envs_through_the_one_action_hook(env, pods):
    env._latest_obs = _reset_to(env, [7, 159])
    before_state = np.stack([o["observation.state"] for o in env._latest_obs["observation"]])
    sent = step_requests(pods)
    result = env.mask_step(np.full((2, 7), 0.2, np.float32), np.array([False, True]), np.zeros(2, bool), np.zeros(2, np.float32))
    assert [a - b for a, b in zip(step_requests(pods), sent)] == [0, 1]  # env 0's pod got nothing
    assert result["task_id"].tolist() == [3] and len(result["observation"]) == 1
    after_state = np.stack([o["observation.state"] for o in env._latest_obs["observation"]])
    assert np.array_equal(after_state[0], before_state[0]) and not np.array_equal(after_state[1], before_state[1])


# -- bad input -----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda e: e.step(torch.zeros(2, K, 6)), r"action must have shape \[2, T >= 1, 7\]"),
        (lambda e: e.step(torch.zeros(3, K, 7)), r"action must have shape \[2, T >= 1, 7\]"),
        (lambda e: e.env_step(np.zeros((1, 7)), env_ids=[5]), r"env_ids must be distinct env indices 0..1"),
        (lambda e: e.env_step(np.zeros((2, 7)), env_ids=[1]), r"action must have shape \[1, 7\]"),
        (lambda e: e.env_reset(env_ids=[0], extra={"info.reset_state_id": np.array([150])}), r"env 0 runs libero_spatial/0"),
        (lambda e: e.env_reset(env_ids=[0], extra={"info.reset_state_id": np.array([200])}), r"outside 0..199"),
    ],
)
def test_bad_input_is_refused_naming_the_field_and_changes_no_env(env, pods, call, message):
    env._latest_obs = _reset_to(env, [7, 159])
    counts = step_requests(pods), resets(pods)
    with pytest.raises(ValueError, match=message):
        call(env)
    assert (step_requests(pods), resets(pods)) == counts


def test_stepping_after_close_is_refused(pods):
    made = Env(config(pods), rank=0, world_size=1)
    made._latest_obs = _reset_to(made, [7, 159])
    made.close()
    with pytest.raises(ClosedEnvironmentError):
        made.step(torch.zeros(2, K, 7))


def test_a_process_beyond_the_jobs_envs_is_refused(pods):
    with pytest.raises(ValueError, match=r"num_envs: process 1 takes job envs 2..3, but the job has 2"):
        Env(config(pods), rank=1, world_size=2)
