"""verl-vla's ``BaseEnv`` contract over a vecsim job (verl-vla itself is never imported here).

verl-vla (github.com/verl-project/verl-vla, read at 8a18e3f) runs a chunk ``[B, T, D]`` through
``BaseEnv.step`` (src/verl_vla/envs/base.py:98-114): its serial action executor calls the
one-action hook ``env_step(action, env_ids)`` T times, then ``_finish_execution_slice``
(base.py:282-309) stacks the per-action flags and, with auto-reset, resets the envs that ended
through ``env_reset``. :class:`VecsimLiberoEnv` gives those hooks (``env_init``, ``env_reset``,
``env_step``, ``env_close``, ``env_benchmark_size``) over a vecsim job, and takes over ``step``
to send the whole chunk in one HTTP call per pod wherever nothing may act between two actions
(no teleop, no recorder, the serial executor without interpolation, smoothing or pacing);
otherwise ``BaseEnv.step`` runs as it is, one call per action. Use it ahead of ``BaseEnv``::

    from verl_vla.envs.base import BaseEnv
    from vecsim.trainers.verl_vla import VecsimLiberoEnv

    class LiberoEnv(VecsimLiberoEnv, BaseEnv):   # in place of verl_vla.envs.libero.libero_env.LiberoEnv
        pass

and name the job in the env config: ``simulator.vecsim.controller_url`` (or ``pod_urls``).
docs/trainers.md says what differs from verl-vla's own LIBERO env.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from vecsim.client.conventions import StateNumbering, env_indices, suite_of, suite_task_index
from vecsim.client.vla_env import VLAEnv

__all__ = ["VecsimLiberoEnv"]

@dataclass(frozen=True)
class _Executed:
    """One applied action's flags, shaped as verl-vla's ``ExecutedStep`` (action_executor.py:74-78)."""

    feedback: dict[str, np.ndarray]


def _get(cfg: Any, name: str, default: Any = None) -> Any:
    """``cfg.name`` of an OmegaConf node, a dict or any object; ``default`` if absent or None."""
    value = cfg.get(name, default) if hasattr(cfg, "get") else getattr(cfg, name, default)
    return default if value is None else value


class VecsimLiberoEnv:
    """verl-vla's LIBERO env hooks over a vecsim job; put it before ``BaseEnv`` in the bases.

    The constructor is verl-vla's ``LiberoEnv``'s (libero_env.py:260-275), as its env manager
    calls it (src/verl_vla/workers/env/env_manager.py:359-361). This process's envs
    are the job's envs ``[p * num_envs, (p + 1) * num_envs)`` with ``p = rank * stage_num +
    stage_id``, verl-vla's global process id (libero_env.py:272). ``cfg.simulator.vecsim`` names
    the job (``controller_url`` or ``pod_urls``; ``token``, ``timeout_s``, ``seed``).
    """

    env_type = "libero"

    def __init__(
        self, cfg: Any, rank: int, world_size: int, stage_id: int = 0, stage_num: int = 1, only_eval: bool = False
    ) -> None:
        self.only_eval = bool(only_eval)
        self.stage_num = int(stage_num)  # verl-vla's name (vecsim's is num_stages), as its LiberoEnv keeps it
        self.global_process_id = int(rank) * self.stage_num + int(stage_id)
        super().__init__(cfg, rank, world_size, stage_id=stage_id)  # type: ignore[call-arg]

    # -- BaseEnv's hooks ------------------------------------------------------------------------

    def env_init(self) -> None:
        """Connect to the job and take this process's envs.

        Raises:
            ValueError: no job named, or the job has too few envs for this process (names both).
        """
        vecsim_cfg = _get(_get(self.cfg, "simulator", {}), "vecsim", {})
        controller_url, pod_urls = _get(vecsim_cfg, "controller_url"), _get(vecsim_cfg, "pod_urls")
        if (controller_url is None) == (pod_urls is None):
            raise ValueError("simulator.vecsim: give exactly one of controller_url and pod_urls")
        # verl-vla's LIBERO env steps ended envs on and reads every action's flags (libero_env.py:378-400).
        self.vla = VLAEnv(
            controller_url,
            pod_urls=None if pod_urls is None else list(pod_urls),
            keys="lerobot",
            camera_keys="verl_vla",
            reward_dtype=np.float32,
            ended_envs="step",
            timeout_s=float(_get(vecsim_cfg, "timeout_s", 60.0)),
            token=_get(vecsim_cfg, "token"),
        )
        start = self.global_process_id * self.num_envs
        if start + self.num_envs > self.vla.num_envs:
            self.vla.close()
            raise ValueError(
                f"num_envs: process {self.global_process_id} takes job envs {start}..{start + self.num_envs - 1}, "
                f"but the job has {self.vla.num_envs}"
            )
        self.job_env_ids = np.arange(start, start + self.num_envs)
        tasks = [self.vla.task_ids[i] for i in self.job_env_ids]
        self.task_ids = np.array([suite_task_index(t) for t in tasks], dtype=np.int64)
        self.task_descriptions = [self.vla.instructions[i] for i in self.job_env_ids]
        self._tasks = tasks
        self._numbering = {suite: self.vla.state_numbering(suite) for suite in {suite_of(t) for t in tasks}}
        self._rng = np.random.default_rng(int(_get(vecsim_cfg, "seed", 0)) + self.global_process_id)
        self.reset_state_ids = np.zeros(self.num_envs, dtype=np.int64)  # suite-global, as verl-vla's
        self.eval_episode_ids = np.full(self.num_envs, -1, dtype=np.int64)
        self._eval_queues = self._build_eval_queues()
        self._eval_cursor = np.zeros(self.num_envs, dtype=np.int64)

    def env_benchmark_size(self) -> int:
        """The eval benchmark's episodes: every initial state of the job's tasks, once."""
        return int(sum(self.vla.num_states.values()))

    def env_reset(self, *, env_ids: Any, reset_eval: bool = False, extra: dict[str, Any] | None = None) -> dict[str, Any]:
        """Reset this process's envs ``env_ids`` to states of their own tasks (train: drawn;
        eval: each env's next state of its eval queue; ``extra["info.reset_state_id"]``: that
        suite-global id) and return verl-vla's reset observation (libero_env.py:320-376).

        Raises:
            ValueError: env ids that are not distinct ints in ``0..num_envs-1``, or a reset state
                id out of range or of another task than its env's (names the field); nothing is reset.
        """
        ids = env_indices(env_ids, self.num_envs)
        if reset_eval:
            self._eval_cursor[:] = 0
        if extra is not None:
            wanted = np.asarray(extra.get("info.reset_state_id"), dtype=np.int64).reshape(-1)
            if wanted.size != 1:
                raise ValueError(f"extra['info.reset_state_id'] must hold one id, got {wanted.tolist()}")
            gids = np.full(ids.size, int(wanted[0]), dtype=np.int64)
        elif self.only_eval:
            gids = np.array([self._next_eval_state(i) for i in ids], dtype=np.int64)
        else:
            gids = np.array([self._draw_state(i) for i in ids], dtype=np.int64)
        obs, info = self.vla.reset(env_ids=self.job_env_ids[ids], global_state_ids=gids)
        self.reset_state_ids[ids] = gids
        self.eval_episode_ids[ids] = gids if self.only_eval or extra is not None else -1
        if self.only_eval and extra is None:
            for i in ids:
                self._eval_cursor[i] += 1
        return self._observations(obs, self.job_env_ids[ids], ids)

    def env_step(self, action: Any, *, env_ids: Any) -> dict[str, Any]:
        """Step this process's envs ``env_ids`` one action each (``action`` ``[B, D]``) and return
        verl-vla's step-result dict (libero_env.py:378-400); ended envs are stepped on, as
        verl-vla's own LIBERO env does, their truncation held by the episode limit.

        Raises:
            ValueError: ``action`` not ``[len(env_ids), action dim]``, or bad ``env_ids``.
            ClosedEnvironmentError: after ``env_close``.
        """
        ids = env_indices(env_ids, self.num_envs)
        action = _numpy(action)
        if action.shape != (ids.size, self.vla.action_dim):
            raise ValueError(
                f"action must have shape [{ids.size}, {self.vla.action_dim}] for env_ids {ids.tolist()}, "
                f"got {list(action.shape)}"
            )
        obs, rewards, terminations, truncations, _ = self.vla.chunk_step(action[:, None, :], env_ids=self.job_env_ids[ids])
        return self._step_result(obs, ids, rewards[:, 0], terminations[:, 0], truncations[:, 0])

    def env_close(self) -> None:
        """Close the job's connections (idempotent)."""
        if hasattr(self, "vla"):
            self.vla.close()

    # -- the whole chunk in one call per pod ----------------------------------------------------

    def whole_chunks(self) -> bool:
        """Whether ``step`` may send a whole chunk at once: nothing of ``BaseEnv`` acts between two
        actions of a chunk (base.py:519-585 without teleop; no recorder; action_executor.py:143-168
        with neither interpolation nor smoothing; no ``target_step_hz`` pacing of ``mask_step``)."""
        execution = _get(self.cfg, "action_execution", {})
        return (
            not getattr(self, "teleops", None)
            and getattr(self, "recorder", None) is None
            and getattr(self, "target_step_hz", None) is None
            and _get(execution, "mode", "serial") == "serial"
            and not _get(_get(execution, "interpolation", {}), "enable", False)
            and not _get(_get(execution, "serial_smoothing", {}), "enable", False)
            and bool(_get(_get(_get(self.cfg, "simulator", {}), "vecsim", {}), "whole_chunks", True))
        )

    def step(self, action: Any, **kwargs: Any) -> Any:
        """``BaseEnv.step`` with the chunk ``[num_envs, T, D]`` sent at once where
        :meth:`whole_chunks` holds: every env applies all T actions in one call per pod, the
        per-action flags are handed to ``BaseEnv._finish_execution_slice`` as its executor hands
        them (auto-reset and the result there); else ``BaseEnv.step`` itself.

        Raises:
            ValueError: ``action`` not ``[num_envs, T >= 1, action dim]``; no env is stepped.
        """
        if not self.whole_chunks():
            return super().step(action, **kwargs)  # type: ignore[misc]
        action = _numpy(action)
        if action.ndim != 3 or action.shape[0] != self.num_envs or action.shape[1] < 1 or action.shape[2] != self.vla.action_dim:
            raise ValueError(f"action must have shape [{self.num_envs}, T >= 1, {self.vla.action_dim}], got {list(action.shape)}")
        every = np.arange(self.num_envs)
        obs, rewards, terminations, truncations, _ = self.vla.chunk_step(action, env_ids=self.job_env_ids)
        # What the executor leaves after T one-action steps (base.py:254-280): the merged result
        # of the last action, the done mask over the chunk, one feedback per action.
        last = self._step_result(obs, every, rewards[:, -1], terminations[:, -1], truncations[:, -1])
        self._update_latest_obs(every, last)  # type: ignore[attr-defined]
        self._execution_merged_step_result = {key: value for key, value in last.items() if key != "extra"}
        self._execution_done |= (terminations | truncations).any(axis=1)
        steps = [
            _Executed({
                "next.reward": rewards[:, k].copy(),
                "next.terminated": terminations[:, k].copy(),
                "next.truncated": truncations[:, k].copy(),
                "next.success": terminations[:, k].copy(),
            })
            for k in range(action.shape[1])
        ]  # fmt: skip
        result, _reset_mask = self._finish_execution_slice(steps)  # type: ignore[attr-defined]
        return result

    # -- helpers --------------------------------------------------------------------------------

    def _draw_state(self, i: int) -> int:
        task = self._tasks[i]
        row = int(self._rng.integers(self.vla.num_states[task]))
        return self._numbering[suite_of(task)].global_state_id(suite_task_index(task), row)

    def _build_eval_queues(self) -> list[np.ndarray]:
        """Each env's eval states (suite-global ids): the envs of the job that run one task share
        its states round robin, so every state of the job's tasks is evaluated once."""
        by_task: dict[str, list[int]] = {}
        for job_env, task in enumerate(self.vla.task_ids):
            by_task.setdefault(task, []).append(job_env)
        queues = []
        for job_env, task in zip(self.job_env_ids.tolist(), self._tasks):
            sharing = by_task[task]
            rows = np.arange(sharing.index(job_env), self.vla.num_states[task], len(sharing))
            numbering = self._numbering[suite_of(task)]
            queues.append(np.array([numbering.global_state_id(suite_task_index(task), r) for r in rows], dtype=np.int64))
        return queues

    def _next_eval_state(self, i: int) -> int:
        queue = self._eval_queues[i]
        return int(queue[self._eval_cursor[i] % len(queue)])

    def _observations(self, obs: dict[str, Any], rows: np.ndarray, ids: np.ndarray) -> dict[str, Any]:
        """verl-vla's observation block for local envs ``ids`` from VLAEnv's batched ``obs``
        (rows ``rows`` of it): per-env dicts (libero_env.py:285-301), tasks, int ids."""
        keys = [k for k in obs if k.startswith("observation.")]
        return {
            "observation": [{k: np.asarray(obs[k][r]) for k in keys} for r in rows],
            "task": [self.task_descriptions[i] for i in ids],
            "task_id": self.task_ids[ids].astype(np.int64, copy=True),
            "eval_episode_id": self.eval_episode_ids[ids].astype(np.int64, copy=True),
        }

    def _step_result(
        self, obs: dict[str, Any], ids: np.ndarray, reward: np.ndarray, terminated: np.ndarray, truncated: np.ndarray
    ) -> dict[str, Any]:
        import torch  # verl-vla's env hands torch tensors (libero_env.py:396-399)

        result = self._observations(obs, np.arange(ids.size), ids)
        result["extra"] = [{"info.reset_state_id": np.asarray([self.reset_state_ids[i]], dtype=np.int64)} for i in ids]
        result["next.reward"] = torch.as_tensor(np.asarray(reward, dtype=np.float32))
        result["next.terminated"] = torch.as_tensor(np.asarray(terminated, dtype=bool))
        result["next.truncated"] = torch.as_tensor(np.asarray(truncated, dtype=bool))
        # LIBERO's termination is its success (libero_env.py:399).
        result["next.success"] = torch.as_tensor(np.asarray(terminated, dtype=bool))
        return result


def _numpy(value: Any) -> np.ndarray:
    """A copy of an action array or tensor, as float32 (``BaseEnv.step`` copies too, base.py:106)."""
    if hasattr(value, "detach"):
        value = value.detach().cpu().numpy()
    return np.array(value, dtype=np.float32)
