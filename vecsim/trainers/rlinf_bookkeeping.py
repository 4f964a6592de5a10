"""RLinf 0.3.0's ``LiberoEnv`` bookkeeping, re-enacted from its code for
:class:`vecsim.trainers.rlinf.VecsimLiberoEnv` (cited as ``libero_env.py:<line>``): the draws of
suite-global reset ids, the episode statistics and rewards, and the auto-reset of ended envs.

Nothing here talks to a pod: :class:`LiberoBookkeeping` reads and writes the arrays its subclass
sets up in its constructor and calls the subclass's ``reset`` for an auto-reset.
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Sequence
from typing import Any

import numpy as np

from vecsim.suites import LIBERO_SUITES

logger = logging.getLogger(__name__)

__all__ = ["LIBERO_SUITE_TASKS", "LiberoBookkeeping", "to_tensor"]

# How many tasks each LIBERO suite has: RLinf numbers reset ids over the whole suite
# (libero_env.py:395-402), also over tasks the job does not serve.
LIBERO_SUITE_TASKS = {suite: libero.num_tasks for suite, libero in LIBERO_SUITES.items()}


class LiberoBookkeeping:
    """RLinf's reset-id draws, metrics, rewards and auto-reset over ``num_envs`` slots.

    A subclass sets the attributes RLinf's constructor sets (``cfg``, ``num_envs``, ``suite``,
    ``is_eval``, ``task_id_filter``, ``specific_reset_id``, the generators, ...) and provides
    ``reset(env_idx, reset_state_ids)``.
    """

    num_envs: int

    # -- RLinf's reset-id bookkeeping, re-enacted (libero_env.py:395-539) ---------------------------

    def _compute_total_num_group_envs(self) -> None:
        # libero_env.py:395-429, with per-task counts from the job's /v1/info instead of LIBERO's files
        self.trial_id_bins = [self._states_per_task] * LIBERO_SUITE_TASKS[self.suite]
        self.total_num_group_envs = sum(self.trial_id_bins)
        self.cumsum_trial_id_bins = np.cumsum(self.trial_id_bins)
        if self.task_id_filter is None:
            self._valid_reset_state_ids = None
            return
        num_tasks = len(self.trial_id_bins)
        validated = []
        for tid in self.task_id_filter:
            if not isinstance(tid, (int, np.integer)):
                raise ValueError(f"task_id_filter must contain ints, got {type(tid).__name__}: {tid}")
            if not 0 <= int(tid) < num_tasks:
                raise ValueError(f"task_id {int(tid)} in task_id_filter is out of range [0, {num_tasks - 1}]")
            validated.append(int(tid))
        ids: list[int] = []
        for tid in sorted(set(validated)):
            start = self.cumsum_trial_id_bins[tid - 1] if tid > 0 else 0
            ids.extend(range(start, self.cumsum_trial_id_bins[tid]))
        self._valid_reset_state_ids = np.array(ids)

    def update_reset_state_ids(self) -> None:
        """Draw the next group-shared reset ids (libero_env.py:431-436); RLinf's ``finish_rollout`` calls it."""
        if self.is_eval or self.cfg.use_ordered_reset_state_ids:
            reset_state_ids = self._get_ordered_reset_state_ids(self.num_group)
        else:
            reset_state_ids = self._get_random_reset_state_ids(self.num_group)
        self.reset_state_ids = reset_state_ids.repeat(self.group_size)

    def _get_random_reset_state_ids(self, num_reset_states: int) -> np.ndarray:
        # libero_env.py:443-457
        if self.specific_reset_id is not None:
            return self.specific_reset_id * np.ones((num_reset_states,), dtype=int)
        if self._valid_reset_state_ids is not None:
            indices = self._generator.integers(low=0, high=len(self._valid_reset_state_ids), size=(num_reset_states,))
            return self._valid_reset_state_ids[indices]
        return self._generator.integers(low=0, high=self.total_num_group_envs, size=(num_reset_states,))

    def get_reset_state_ids_all(self) -> np.ndarray:
        """Every process's reset-id pool (libero_env.py:459-488), eval order interleaved by task."""
        if self.is_eval:
            if self._valid_reset_state_ids is not None:
                ids = self._valid_reset_state_ids.copy()
            else:
                ids = _interleaved_eval_ids(self.trial_id_bins, self.cumsum_trial_id_bins)
            return _round_robin(ids, self.total_num_processes)
        valid = self._valid_reset_state_ids
        ids = valid.copy() if valid is not None else np.arange(self.total_num_group_envs)
        self._generator_ordered.shuffle(ids)
        if len(ids) < self.total_num_processes:
            ids = np.tile(ids, (self.total_num_processes // len(ids)) + 1)
        ids = ids[: len(ids) - (len(ids) % self.total_num_processes)]
        return ids.reshape(self.total_num_processes, -1)

    def _get_ordered_reset_state_ids(self, num_reset_states: int) -> np.ndarray:
        # libero_env.py:490-513
        if self.specific_reset_id is not None:
            return self.specific_reset_id * np.ones((num_reset_states,), dtype=int)
        if self.is_eval:
            pool = self._eval_reset_pool
            result = np.full((num_reset_states,), -1, dtype=np.int64)
            if self.start_idx >= len(pool):
                return result
            end = min(self.start_idx + num_reset_states, len(pool))
            result[: end - self.start_idx] = pool[self.start_idx : end]
            self.start_idx = end
            return result
        if self.start_idx + num_reset_states > len(self.reset_state_ids_all[0]):
            self.reset_state_ids_all = self.get_reset_state_ids_all()
            self.start_idx = 0
        ids = self.reset_state_ids_all[self.seed_offset][self.start_idx : self.start_idx + num_reset_states]
        self.start_idx += num_reset_states
        return ids

    def _get_task_and_trial_ids_from_reset_state_ids(self, reset_state_ids: Any) -> tuple[np.ndarray, np.ndarray]:
        """``(task indices, rows)`` of suite-global reset ids (libero_env.py:515-528).

        Raises:
            ValueError: an id outside the suite's range (RLinf drops it silently; names it here).
        """
        ids = np.asarray(reset_state_ids).reshape(-1)
        if ids.dtype.kind not in "iu":
            raise ValueError(f"reset_state_ids must be integers, got dtype {ids.dtype}")
        bad = [int(i) for i in ids if not 0 <= i < self.total_num_group_envs]
        if bad:
            raise ValueError(
                f"reset_state_ids {bad} are outside {self.suite}'s 0..{self.total_num_group_envs - 1} "
                f"({len(self.trial_id_bins)} tasks x {self._states_per_task} states)"
            )
        tasks = np.searchsorted(self.cumsum_trial_id_bins, ids, side="right")
        starts = np.concatenate([[0], self.cumsum_trial_id_bins])[tasks]
        return tasks.astype(np.int64), (ids - starts).astype(np.int64)

    # -- RLinf's properties and metrics (libero_env.py:541-607) -------------------------------------

    @property
    def elapsed_steps(self) -> np.ndarray:
        return self._elapsed_steps

    @property
    def info_logging_keys(self) -> list[str]:
        return []

    @property
    def is_start(self) -> bool:
        return self._is_start

    @is_start.setter
    def is_start(self, value: bool) -> None:
        self._is_start = value

    def _init_metrics(self) -> None:
        self.success_once = np.zeros(self.num_envs, dtype=bool)
        self.fail_once = np.zeros(self.num_envs, dtype=bool)
        self.returns = np.zeros(self.num_envs)
        self.success_episode_len = np.zeros(self.num_envs, dtype=np.int32)
        self._task_success_stats: dict[int, dict[str, int]] = {}
        self._eval_seen_trials: set[tuple[int, int]] = set()

    def _reset_metrics(self, env_idx: np.ndarray) -> None:
        mask = np.zeros(self.num_envs, dtype=bool)
        mask[env_idx] = True
        self.prev_step_reward[mask] = 0.0
        self.success_once[mask] = False
        self.fail_once[mask] = False
        self.returns[mask] = 0
        self.success_episode_len[mask] = 0
        self._elapsed_steps[env_idx] = 0

    def _record_metrics(self, step_reward: np.ndarray, terminations: np.ndarray, infos: dict) -> dict:
        # libero_env.py:583-607
        self.returns += step_reward * (~self.success_once)
        new_success = terminations & ~self.success_once
        if new_success.any():
            self.success_episode_len[new_success] = self.elapsed_steps[new_success]
        self.success_once = self.success_once | terminations
        episode = {
            "success_once": self.success_once.copy(),
            "return": self.returns.copy(),
            "episode_len": self.elapsed_steps.copy(),
        }
        length = np.where(self.success_once, self.success_episode_len, self.elapsed_steps)
        episode["reward"] = episode["return"] / np.maximum(length, 1)
        infos["episode"] = to_tensor(episode)
        return infos

    def _calc_step_reward(self, terminations: np.ndarray) -> np.ndarray:
        # libero_env.py:878-888: RLinf's reward, from the pod's per-action success
        step_penalty = -1 if self.use_step_penalty else 0
        reward = step_penalty + self.cfg.reward_coef * terminations
        if self.use_rel_reward:
            diff = reward - self.prev_step_reward
            self.prev_step_reward = reward
            return diff
        return reward

    # -- auto-reset (libero_env.py:816-876) ----------------------------------------------------------

    def _handle_auto_reset(self, dones: np.ndarray, final_obs: Any, infos: dict) -> tuple[Any, dict, Any]:
        if self.is_eval:
            return self._handle_eval_auto_reset(dones, final_obs, infos)
        obs, infos = self._handle_train_auto_reset(dones, final_obs, infos)
        return obs, infos, None

    def _handle_eval_auto_reset(self, dones: np.ndarray, last_obs: Any, infos: dict) -> tuple[Any, dict, np.ndarray]:
        final_obs = copy.deepcopy(last_obs)
        env_idx = np.arange(0, self.num_envs)[dones]
        final_info = copy.deepcopy(infos)
        count_mask = self._count_completed(env_idx, final_info)
        new_ids = self._get_ordered_reset_state_ids(len(env_idx))
        valid = new_ids >= 0
        to_reset = env_idx[valid]
        if len(to_reset) > 0:
            self.reset_state_ids[to_reset] = new_ids[valid]
            obs, infos = self.reset(env_idx=to_reset, reset_state_ids=self.reset_state_ids[to_reset])
        else:
            obs, infos = last_obs, {}
        _keep_lost(infos, final_info)
        infos["final_observation"] = final_obs
        infos["final_info"] = final_info
        infos["_final_info"] = np.asarray(dones, dtype=bool) & count_mask
        infos["_final_observation"] = dones
        infos["_elapsed_steps"] = dones
        return obs, infos, count_mask

    def _count_completed(self, env_idx: np.ndarray, final_info: dict) -> np.ndarray:
        # rlinf/envs/libero/utils.py record_completed_episode_task_stats: each (task, trial) once
        count_mask = np.zeros(self.num_envs, dtype=bool)
        episode = final_info.get("episode")
        if not episode or "success_once" not in episode:
            return count_mask
        success = np.asarray(episode["success_once"])
        for eid in env_idx:
            key = (int(self.task_ids[eid]), int(self.trial_ids[eid]))
            if key in self._eval_seen_trials:
                logger.warning("[libero eval] duplicate episode skipped: task_id=%d, trial_id=%d", *key)
                continue
            self._eval_seen_trials.add(key)
            count_mask[eid] = True
            stats = self._task_success_stats.setdefault(key[0], {"success": 0, "total": 0})
            stats["total"] += 1
            stats["success"] += int(bool(success[eid]))
        return count_mask

    def _handle_train_auto_reset(self, dones: np.ndarray, last_obs: Any, infos: dict) -> tuple[Any, dict]:
        final_obs = copy.deepcopy(last_obs)
        env_idx = np.arange(0, self.num_envs)[dones]
        final_info = copy.deepcopy(infos)
        if self.use_fixed_reset_state_ids:
            self.update_reset_state_ids()
            obs, infos = self.reset(env_idx=env_idx, reset_state_ids=self.reset_state_ids[env_idx])
        else:
            obs, infos = self.reset(env_idx=env_idx, reset_state_ids=None)
        _keep_lost(infos, final_info)
        infos["final_observation"] = final_obs
        infos["final_info"] = final_info
        infos["_final_info"] = np.asarray(dones, dtype=bool)
        infos["_final_observation"] = dones
        infos["_elapsed_steps"] = dones
        return obs, infos


def to_tensor(value: Any) -> Any:
    """RLinf's ``rlinf.envs.utils.to_tensor`` on CPU (envs/utils.py:53-101): float64 -> float32."""
    import torch

    if value is None:
        return None
    if isinstance(value, dict):
        return {k: to_tensor(v) for k, v in value.items()}
    if isinstance(value, torch.Tensor):
        out = value
    elif isinstance(value, np.ndarray):
        if value.dtype == object:
            return [to_tensor(x) for x in value]
        if value.dtype == np.uint16:
            value = value.astype(np.int32)
        elif value.dtype == np.uint32:
            value = value.astype(np.int64)
        out = torch.tensor(value)
    else:
        out = torch.tensor(value)
    return out.to(torch.float32) if out.dtype == torch.float64 else out


def _interleaved_eval_ids(bins: Sequence[int], cumsum: np.ndarray) -> np.ndarray:
    # rlinf/envs/libero/utils.py build_interleaved_eval_reset_state_ids: (task0, trial0), (task1, trial0), ...
    ids = [
        (cumsum[t - 1] if t > 0 else 0) + trial
        for trial in range(max(bins, default=0))
        for t in range(len(bins))
        if trial < bins[t]
    ]
    return np.array(ids, dtype=np.int64)


def _round_robin(ids: np.ndarray, n_procs: int) -> np.ndarray:
    # rlinf/envs/libero/utils.py distribute_reset_state_ids_round_robin
    width = int(np.bincount(np.arange(len(ids)) % n_procs, minlength=n_procs).max())
    out = np.full((n_procs, width), -1, dtype=np.int64)
    for i, state_id in enumerate(ids):
        out[i % n_procs, i // n_procs] = state_id
    return out


def _keep_lost(infos: dict, final_info: dict) -> None:
    """After an auto-reset: the chunk's ``lost`` flags stay in the infos RLinf's worker reads."""
    if "lost" in final_info:
        infos["lost"] = final_info["lost"]
