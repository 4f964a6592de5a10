"""A call's answer, row by row, from what the workers left: the named envs' observations and result
rows (``[n, K, 4]``: reward, terminated, truncated, success, read from the pool's shared memory)
and the workers' replies (each env's own info, the exceptions envs raised, recorded frames).

Pure functions over arrays; :class:`~vecsim.engine.vector_env.TaskGroupedVectorEnv` calls them
once the workers have answered. Row ``i`` is the ``i``-th env the call named.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Any, NamedTuple

import gymnasium
import numpy as np

from vecsim import trees
from vecsim.engine.base import ChunkResult
from vecsim.engine.errors import EnvError
from vecsim.engine.protocol import Reply
from vecsim.engine.worker import REWARD, SUCCESS, TERMINATED, TRUNCATED

log = logging.getLogger("vecsim.engine.answers")


class EnvRows(NamedTuple):
    """What a call's workers left for its envs, row by row: observations (batched), result rows
    ``[n, K, 4]``, each env's own info and the envs that raised (:class:`EnvError`, by row)."""

    obs: Any
    rows: np.ndarray
    env_info: list[dict[str, Any]]
    errors: list[EnvError]

    def split(self, n: int) -> tuple[EnvRows, EnvRows]:
        """The first ``n`` rows and the rest, each numbered from 0."""
        head = EnvRows(
            trees.map_leaves(lambda leaf: leaf[:n], self.obs),
            self.rows[:n],
            self.env_info[:n],
            [e for e in self.errors if e.row < n],
        )
        tail = EnvRows(
            trees.map_leaves(lambda leaf: leaf[n:], self.obs),
            self.rows[n:],
            self.env_info[n:],
            [dataclasses.replace(e, row=e.row - n) for e in self.errors if e.row >= n],
        )
        return head, tail


def per_row(
    replies: dict[int, Reply], ids: np.ndarray, envs_per_worker: int, task_ids: list[str]
) -> tuple[list[dict[str, Any]], list[EnvError]]:
    """Each row's own env info and the rows whose env raised (logged), from the workers' replies
    to a call naming envs ``ids``; ``task_ids``: every env's task, by env index."""
    env_info: list[dict[str, Any]] = [{} for _ in range(ids.size)]
    errors: list[EnvError] = []
    if not any(reply.env_info or reply.errors for reply in replies.values()):
        return env_info, errors
    # Worker w's local index i is env w * envs_per_worker + i.
    row_of = {env: row for row, env in enumerate(ids.tolist())}
    for worker, reply in replies.items():
        first = worker * envs_per_worker
        for local, own in reply.env_info:
            env_info[row_of[first + local]] = own
        for local, type_name, message in reply.errors:
            errors.append(EnvError(row_of[first + local], type_name, message))
    errors.sort(key=lambda e: e.row)
    for error in errors:
        env = int(ids[error.row])
        log.info("env %d (%s) raised %s: %s", env, task_ids[env], error.type_name, error.message)
    return env_info, errors


def reset_answer(answer: EnvRows, task_ids: list[str]) -> tuple[Any, dict[str, Any]]:
    """A reset's ``(obs, info)`` over its rows; ``task_ids``: each row's task."""
    return answer.obs, {
        "success": answer.rows[:, 0, SUCCESS] != 0,
        "task_id": task_ids,
        "env_info": answer.env_info,
        "errors": answer.errors,
    }


def chunk_result(
    answer: EnvRows, recorded: np.ndarray, past_end: bool, images: gymnasium.spaces.Dict | None
) -> ChunkResult:
    """A step's answer over result rows ``[n, K, 4]``; the recorded envs' frames (``images``: the
    cameras' space, None without cameras) zeroed, for :func:`fill_frames`."""
    rows = answer.rows
    n, k = rows.shape[:2]
    stopped = (rows[:, :, TERMINATED] != 0) | (rows[:, :, TRUNCATED] != 0)
    if past_end:
        stopped = np.zeros_like(stopped)  # every env applied all K
    # An env stops at its first termination or truncation; one that never did applied all K.
    first_stop = np.argmax(stopped, axis=1) if k else np.zeros(n, dtype=np.int64)
    num_steps = np.where(stopped.any(axis=1), first_stop + 1, k).astype(np.int32)
    cameras = images.spaces if images is not None and recorded.size else {}
    frames = {camera: np.zeros((recorded.size, k, *space.shape), space.dtype) for camera, space in cameras.items()}
    return ChunkResult(
        obs=answer.obs,
        reward=rows[:, :, REWARD].copy(),
        terminated=rows[:, :, TERMINATED] != 0,
        truncated=rows[:, :, TRUNCATED] != 0,
        success=rows[:, :, SUCCESS] != 0,
        num_steps=num_steps,
        frames=frames,
        env_info=answer.env_info,
        errors=answer.errors,
    )


def fill_frames(
    result: ChunkResult,
    replies: dict[int, Reply],
    recorded: np.ndarray,
    workers: np.ndarray,
    local_indices: np.ndarray,
) -> None:
    """Fill ``result.frames`` for the recorded rows: the frames their workers drew before each
    env's last action, then the observation after it. Row ``i`` is env ``local_indices[i]`` of
    worker ``workers[i]``."""
    drawn = {(worker, local): frames for worker, reply in replies.items() for local, frames in reply.frames}
    for index, row in enumerate(recorded):
        before_last = drawn[(int(workers[row]), int(local_indices[row]))]
        last = int(result.num_steps[row]) - 1
        for camera, out in result.frames.items():
            for step, frame in enumerate(before_last):
                out[index, step] = frame[camera][0]
            out[index, last] = result.obs["images"][camera][row]
