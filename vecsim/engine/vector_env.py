"""The pod's task-grouped vector env: the envs of one assignment, stepped and reset by env index.

:class:`TaskGroupedVectorEnv` runs the envs of one :class:`~vecsim.config.Assignment` as contiguous
blocks, one per task, in a pool of worker processes of its own (:mod:`vecsim.engine.pool`, built,
spoken to and watched by :mod:`vecsim.engine.supervisor`). A
worker hosts ``envs_per_worker`` consecutive env indices, whatever their tasks: a run of envs may
cross from one task block into the next, each env built for its own task (the last worker may
host fewer; ``envs_per_worker`` 0 lets the pod pick,
:func:`~vecsim.engine.pool.resolve_envs_per_worker`). Env index ``w * envs_per_worker + i`` is
local index ``i`` of worker ``w`` (:mod:`vecsim.engine.worker`).

A call checks every argument first (:mod:`vecsim.engine.checks`; a rejected call changes nothing),
sends an order only to the workers that host an env it names (:mod:`vecsim.engine.protocol`),
then copies the named envs' observations and result rows out of the pool's shared memory and
reads its answer from them (:mod:`vecsim.engine.answers`). A step
applies each env's chunk (``[envs, K, ...]``, K from 1 to ``max_chunk``) in order and stops an env
at its first termination or truncation. An exception an env raises is named in the answer
(:class:`~vecsim.engine.errors.EnvError`) and every other env of the call goes on.

Example::

    with TaskGroupedVectorEnv(assignment) as envs:
        obs, info = envs.reset_envs([0, 1], state_ids=[0, 3])
        result = envs.chunk_step_envs([0, 1], actions)  # actions [2, K, action_dim]
"""

from __future__ import annotations

import itertools
from typing import Any

import gymnasium
import numpy as np
from gymnasium.vector.utils import create_empty_array

from vecsim.config import Assignment
from vecsim.engine import answers, checks
from vecsim.engine.base import DEFAULT_MAX_CHUNK, CallTiming, ChunkResult
from vecsim.engine.checks import assignment_spaces
from vecsim.engine.errors import EnvError, InvalidRequestError
from vecsim.engine.pool import resolve_envs_per_worker
from vecsim.engine.protocol import Order, Reply
from vecsim.engine.supervisor import WorkerSupervisor
from vecsim.engine.tasks import get_task
from vecsim.engine.worker import WorkerSpec
from vecsim.spaces import wire_action_space


class TaskGroupedVectorEnv:
    """The envs of one assignment, in worker processes, addressed by env index.

    Env indices run ``0..num_envs-1`` in contiguous blocks, one per task block of the assignment;
    worker ``w`` hosts envs ``w * envs_per_worker`` onwards, across blocks. After construction every env is in state 0. Thread-safe: calls are serialised.
    ``last_timing`` (:class:`CallTiming`) tells where the workers spent the last call's time.

    Args:
        assignment: what to run (tasks and their env counts, camera, render preset,
            ``envs_per_worker`` (0: :func:`resolve_envs_per_worker` picks),
            ``max_episode_steps``).
        context: multiprocessing start method for the workers.
        timeout_s: longest wait for the workers on one reset or step; None waits forever.
        build_timeout_s: longest wait for the workers to build; None waits forever.
        max_chunk: the most actions per env one step call takes (:meth:`chunk_step_envs`).

    Raises:
        UnknownTaskError: a task id no provider knows.
        TaskSetupError: a LIBERO task, and LIBERO is not installed or lacks its assets.
        InvalidRequestError: the tasks do not share their spaces.
        SimBuildError: a worker failed to build its envs (the message names the task).
    """

    def __init__(
        self,
        assignment: Assignment,
        *,
        context: str = "forkserver",
        timeout_s: float | None = None,
        build_timeout_s: float | None = None,
        max_chunk: int = DEFAULT_MAX_CHUNK,
    ) -> None:
        if max_chunk < 1:
            raise ValueError(f"max_chunk: must be at least 1, got {max_chunk}")
        self.assignment = assignment
        self.max_chunk = max_chunk
        self.single_observation_space, self.served_action_space = assignment_spaces(assignment)
        # What /v1/info serves is the envs' own action space; a Dict or Tuple one travels flattened.
        self.single_action_space = wire_action_space(self.served_action_space)
        self.num_envs = assignment.num_envs
        self.task_ids: list[str] = []
        self._num_states = np.zeros(self.num_envs, dtype=np.int64)
        self.last_timing = CallTiming()

        per_worker = self.envs_per_worker = resolve_envs_per_worker(assignment)
        for block in assignment.tasks:
            task = get_task(block.task_id)
            self.task_ids += [task.task_id] * block.num_envs
            self._num_states[block.env_start : block.env_start + block.num_envs] = task.num_states
        # Worker w hosts envs w*per_worker ... (w+1)*per_worker - 1, across task boundaries.
        self._workers = [
            WorkerSpec(
                task_ids=tuple(self.task_ids[first : first + per_worker]),
                env_indices=tuple(range(first, min(first + per_worker, self.num_envs))),
                envs_per_worker=per_worker,
                camera=assignment.camera,
                render=assignment.render,
                max_episode_steps=assignment.max_episode_steps,
                observation_space=self.single_observation_space,
                action_space=self.single_action_space,
                max_chunk=max_chunk,
                libero=assignment.libero,
                make_kwargs=assignment.make_kwargs,
            )
            for first in range(0, self.num_envs, per_worker)
        ]
        envs = np.arange(self.num_envs, dtype=np.int64)
        self._location = np.stack(divmod(envs, per_worker), axis=1).reshape(-1, 2)
        self._supervisor = WorkerSupervisor(
            self._workers, context, timeout_s=timeout_s, build_timeout_s=build_timeout_s
        )

    @property
    def num_workers(self) -> int:
        """Number of worker processes (0 for a spare pod)."""
        return len(self._workers)

    @property
    def worker_pids(self) -> list[int]:
        """Process ids of the workers, in worker order."""
        return self._supervisor.pids

    def reset_envs(
        self, env_indices: Any, state_ids: Any = None, *, seeds: Any = None, options: dict[str, Any] | None = None
    ) -> tuple[Any, dict[str, Any]]:
        """Reset the named envs; no other env changes.

        With ``state_ids``, each to the named fixed initial state; with ``seeds`` (one int or
        None per env) instead, as the env's own ``reset(seed=seeds[i], options=options)``.

        Returns:
            ``(obs, info)``: ``obs`` batched over the named envs in the given order, ``info``
            ``{"success": bool[n], "task_id": list[str], "env_info": list[dict], "errors":
            list[EnvError]}``. Empty ``env_indices``: empty results.

        Raises:
            UnknownEnvError: an env index out of range.
            InvalidRequestError: duplicate env ids, non-integer ids, lengths that differ, a
                state id out of its task's range, a seed that is not a non-negative int or None,
                or both or neither of ``state_ids`` and ``seeds``.
            SimCrashedError: a worker died, hung or failed (the pod must rebuild).
        """
        ids = checks.env_indices(env_indices, self.num_envs)
        if (state_ids is None) == (seeds is None):
            raise InvalidRequestError("give either state_ids (fixed initial states) or seeds (the envs' own reset)")
        if seeds is None:
            states = checks.state_ids(state_ids, ids, self._num_states, self.task_ids)
            if options:
                raise InvalidRequestError("options: go with seeds (the envs' own reset), not with state_ids")
        else:
            seed_values = checks.seeds(seeds, ids)
        if ids.size == 0:
            return self._empty_obs(), {"success": np.zeros(0, dtype=bool), "task_id": [], "env_info": [], "errors": []}
        workers, local_indices = self._location[ids].T
        orders = {}
        for worker, rows in self._by_worker(workers, local_indices):
            if seeds is None:
                orders[worker] = Order(local_indices[rows], state_ids=states[rows])
            else:
                orders[worker] = Order(local_indices[rows], seeds=seed_values[rows], options=options)
        return answers.reset_answer(self._run(orders, workers, local_indices, ids)[0], [self.task_ids[i] for i in ids])

    def step_envs(
        self, env_indices: Any, actions: Any
    ) -> tuple[dict[str, Any], np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Step the named envs one control step each; no other env advances.

        Returns:
            ``(obs, reward float64[n], terminated bool[n], truncated bool[n], {"success": bool[n],
            "env_info", "errors"})`` over the named envs in the given order (``env_info`` and
            ``errors`` as in :class:`ChunkResult`). Empty ``env_indices``: empty results.

        Raises:
            UnknownEnvError: an env index out of range.
            InvalidRequestError: duplicate env ids, non-integer ids, actions of the wrong shape or
                dtype, or a NaN or infinite action.
            SimCrashedError: a worker died, hung or failed (the pod must rebuild).
        """
        ids = checks.env_indices(env_indices, self.num_envs)
        chunk = checks.actions(actions, ids, self.single_action_space)
        _, result = self._step_chunks(ids, chunk, np.zeros(0, dtype=np.int64))
        return (
            result.obs,
            result.reward[:, 0],
            result.terminated[:, 0],
            result.truncated[:, 0],
            {"success": result.success[:, 0], "env_info": result.env_info, "errors": result.errors},
        )

    def chunk_step_envs(
        self, env_indices: Any, actions: Any, record_env_indices: Any = (), step_past_end: bool = False
    ) -> ChunkResult:
        """Apply a chunk of K actions to each named env, in order; no other env advances.

        Env ``env_indices[i]`` takes ``actions[i, 0]``, ``actions[i, 1]``, ... and stops at its first
        termination or truncation (its later actions are not applied), or with ``step_past_end``
        applies all K (an ended env is stepped on: physics go on, its flags and reward are what
        the scene computes, its episode limit keeps counting; ``num_steps`` is K). Cameras are rendered once
        per env, after its last applied action; the envs in ``record_env_indices`` (a subset of
        ``env_indices``) are also rendered after each of their other applied actions. K = 0 moves
        nothing and answers the envs' current observations.

        Returns:
            :class:`ChunkResult` over the named envs in the given order. Empty ``env_indices``: empty
            results.

        Raises:
            UnknownEnvError: an env index out of range.
            InvalidRequestError: duplicate env ids, non-integer ids, a chunk of the wrong shape or
                dtype or longer than ``max_chunk``, a NaN or infinite action (the message names
                the env and the chunk index), or ``record_env_indices`` not among ``env_indices``.
            SimCrashedError: a worker died, hung or failed (the pod must rebuild).
        """
        ids = checks.env_indices(env_indices, self.num_envs)
        chunk = checks.chunk(actions, ids, self.single_action_space, self.max_chunk)
        return self._step_chunks(ids, chunk, checks.record(record_env_indices, ids), bool(step_past_end))[1]

    def reset_and_step_envs(
        self,
        reset_env_indices: Any,
        state_ids: Any,
        env_indices: Any,
        actions: Any,
        *,
        chunked: bool = True,
        record_env_indices: Any = (),
        step_past_end: bool = False,
    ) -> tuple[tuple[Any, dict[str, Any]], ChunkResult]:
        """Reset some envs to fixed initial states and step other envs, in one call of the
        workers: what a rollout's refill asks of a pod, so that an env's reset runs beside the
        steps of the pod's other envs instead of before them.

        ``reset_env_indices``/``state_ids`` as :meth:`reset_envs`'s; ``env_indices``/``actions``
        (a chunk per env with ``chunked``, else one action per env), ``record_env_indices`` and
        ``step_past_end`` as :meth:`chunk_step_envs`'s (one action per env answers chunks of one).
        The two sets of envs are disjoint. Everything is checked before any env moves.

        Returns:
            ``((obs, info), result)``: what :meth:`reset_envs` returns over the reset envs, and
            the :class:`ChunkResult` over the stepped ones.

        Raises:
            UnknownEnvError, InvalidRequestError, SimCrashedError: as those two methods'; and
                InvalidRequestError for an env both reset and stepped (names it).
        """
        reset_ids = checks.env_indices(reset_env_indices, self.num_envs, "reset_env_indices")
        states = checks.state_ids(state_ids, reset_ids, self._num_states, self.task_ids, "reset_state_ids")
        ids = checks.env_indices(env_indices, self.num_envs)
        both = np.intersect1d(reset_ids, ids)
        if both.size:
            raise InvalidRequestError(f"reset_env_indices: env {int(both[0])} is also stepped (env_indices)")
        chunk = (
            checks.chunk(actions, ids, self.single_action_space, self.max_chunk)
            if chunked
            else checks.actions(actions, ids, self.single_action_space)
        )
        recorded = checks.record(record_env_indices, ids)
        if reset_ids.size and ids.size and chunk.shape[1]:
            return self._step_chunks(ids, chunk, recorded, bool(step_past_end), (reset_ids, states))
        reset = self.reset_envs(reset_ids, states)
        return reset, self._step_chunks(ids, chunk, recorded, bool(step_past_end))[1]

    def _step_chunks(
        self,
        ids: np.ndarray,
        chunk: np.ndarray,
        recorded: np.ndarray,
        past_end: bool = False,
        reset: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> tuple[tuple[Any, dict[str, Any]] | None, ChunkResult]:
        """Step ``ids`` through ``chunk``; with ``reset`` (env ids, state ids; disjoint from
        ``ids``, none of them empty), reset those envs in the same worker call. Returns the
        reset's ``(obs, info)`` (None without one) and the step's result."""
        n, k = chunk.shape[:2]
        workers, local_indices = self._location[ids].T
        images = self._images_space()
        if n == 0 or k == 0:
            obs = self._empty_obs() if n == 0 else self._supervisor.observations(workers, local_indices)
            nothing = answers.EnvRows(obs, np.zeros((n, k, 4)), [{} for _ in range(n)], [])
            return None, answers.chunk_result(nothing, recorded, past_end, images)
        record = np.zeros(n, dtype=bool)
        record[recorded] = True
        orders: dict[int, Order | tuple[Order, ...]] = {}
        all_ids = ids
        if reset is not None:
            reset_workers, reset_locals = self._location[reset[0]].T
            for worker, rows in self._by_worker(reset_workers, reset_locals):
                orders[worker] = Order(reset_locals[rows], state_ids=reset[1][rows])
            workers = np.concatenate([workers, reset_workers])
            local_indices = np.concatenate([local_indices, reset_locals])
            all_ids = np.concatenate([ids, reset[0]])
        for worker, rows in self._by_worker(workers[:n], local_indices[:n]):
            step = Order(
                local_indices[rows],
                actions=chunk[rows],
                record=record[rows] if recorded.size else None,
                past_end=past_end,
            )
            # A worker with envs of both runs its resets, then its steps, in one order.
            orders[worker] = (orders[worker], step) if worker in orders else step
        stepped, replies = self._run(orders, workers, local_indices, all_ids)
        reset_answer = None
        if reset is not None:
            stepped, reset_rows = stepped.split(n)
            reset_answer = answers.reset_answer(reset_rows, [self.task_ids[i] for i in reset[0]])
        result = answers.chunk_result(stepped._replace(rows=stepped.rows[:, :k]), recorded, past_end, images)
        answers.fill_frames(result, replies, recorded, workers, local_indices)
        return reset_answer, result

    def frame(self, env_index: int, camera: str) -> np.ndarray:
        """Return a copy of the uint8 HxWx3 image ``camera`` of env ``env_index`` saw last.

        Raises:
            UnknownEnvError: no env ``env_index``.
            InvalidRequestError: the envs have no camera ``camera``.
            SimCrashedError: the workers crashed or were closed.
        """
        ids = checks.env_indices(np.array([env_index]), self.num_envs)
        images = self._images_space()
        cameras = [] if images is None else list(images.spaces)
        if camera not in cameras:
            raise InvalidRequestError(f"camera: no camera {camera!r}; cameras: {cameras}")
        workers, local_indices = self._location[ids].T
        return self._supervisor.observations(workers, local_indices)["images"][camera][0]

    def close(self) -> None:
        """Stop the worker processes. Idempotent. Returns None."""
        self._supervisor.close()

    def __enter__(self) -> TaskGroupedVectorEnv:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def env_attr(self, env_indices: Any, op: str, name: Any, payload: Any = None) -> tuple[list[Any], list[EnvError]]:
        """Get (``op`` ``get``), call (``call``, ``payload`` ``(args, kwargs)``) or set (``set``,
        ``payload`` one value per env) attribute ``name`` of each named env.

        Returns:
            ``(results, errors)``: one JSON result per env (None for ``set``), and the envs whose
            attribute raised (:class:`EnvError`; their result is None).

        Raises:
            UnknownEnvError: an env index out of range.
            InvalidRequestError: duplicate env ids, a name that is not a public attribute name
                (or one vecsim keeps: ``close``, ``reset``, ``step``, ...), a bad payload.
            SimCrashedError: a worker died, hung or failed.
        """
        ids = checks.env_indices(env_indices, self.num_envs)
        checks.attr_request(op, name, payload, ids)
        if ids.size == 0:
            return [], []
        requests: dict[int, dict[int, tuple[str, str, Any]]] = {}
        for row, env in enumerate(ids.tolist()):
            worker = int(self._location[env, 0])
            requests.setdefault(worker, {})[env] = (op, name, payload[row] if op == "set" else payload)
        replies = self._supervisor.ask("env_attr", requests)
        by_env = {env: (ok, value) for entries in replies.values() for env, ok, value in entries}
        results: list[Any] = []
        errors: list[EnvError] = []
        for row, env in enumerate(ids):
            ok, value = by_env[int(env)]
            results.append(value if ok else None)
            if not ok:
                errors.append(EnvError(row, *value))
        return results, errors

    # Internals.

    def _images_space(self) -> gymnasium.spaces.Dict | None:
        space = self.single_observation_space
        return space.spaces.get("images") if isinstance(space, gymnasium.spaces.Dict) else None

    def _empty_obs(self) -> dict[str, Any]:
        return create_empty_array(self.single_observation_space, n=0, fn=np.zeros)

    @staticmethod
    def _by_worker(workers: np.ndarray, local_indices: np.ndarray) -> list[tuple[int, np.ndarray]]:
        """The rows of a call grouped by worker: ``[(worker, rows), ...]``, each worker's rows in
        local-index order (the order a worker runs its envs in)."""
        rows = np.lexsort((local_indices, workers))
        ordered = workers[rows]
        bounds = [0, *(np.flatnonzero(ordered[1:] != ordered[:-1]) + 1).tolist(), rows.size]
        return [(int(ordered[first]), rows[first:last]) for first, last in itertools.pairwise(bounds) if last > first]

    def _run(
        self,
        orders: dict[int, Order | tuple[Order, ...]],
        workers: np.ndarray,
        local_indices: np.ndarray,
        ids: np.ndarray,
    ) -> tuple[answers.EnvRows, dict[int, Reply]]:
        """Send each worker of ``orders`` its order (no other worker hears of the call); return what
        they left for envs ``ids`` (at ``workers``, ``local_indices``) row by row, and their replies."""
        obs, rows, replies = self._supervisor.run(orders, workers, local_indices)
        self.last_timing = CallTiming(
            float(sum(reply.physics_s for reply in replies.values())),
            float(sum(reply.render_s for reply in replies.values())),
            sum(reply.renders for reply in replies.values()),
        )
        env_info, errors = answers.per_row(replies, ids, self.envs_per_worker, self.task_ids)
        return answers.EnvRows(obs, rows, env_info, errors), replies
