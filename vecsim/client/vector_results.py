"""What a call's answer makes of :class:`~vecsim.client.vector_env.HTTPVectorEnv`'s envs.

:class:`EnvResults` holds each env's state between calls (its last observation; whether it was
ever reset, ended under autoreset or got no answer) and turns a call's
:class:`~vecsim.client.calls.StageBatch` answers into gymnasium's ``(obs, info)`` and
``(obs, reward, terminated, truncated, info)``, with ``info``'s ``_key`` masks, ``final_obs``
under SAME_STEP and ``num_steps`` for chunks (``StageBatch.chunk``).
"""

from __future__ import annotations

import contextlib
import copy
import logging
from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np
from gymnasium import Space
from gymnasium.error import ResetNeeded
from gymnasium.vector.utils import create_empty_array
from gymnasium.vector.vector_env import AutoresetMode

from vecsim import trees
from vecsim.client.calls import StageBatch, take_rows
from vecsim.client.errors import ClientError, builtin_exception
from vecsim.client.gym_values import env_observation
from vecsim.info import merge_rows

logger = logging.getLogger(__name__)

__all__ = ["EnvResults", "without_errors"]


def without_errors(batch: StageBatch) -> StageBatch:
    """``batch`` without the rows whose env raised (``batch`` itself when none did)."""
    if not batch.errors:
        return batch
    raised = {key for key, _, _ in batch.errors}
    return take_rows(batch, [j for j, key in enumerate(batch.traj_keys) if key not in raised])


def _row_success(batch: StageBatch) -> np.ndarray:
    """Per row: success after the row's last applied action (a chunk's), or the row's success."""
    return batch.success if batch.chunk is None else batch.last(batch.success) & (batch.num_steps > 0)


class EnvResults:
    """The envs' state between calls and their answers as gymnasium's results.

    ``keys[i]`` is env ``i``'s traj_key, ``task_ids[i]`` its task; ``native``: every env is a gym
    task reset by seed (its info carries the env's own keys only, no ``success``/``task_id``).
    ``obs`` is the last observation of every env (``[num_envs, ...]``); ``ever_reset``,
    ``autoreset`` (ended: reset at the next step, or refused) and ``failed`` (no answer in its
    last call: reset it first) are per-env masks.
    """

    def __init__(
        self,
        space: Space,
        keys: list[str],
        task_ids: list[str],
        native: bool,
        autoreset_mode: AutoresetMode,
    ) -> None:
        self.single_observation_space = space
        self.keys = keys
        self.key_index = {key: i for i, key in enumerate(keys)}
        self.num_envs = len(keys)
        self.task_ids = task_ids
        self.native = native
        self.autoreset_mode = autoreset_mode
        self.obs = create_empty_array(space, n=self.num_envs, fn=np.zeros)
        self.ever_reset = np.zeros(self.num_envs, dtype=bool)
        self.autoreset = np.zeros(self.num_envs, dtype=bool)
        self.failed = np.zeros(self.num_envs, dtype=bool)

    def steppable(self, envs: np.ndarray, refuse_ended: bool) -> np.ndarray:
        """Check that the envs ``envs`` marks may be stepped; return the mask of those that ended
        (and were not reset since).

        Raises:
            ResetNeeded: an env never reset, without an answer in its last call, or (with
                ``refuse_ended``) ended.
        """
        if not self.ever_reset[envs].all():
            raise ResetNeeded(
                f"envs {np.flatnonzero(envs & ~self.ever_reset).tolist()} were never reset; call reset() first"
            )
        if (self.failed & envs).any():
            failed = np.flatnonzero(self.failed & envs).tolist()
            raise ResetNeeded(
                f"envs {failed} got no answer in their last call (the env raised, its pod failed, or the "
                "call was interrupted); reset them with "
                "reset(options={'reset_mask': mask}) before stepping"
            )
        ended = self.autoreset & envs
        if refuse_ended and ended.any():
            raise ResetNeeded(
                f"envs {np.flatnonzero(ended).tolist()} ended and autoreset is disabled; "
                "reset them with reset(options={'reset_mask': mask}) before stepping, or make the env "
                "with ended_envs='step' or 'freeze'"
            )
        return ended

    def take_reset(self, batch: StageBatch | None, fixed: bool) -> tuple[tuple[Any, dict[str, Any]], np.ndarray]:
        """Take the reset rows of ``batch`` (all or some of the call's; ``fixed``: to fixed
        initial states, whose ids the info names); return ``(obs, info)`` and the mask of the
        envs it reset."""
        done = np.zeros(self.num_envs, dtype=bool)
        info: dict[str, Any] = {}
        if batch is not None:
            rows = np.array([self.key_index[k] for k in batch.traj_keys], dtype=np.int64)
            trees.put_rows(self.obs, batch.obs, rows)
            self.ever_reset[rows] = True
            self.autoreset[rows] = False
            self.failed[rows] = False
            self._add_env_info(info, batch, rows)
            self._add_batch_info(info, batch, rows, with_state_ids=fixed)
            done[rows] = True
        return (copy.deepcopy(self.obs), info), done

    def fail(
        self,
        error: ClientError,
        failed: np.ndarray,
        result: tuple[Any, ...] | None,
        raised: Sequence[tuple[str, str, str]] = (),
    ) -> None:
        """Mark the envs of a call that got no answer and tell the caller through ``error``;
        ``raised``: the envs of answering pods that raised (among ``failed``, named in a note)."""
        self.failed |= failed
        self.autoreset[failed] = False
        envs = np.flatnonzero(failed).tolist()
        error.failed_envs = envs
        error.result = result
        if raised:
            error.add_note("envs that raised: " + self._describe(raised))
        logger.warning("envs %s got no answer and must be reset: %s", envs, error)

    def _describe(self, errors: Sequence[tuple[str, str, str]]) -> str:
        """``errors`` (``(traj_key, type name, message)``) as "env i Type: message; ..."."""
        return "; ".join(f"env {self.key_index[key]} {kind}: {text}" for key, kind, text in errors)

    @contextlib.contextmanager
    def failing_if_interrupted(self, envs: np.ndarray) -> Iterator[None]:
        """Mark ``envs`` failed (to be reset before a step) if a Ctrl-C lands while an answer is
        being taken in: what this env holds of them is then partly the old call's."""
        try:
            yield
        except BaseException as exc:
            if not isinstance(exc, Exception):
                self.failed |= envs
                self.autoreset[self.failed] = False
            raise

    def take_step(
        self, reset_batch: StageBatch, step_batch: StageBatch
    ) -> tuple[tuple[Any, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]], np.ndarray]:
        """Take a step call's answer (all or some of its envs'); return what ``step_wait`` returns
        and the mask of the envs the answer covers (a step, or a reset in its place)."""
        # [num_envs], or [num_envs, K] for a chunk step (also one that only resets: no rows, K kept).
        chunk = step_batch.chunk
        per_action = (self.num_envs,) if chunk is None else (self.num_envs, chunk)
        reward = np.zeros(per_action, dtype=np.float64)
        terminated = np.zeros(per_action, dtype=bool)
        truncated = np.zeros(per_action, dtype=bool)
        info: dict[str, Any] = {}

        ended = step_batch.ended()
        if self.autoreset_mode == AutoresetMode.SAME_STEP:
            # An env that ended is answered only once its reset is: its step row alone would
            # leave it ended, which SAME_STEP never shows.
            reset_keys = set(reset_batch.traj_keys)
            take = np.array(
                [j for j, k in enumerate(step_batch.traj_keys) if not ended[j] or k in reset_keys], dtype=np.int64
            )
        else:
            take = np.arange(step_batch.n, dtype=np.int64)
        stepped = np.array([self.key_index[step_batch.traj_keys[j]] for j in take], dtype=np.int64)
        reset = np.array([self.key_index[k] for k in reset_batch.traj_keys], dtype=np.int64)
        if len(take):
            reward[stepped] = step_batch.reward[take]
            terminated[stepped] = step_batch.terminated[take]
            truncated[stepped] = step_batch.truncated[take]
        trees.put_rows(self.obs, step_batch.obs, stepped, take)

        if self.autoreset_mode == AutoresetMode.SAME_STEP and len(reset):
            # The stepped obs of an env that ended goes to final_obs; its reset obs replaces it.
            final_obs = np.full(self.num_envs, None, dtype=object)
            rows_of = {k: j for j, k in enumerate(step_batch.traj_keys)}
            for i in reset:
                final_obs[i] = env_observation(
                    self.single_observation_space, trees.row(step_batch.obs, rows_of[self.keys[i]])
                )
            final_info: dict[str, Any] = {}
            ended_rows = np.array([rows_of[self.keys[i]] for i in reset], dtype=np.int64)
            ended_mask = np.zeros(step_batch.n, dtype=bool)
            ended_mask[ended_rows] = True
            self._add_env_info(final_info, step_batch, None, ended_mask)
            self._add_rows_info(final_info, step_batch, ended_rows, reset)
            done = np.zeros(self.num_envs, dtype=bool)
            done[reset] = True
            info["final_obs"], info["_final_obs"] = final_obs, done
            info["final_info"], info["_final_info"] = final_info, done.copy()

        trees.put_rows(self.obs, reset_batch.obs, reset)
        keep = np.zeros(step_batch.n, dtype=bool)
        keep[take] = True
        if self.autoreset_mode == AutoresetMode.SAME_STEP:
            keep &= ~ended  # an env reset in the same step shows its reset's info; its step's is final_info
        self._add_env_info(info, step_batch, None, keep)
        self._add_env_info(info, reset_batch, None)
        self._add_rows_info(info, step_batch, take, stepped)
        self._add_batch_info(info, reset_batch, reset, with_state_ids=not self.native)
        answered = np.zeros(self.num_envs, dtype=bool)
        answered[stepped] = True
        answered[reset] = True
        if chunk is not None:
            num_steps = np.zeros(self.num_envs, dtype=np.int32)
            num_steps[stepped] = step_batch.num_steps[take]
            info["num_steps"], info["_num_steps"] = num_steps, answered.copy()
        if self.autoreset_mode == AutoresetMode.SAME_STEP:
            self.autoreset[answered] = False
        else:
            ended = terminated | truncated
            self.autoreset[answered] = (ended if chunk is None else ended.any(axis=1))[answered]
        self.failed[answered] = False
        return (copy.deepcopy(self.obs), reward, terminated, truncated, info), answered

    def _add_env_info(
        self, info: dict[str, Any], batch: StageBatch, envs: np.ndarray | None, keep: np.ndarray | None = None
    ) -> None:
        """Merge the envs' own info of ``batch`` (the rows ``keep`` marks, or all) into ``info``."""
        if not batch.env_info:
            return
        env_of_row = np.array([self.key_index[k] for k in batch.traj_keys], dtype=np.int64)
        for rows, batched in batch.env_info:
            merge_rows(info, batched, env_of_row[rows], self.num_envs, None if keep is None else keep[rows])

    def raise_env_errors(self, errors: list[tuple[str, str, str]], result: tuple[Any, ...]) -> None:
        """Raise the error of the lowest env of ``errors`` (``(traj_key, type name, message)`` of
        the envs of a call that raised), carrying ``failed_envs`` and ``result`` (the call's answer
        without their rows, taken already); mark those envs to be reset. Nothing when none raised.
        The envs' order, not the order their pods answered in, decides which error is raised."""
        if not errors:
            return
        errors = sorted(errors, key=lambda error: self.key_index[error[0]])
        failed = sorted({self.key_index[key] for key, _, _ in errors})
        self.failed[failed] = True
        self.autoreset[failed] = False
        key, type_name, message = errors[0]
        logger.warning(
            "envs %s raised (first: env %d %s: %s); they must be reset", failed, self.key_index[key], type_name, message
        )
        error = builtin_exception(type_name, message)
        error.failed_envs = failed
        error.result = result
        if len(failed) > 1:
            error.add_note(f"envs {failed} raised; the others: {self._describe(errors[1:])}")
        raise error

    def _add_batch_info(
        self, info: dict[str, Any], batch: StageBatch, envs: np.ndarray, with_state_ids: bool = False
    ) -> None:
        self._add_rows_info(info, batch, np.arange(batch.n), envs)
        if with_state_ids and len(envs):
            # Like the task envs' own reset info, which names the state id they reset to.
            if "state_id" not in info:
                info["state_id"] = np.zeros(self.num_envs, dtype=np.int64)
                info["_state_id"] = np.zeros(self.num_envs, dtype=bool)
            info["state_id"][envs] = batch.state_ids
            info["_state_id"][envs] = True

    def _add_rows_info(self, info: dict[str, Any], batch: StageBatch, rows: np.ndarray, envs: np.ndarray) -> None:
        """Put a robot task's ``success`` and ``task_id`` of rows ``rows`` at envs ``envs``, masked."""
        if len(envs) == 0 or self.native:
            return
        if "success" not in info:
            info["success"], info["_success"] = np.zeros(self.num_envs, dtype=bool), np.zeros(self.num_envs, dtype=bool)
            info["task_id"] = np.full(self.num_envs, None, dtype=object)
            info["_task_id"] = np.zeros(self.num_envs, dtype=bool)
        info["success"][envs] = _row_success(batch)[rows]
        info["_success"][envs] = True
        for i in envs:
            info["task_id"][i] = self.task_ids[i]
        info["_task_id"][envs] = True
