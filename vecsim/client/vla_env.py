"""VLAEnv: a vecsim job as the env a VLA-RL trainer drives.

VLA-RL trainers talk to their simulator through a small contract: ``reset`` of chosen envs to
chosen initial states, and ``chunk_step(actions[num_envs, K, action_dim])`` answering per-action
rewards, terminations and truncations. :class:`VLAEnv` gives a vecsim job that shape; it is not
itself a trainer's env class: the adapters in :mod:`vecsim.trainers` are, built on it
(docs/trainers.md)::

    env = VLAEnv("http://controller:8000", keys="lerobot", camera_keys="lerobot")
    obs, info = env.reset(env_ids=[0, 1, 2], state_ids=[4, 4, 7])
    obs, rewards, terminations, truncations, infos = env.chunk_step(actions)   # [num_envs, K, A]
    obs, *_ = env.chunk_step(actions[:2], env_ids=[0, 2])                      # only envs 0 and 2

Each env's task is fixed by the job (``task_ids``, and ``task_indices``: the int index in its
suite; a property, not a list made at construction, so that a job of tasks without an index, a
gym id, still makes a VLAEnv and raises only when asked). State ids are per task;
``reset(global_state_ids=...)`` takes the trainers' suite-global ids (task ``t``'s rows after
those of tasks ``0..t-1``, :class:`~vecsim.client.conventions.StateNumbering`) and refuses an id
of another task than the env's. The policy's state vector is LIBERO's 8-float
``state`` where the job serves it (LIBERO tasks), else the robot's ``proprio``. Every action's
termination and truncation is reported where it happened, also with ``auto_reset`` (RLinf moves
them to the chunk's last column then).

It is a thin layer over :class:`~vecsim.client.vector_env.HTTPVectorEnv`: autoreset disabled, or
gymnasium's same-step autoreset with ``auto_reset=True``.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

import httpx
import numpy as np
from gymnasium.vector import AutoresetMode

from vecsim.client.conventions import StateNumbering, camera_key_map, suite_of, suite_task_index
from vecsim.client.vector_env import HTTPVectorEnv
from vecsim.config import JobConfig, RoutingTable

__all__ = ["VLAEnv"]

Keys = Literal["vecsim", "lerobot"]


class VLAEnv:
    """A vecsim job with the reset/chunk_step contract of VLA-RL trainers (module docstring).

    The job is named as for :class:`HTTPVectorEnv` (exactly one of ``controller_url``,
    ``job_config``, ``routing``, ``pod_urls``). ``keys`` picks the observation's key names:

    - ``"vecsim"``: ``{"images": {camera: uint8[n, H, W, 3]}, "proprio": float[n, d],
      "state": float64[n, 8] (LIBERO tasks only), "instruction": [str] * n}``;
    - ``"lerobot"``: LeRobot's names, ``{"observation.images.<camera>": ...,
      "observation.state": ..., "task": [str] * n}``; ``observation.state`` is LIBERO's 8-float
      ``state`` where the job serves it, else ``proprio``.

    ``camera_keys`` renames the cameras: a preset of
    :data:`~vecsim.client.conventions.CAMERA_KEYS` (``"verl_vla"``, ``"lerobot"``, ``"rlinf"``)
    or a mapping ``{camera: key}``; a mapped camera's image goes under its key (in place of
    ``observation.images.<camera>``, or of ``<camera>`` inside ``images``), cameras the mapping
    leaves out keep their names. ``reward_dtype`` is the rewards' dtype (float64 by default; the
    trainers' adapters ask float32). ``ended_envs`` is :class:`HTTPVectorEnv`'s (``"raise"``,
    ``"step"``, ``"freeze"``): what a chunk sent to an env that ended and was not reset does.

    Every observation is batched over the envs of the call (all ``num_envs``, or the
    ``env_ids`` of a subset step), in that order, with ``task_id`` (the vecsim task of each env)
    beside it. ``auto_reset``: envs that end inside a chunk are reset to a fresh state id (drawn
    from the seed of the last ``reset(seed=...)``) once the chunk is over;
    ``infos["final_obs"]`` then holds their last observation (same key names, one env each).
    Without it, an env that ended must be reset before the next chunk (or stepped on or frozen,
    as ``ended_envs`` says).
    """

    def __init__(
        self,
        controller_url: str | None = None,
        *,
        job_config: JobConfig | str | Path | None = None,
        routing: RoutingTable | None = None,
        pod_urls: Sequence[str] | None = None,
        keys: Keys = "vecsim",
        camera_keys: str | Mapping[str, str] | None = None,
        reward_dtype: Any = np.float64,
        ended_envs: str = "raise",
        auto_reset: bool = False,
        timeout_s: float = 30.0,
        transport: httpx.AsyncBaseTransport | None = None,
        token: str | None = None,
    ) -> None:
        """Connect to the job; nothing is reset yet.

        Raises:
            ValueError: ``keys`` neither ``"vecsim"`` nor ``"lerobot"``, an unknown
                ``camera_keys`` preset or a bad mapping, a ``reward_dtype`` that is not a float
                dtype, an unknown ``ended_envs``; and as :class:`HTTPVectorEnv`.
            PodUnavailableError, PodRequestError, TimeoutError: as :class:`HTTPVectorEnv`.
        """
        if keys not in ("vecsim", "lerobot"):
            raise ValueError(f"keys must be 'vecsim' or 'lerobot', got {keys!r}")
        self.keys = keys
        self.camera_keys = {} if camera_keys is None else camera_key_map(camera_keys)
        try:
            self.reward_dtype = np.dtype(reward_dtype)
        except TypeError:
            self.reward_dtype = None
        if self.reward_dtype is None or self.reward_dtype.kind != "f":
            raise ValueError(f"reward_dtype must be a float dtype, got {reward_dtype!r}")
        self.auto_reset = auto_reset
        self.vector_env = HTTPVectorEnv(
            controller_url,
            job_config=job_config,
            routing=routing,
            pod_urls=pod_urls,
            autoreset_mode=AutoresetMode.SAME_STEP if auto_reset else AutoresetMode.DISABLED,
            timeout_s=timeout_s,
            transport=transport,
            token=token,
            ended_envs=ended_envs,
        )
        self.ended_envs = self.vector_env.ended_envs
        self.num_envs = self.vector_env.num_envs
        self.task_ids = list(self.vector_env.task_ids)
        instructions = self.vector_env.client.instructions
        self.instructions = [instructions.get(task, "") for task in self.task_ids]
        self.num_states = {task: self.vector_env.client.num_states[task] for task in set(self.task_ids)}
        self.action_dim = int(np.prod(self.vector_env.single_action_space.shape))
        # The policy's state vector: LIBERO's 8-float state where the job serves it.
        self.state_key = (
            "state" if "state" in getattr(self.vector_env.single_observation_space, "spaces", {}) else "proprio"
        )
        self._obs: Any = None

    @property
    def task_indices(self) -> list[int]:
        """Each env's task as its int index in its suite (``"libero_spatial/3"`` -> 3).

        Raises:
            ValueError: a task id without an integer index (a gym task; names it).
        """
        return [suite_task_index(task) for task in self.task_ids]

    def state_numbering(self, suite: str) -> StateNumbering:
        """The suite-global state numbering of ``suite``, from the job's per-task state counts.

        Raises:
            ValueError: as :meth:`StateNumbering.from_num_states`.
        """
        return StateNumbering.from_num_states(self.vector_env.client.num_states, suite)

    def reset(
        self,
        env_ids: Sequence[int] | np.ndarray | None = None,
        state_ids: Sequence[int] | np.ndarray | None = None,
        seed: int | None = None,
        *,
        global_state_ids: Sequence[int] | np.ndarray | None = None,
    ) -> tuple[dict[str, Any], dict[str, Any]]:
        """Reset ``env_ids`` (default: all) to ``state_ids`` (one per env id, of that env's task;
        default: drawn, seeded by ``seed``), or to ``global_state_ids`` (one suite-global id per
        env id, which must fall in the env's own task). The other envs do not change; no env ids
        is a no-op.

        Returns:
            ``(obs, info)``: the observation of every env (the named ones just reset), and the
            vector env's reset info (``state_id`` and ``success`` with their ``_`` masks).

        Raises:
            ValueError: an env id out of range or named twice, state ids not one per env id, a
                state id outside its task's range, both ``state_ids`` and ``global_state_ids``,
                or a global id out of range or of another task than its env's (names env and id).
        """
        ids = np.arange(self.num_envs) if env_ids is None else np.asarray(env_ids, dtype=np.int64).reshape(-1)
        if global_state_ids is not None:
            if state_ids is not None:
                raise ValueError("give state_ids (per task) or global_state_ids (suite-global), not both")
            state_ids = self._rows_of_global_ids(ids, global_state_ids)
        if ids.size == 0:
            if self._obs is None:
                raise ValueError("no env ids and no env was ever reset: there is no observation to answer")
            return self._present(copy.deepcopy(self._obs)), {}
        if ((ids < 0) | (ids >= self.num_envs)).any() or len(set(ids.tolist())) != ids.size:
            raise ValueError(f"env_ids must be distinct vector indices 0..{self.num_envs - 1}, got {ids.tolist()}")
        mask = np.zeros(self.num_envs, dtype=bool)
        mask[ids] = True
        options: dict[str, Any] = {"reset_mask": mask}
        if state_ids is not None:
            states = np.asarray(state_ids).reshape(-1)
            if states.shape != ids.shape or states.dtype.kind not in "iu":
                raise ValueError(f"state_ids must be {ids.size} integers, one per env id, got {states.tolist()}")
            full = np.zeros(self.num_envs, dtype=np.int64)
            full[ids] = states
            options["state_ids"] = full
        obs, info = self.vector_env.reset(seed=seed, options=options)
        self._obs = obs
        return self._present(obs), info

    def _rows_of_global_ids(self, ids: np.ndarray, global_state_ids: Any) -> np.ndarray:
        """Each env's state row of its suite-global id, checked against the env's task."""
        gids = np.asarray(global_state_ids).reshape(-1)
        if gids.shape != ids.shape or (gids.size and gids.dtype.kind not in "iu"):
            raise ValueError(f"global_state_ids must be {ids.size} integers, one per env id, got {gids.tolist()}")
        rows = np.zeros(ids.size, dtype=np.int64)
        for j, (env, gid) in enumerate(zip(ids.tolist(), gids.tolist())):
            if not 0 <= env < self.num_envs:
                raise ValueError(f"env_ids must be vector indices 0..{self.num_envs - 1}, got {env}")
            task = self.task_ids[env]
            try:
                task_index, row = self.state_numbering(suite_of(task)).split_global_state_id(gid)
            except ValueError as exc:
                raise ValueError(f"global_state_ids: env {env} ({task}): {exc}") from None
            if task_index != suite_task_index(task):
                raise ValueError(
                    f"global_state_ids: id {gid} of env {env} is a state of task {suite_of(task)}/{task_index}, "
                    f"but env {env} runs {task}"
                )
            rows[j] = row
        return rows

    def chunk_step(
        self, actions: Any, env_ids: Sequence[int] | np.ndarray | None = None
    ) -> tuple[dict[str, Any], np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Apply a chunk of K actions to every env (``[num_envs, K, action_dim]``, numpy or
        torch), or only to ``env_ids`` (``[len(env_ids), K, action_dim]``, row j for
        ``env_ids[j]``): the other envs are not touched and pods without any of them get no
        request; each pod gets one request for the whole chunk.

        Returns:
            ``(obs, rewards [n, K] of reward_dtype, terminations bool[n, K], truncations
            bool[n, K], infos)`` over the stepped envs in order (``n`` = ``num_envs`` or
            ``len(env_ids)``): each env stops at its first termination or truncation (later
            entries 0/false) unless ``ended_envs="step"``, ``obs`` is after each env's last
            applied action (after its reset, with ``auto_reset``), ``infos["num_steps"]`` the
            actions each env applied; info arrays are sliced to the stepped envs too.

        Raises:
            ResetNeeded: (without ``auto_reset``, ``ended_envs="raise"``) an env ended and was
                not reset, or was never reset.
            ValueError: a chunk of the wrong shape or not finite, or bad ``env_ids``.
        """
        if hasattr(actions, "detach"):  # a torch tensor, without importing torch here
            actions = actions.detach().cpu().numpy()
        obs, rewards, terminations, truncations, infos = self.vector_env.chunk_step(actions, env_ids)
        self._obs = obs
        if "final_obs" in infos:
            infos["final_obs"] = np.array(
                [None if row is None else self._rename(row) for row in infos["final_obs"]], dtype=object
            )
        rewards = rewards.astype(self.reward_dtype, copy=False)
        if env_ids is None:
            return self._present(obs), rewards, terminations, truncations, infos
        rows = np.asarray(env_ids, dtype=np.int64).reshape(-1)
        sub_obs = {key: _take(value, rows) for key, value in self._present(obs).items()}
        return sub_obs, rewards[rows], terminations[rows], truncations[rows], _take(infos, rows, self.num_envs)

    def close(self) -> None:
        """Close the connections to the job. Idempotent."""
        self.vector_env.close()

    def __enter__(self) -> VLAEnv:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _rename(self, obs: dict[str, Any]) -> dict[str, Any]:
        """The observation's arrays under this env's key names (batched or one env's)."""
        images = obs.get("images", {})
        if self.keys == "vecsim":
            named = {
                "images": {self.camera_keys.get(c, c): image for c, image in images.items()},
                "proprio": obs["proprio"],
            }
            if "state" in obs:
                named["state"] = obs["state"]
            return named
        named = {self.camera_keys.get(c, f"observation.images.{c}"): image for c, image in images.items()}
        named["observation.state"] = obs[self.state_key]
        return named

    def _present(self, obs: dict[str, Any]) -> dict[str, Any]:
        presented = self._rename(obs)
        presented["task" if self.keys == "lerobot" else "instruction"] = list(self.instructions)
        presented["task_id"] = list(self.task_ids)
        return presented


def _take(value: Any, rows: np.ndarray, n: int | None = None) -> Any:
    """Rows ``rows`` of a batched value: arrays and lists along their first axis, dicts leaf by
    leaf; with ``n``, only values of first dimension ``n`` (the info's per-env arrays)."""
    if isinstance(value, dict):
        return {key: _take(item, rows, n) for key, item in value.items()}
    if isinstance(value, np.ndarray) and value.ndim and (n is None or value.shape[0] == n):
        return value[rows]
    if isinstance(value, list) and (n is None or len(value) == n):
        return [value[int(r)] for r in rows]
    return value
