"""One stage call: its answer (:class:`StageBatch`), its handle (:class:`PendingCall`), and how it
is carried out: the actions checked, each pod sent its rows, the answers written into batch
arrays allocated before the requests go out, and a pod's failure kept to its own trajectories.

No routing decisions here: the routes come from the route book, the HTTP from a ``post`` callable
(``StageClient._post``: one pod, one request, with the routing generation and its 409 handling).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import time
from collections.abc import Awaitable, Callable, Generator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

import numpy as np
from gymnasium import Space
from gymnasium.spaces import Box
from gymnasium.vector.utils import create_empty_array

from vecsim import trees
from vecsim.client.errors import PodRequestError, PodUnavailableError, call_error
from vecsim.client.jobinfo import JobInfo
from vecsim.client.pods import EventLoopThread
from vecsim.client.routebook import RouteBook
from vecsim.client.routing import TrajRoute
from vecsim.spaces import in_kind_of

__all__ = ["Ended", "PendingCall", "StageBatch", "check_actions", "completed", "empty_batch", "run_call", "take_rows"]

T = TypeVar("T")

# ``post(pod, op, body, traj_keys, extra_answer_bytes)``: one request to one pod, its decoded answer.
Post = Callable[[str, str, dict[str, Any], list[str], int], Awaitable[dict[str, Any]]]


@dataclass
class StageBatch:
    """The answer to one reset or step call: row ``j`` belongs to ``traj_keys[j]``.

    ``state_ids`` are the trajectories' state ids (the ones just reset to, after a reset). After
    a reset ``reward`` is 0 and ``terminated``/``truncated`` are False. ``submitted_at`` and
    ``finished_at`` are ``time.perf_counter()`` stamps of the call.

    A step of chunks (K actions per trajectory) answers ``reward``, ``terminated``, ``truncated``
    and ``success`` of shape ``[n, K]`` (0/false after a trajectory's env stopped), ``obs`` after
    each one's last applied action, ``num_steps`` ``[n]`` the actions each applied, and ``frames``
    ``{traj_key: {camera: uint8[K, H, W, 3]}}`` for the trajectories asked to be recorded. A
    one-action step answers ``[n]`` arrays and ``num_steps`` of ones; a reset, zeros.

    ``env_info`` holds the envs' own info as the pods answered it: ``(rows, batched)`` per pod,
    ``batched`` over those rows as :func:`vecsim.info.batch_infos` makes it. ``errors`` names the
    rows whose env raised: ``(traj_key, exception type name, message)``; those envs did nothing.
    """

    traj_keys: list[str]
    task_ids: list[str]
    state_ids: np.ndarray
    obs: dict[str, Any]
    reward: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    success: np.ndarray
    submitted_at: float = 0.0
    finished_at: float = 0.0
    num_steps: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int32))
    frames: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    env_info: list[tuple[np.ndarray, dict[str, Any]]] = field(default_factory=list)
    errors: list[tuple[str, str, str]] = field(default_factory=list)

    @property
    def n(self) -> int:
        return len(self.traj_keys)


class PendingCall(Generic[T]):
    """A call in flight on the client's loop: ``await`` it, or block on :meth:`result`.

    ``pick``, when given, selects one item of the call's answer (a tuple) as the result. ``loop``
    is the client's loop the call runs on (None for a call answered already).
    """

    def __init__(
        self, future: concurrent.futures.Future[Any], pick: int | None = None, loop: EventLoopThread | None = None
    ) -> None:
        self._future = future
        self._pick = pick
        self._loop = loop

    def done(self) -> bool:
        """Return True once the call has finished (answered, failed or cancelled)."""
        return self._future.done()

    def result(self, timeout: float | None = None) -> T:
        """Wait for the call and return its answer.

        Interrupted while waiting (Ctrl-C: ``KeyboardInterrupt``), the call is cancelled first:
        its stages take a new call at once. What the pods already did stays done.

        Raises:
            TimeoutError: not finished within ``timeout`` seconds (the call stays in flight).
            concurrent.futures.CancelledError: the call was cancelled.
            Whatever the call raised (``PodUnavailableError``, ``PodRequestError``, ...).
        """
        try:
            answer = self._future.result(timeout)
        except BaseException as exc:
            if not isinstance(exc, TimeoutError) and not self._future.done():
                self.cancel()
            raise
        return answer if self._pick is None else answer[self._pick]

    def cancel(self) -> None:
        """Stop the call and wait until it has ended on the client's loop (what the pods already
        did stays done); its stages take a new call at once. A finished call stays as it is."""
        if self._loop is not None:
            self._loop.cancel(self._future)
        else:
            self._future.cancel()

    @staticmethod
    def wait_any(calls: Sequence[PendingCall[Any]], timeout: float | None = None) -> bool:
        """Block until at least one of ``calls`` has finished; return False on ``timeout``."""
        done, _ = concurrent.futures.wait([c._future for c in calls], timeout, concurrent.futures.FIRST_COMPLETED)
        return bool(done)

    def __await__(self) -> Generator[Any, None, T]:
        answer = yield from self._wait().__await__()
        return answer if self._pick is None else answer[self._pick]

    async def _wait(self) -> Any:
        try:
            return await asyncio.wrap_future(self._future)
        except asyncio.CancelledError:
            # Awaited on the client's own loop (a chained call): the call is cancelled with its
            # awaiter, and the awaiter ends only after it.
            if self._loop is not None and asyncio.get_running_loop() is self._loop.loop:
                await self._loop.ended(self._future)
            raise


def completed(value: Any, pick: int | None) -> PendingCall[Any]:
    """A call answered already with ``value``."""
    future: concurrent.futures.Future[Any] = concurrent.futures.Future()
    future.set_result(value)
    return PendingCall(future, pick)


def take_rows(batch: StageBatch, rows: list[int]) -> StageBatch:
    """Return the batch of rows ``rows`` of ``batch`` (in that order), timing stamps included."""
    index = np.asarray(rows, dtype=np.int64)

    new_row = {int(r): j for j, r in enumerate(rows)}
    env_info = [
        (np.array([new_row[int(r)] for r in pod_rows], dtype=np.int64), batched)
        for pod_rows, batched in batch.env_info
        if all(int(r) in new_row for r in pod_rows)
    ]
    kept = {batch.traj_keys[r] for r in rows}

    return StageBatch(
        traj_keys=[batch.traj_keys[r] for r in rows],
        task_ids=[batch.task_ids[r] for r in rows],
        state_ids=batch.state_ids[index],
        obs=trees.take_rows(batch.obs, index),
        reward=batch.reward[index],
        terminated=batch.terminated[index],
        truncated=batch.truncated[index],
        success=batch.success[index],
        submitted_at=batch.submitted_at,
        finished_at=batch.finished_at,
        num_steps=batch.num_steps[index],
        frames={key: batch.frames[key] for key in (batch.traj_keys[r] for r in rows) if key in batch.frames},
        env_info=env_info,
        errors=[error for error in batch.errors if error[0] in kept],
    )


@dataclass(frozen=True)
class Ended:
    """What a trajectory's env was when its episode ended: its observation (one env's), its
    last termination, truncation and success flags. A frozen env answers these, unstepped."""

    obs: Any
    terminated: bool
    truncated: bool
    success: bool


def ended_rows(batch: StageBatch) -> dict[str, Ended]:
    """The rows of a step answer whose env terminated or truncated (at any action), as :class:`Ended`."""
    flags = batch.terminated | batch.truncated
    ended = flags if flags.ndim == 1 else flags.any(axis=1)
    out: dict[str, Ended] = {}
    for j in np.flatnonzero(ended):
        if batch.terminated.ndim == 1:
            last = (batch.terminated[j], batch.truncated[j], batch.success[j])
        else:
            # The flags where the env ended: its last applied action (num_steps of K), or the
            # last action for an env stepped past its end.
            k = max(int(batch.num_steps[j]) - 1, 0)
            last = (batch.terminated[j, k], batch.truncated[j, k], batch.success[j, k])
        out[batch.traj_keys[j]] = Ended(trees.row(batch.obs, int(j)), *(bool(v) for v in last))
    return out


@dataclass
class _PodWork:
    """What one call asks of one pod: resets first, then steps (rows index the call's batches)."""

    reset_rows: list[int] = field(default_factory=list)
    step_rows: list[int] = field(default_factory=list)


def empty_batch(
    space: Space | None,
    keys: list[str] | None = None,
    routes: Mapping[str, TrajRoute] | None = None,
    chunk: int | None = None,
) -> StageBatch:
    """An answer of ``len(keys)`` rows of zeros (``space``: one env's observation space, None:
    no observation), per-action arrays ``[n, chunk]`` for a chunk step."""
    keys = keys or []
    n = len(keys)
    obs = create_empty_array(space, n=n, fn=np.zeros) if space is not None else {}
    per_action = (n,) if chunk is None else (n, chunk)
    return StageBatch(
        traj_keys=keys,
        task_ids=[routes[k].task_id for k in keys] if routes else [],
        state_ids=np.array([routes[k].state_id for k in keys] if routes else [], dtype=np.int64),
        obs=obs,
        reward=np.zeros(per_action, dtype=np.float64),
        terminated=np.zeros(per_action, dtype=bool),
        truncated=np.zeros(per_action, dtype=bool),
        success=np.zeros(per_action, dtype=bool),
        num_steps=np.zeros(n, dtype=np.int32),
    )

def fill_batch(
    batch: StageBatch,
    answer: dict[str, Any],
    rows: np.ndarray,
    pod: str,
    check_tasks: bool,
    chunk: int | None = None,
) -> None:
    """Write one pod's ``answer`` into rows ``rows`` of ``batch`` (a reset's with ``check_tasks``).

    Raises:
        PodRequestError: an answer of the wrong structure or shape, or of other tasks (names the key path).
    """
    try:
        _fill_answer(batch, answer, rows, pod, check_tasks, chunk)
    except trees.TreeMismatchError as exc:
        raise PodRequestError(pod, None, str(exc)) from None


def _fill_answer(
    batch: StageBatch, answer: dict[str, Any], rows: np.ndarray, pod: str, check_tasks: bool, chunk: int | None
) -> None:
    trees.fill_rows(batch.obs, answer.get("obs"), rows, "obs")
    env_info = answer.get("env_info")
    if env_info:
        batch.env_info.append((rows, env_info))
    errors = answer.get("errors")
    if errors:
        row_of = {int(env): int(row) for env, row in zip(answer["env_indices"], rows)}
        for env, kind, message in zip(errors.get("env_indices", ()), errors.get("type", ()), errors.get("message", ())):
            if int(env) in row_of:
                batch.errors.append((batch.traj_keys[row_of[int(env)]], str(kind), str(message)))
    info = answer.get("info") or {}
    trees.fill_rows(batch.success, info.get("success"), rows, "info.success")
    if check_tasks:
        said = list(info.get("task_id") or [])
        expected = [batch.task_ids[r] for r in rows]
        if said != expected:
            raise PodRequestError(pod, None, f"reset envs run tasks {said}, the routing table says {expected}")
    else:
        trees.fill_rows(batch.reward, answer.get("reward"), rows, "reward")
        trees.fill_rows(batch.terminated, answer.get("terminated"), rows, "terminated")
        trees.fill_rows(batch.truncated, answer.get("truncated"), rows, "truncated")
        if chunk is None:
            batch.num_steps[rows] = 1
        else:
            trees.fill_rows(batch.num_steps, answer.get("num_steps"), rows, "num_steps")

def check_actions(space: Space | None, step: Mapping[str, Any]) -> np.ndarray:
    """Return the call's actions as ``[n, *action shape]``, or its chunks (Box action spaces
    only) as ``[n, K, *action shape]``, in the dtype sent where it is of the action space's kind
    (:func:`vecsim.spaces.in_kind_of`; ``space`` None: float32 of any shape).

    Raises:
        ValueError: an action not numeric, of the wrong shape or not finite, or chunks of
            different lengths (names the traj_key).
    """
    shape = tuple(space.shape) if space is not None and space.shape is not None else None
    dtype = space.dtype if space is not None and space.dtype is not None else np.float32
    rows = []
    chunk: int | None = None  # K of the call's chunks; None: one action per trajectory
    for index, (key, action) in enumerate(step.items()):
        try:
            row = in_kind_of(np.asarray(action), dtype)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"traj_key {key!r}: action is not numeric: {exc}") from None
        if shape is not None and row.shape != shape and row.shape[1:] != shape:
            raise ValueError(
                f"traj_key {key!r}: action has shape {list(row.shape)}, expected {list(shape)} "
                f"or a chunk [K, {', '.join(map(str, shape))}]"
            )
        this = None if shape is None or row.shape == shape else row.shape[0]
        if this is not None and not isinstance(space, Box):
            raise ValueError(
                f"traj_key {key!r}: action has shape {list(row.shape)}, expected {list(shape or ())}; "
                f"chunks of actions are for Box action spaces, this job's is {space}"
            )
        if index and this != chunk:
            sent = "one action" if this is None else f"a chunk of {this}"
            first = "one action" if chunk is None else f"chunks of {chunk}"
            raise ValueError(
                f"traj_key {key!r}: {sent}, the call's first traj_key sent {first}; one call, one chunk length"
            )
        chunk = this
        rows.append(row)
    actions = np.stack(rows)
    if actions.dtype.kind != "f":
        return actions  # the pod checks integer actions against the space
    # One finiteness check for the whole batch: per-row checks cost more than a cheap scene's step.
    finite = np.isfinite(actions.reshape(len(rows), -1)).all(axis=1)
    if not finite.all():
        key = list(step)[int(np.flatnonzero(~finite)[0])]
        raise ValueError(f"traj_key {key!r}: action holds NaN or inf")
    return actions

async def run_call(
    book: RouteBook,
    info: JobInfo,
    post: Post,
    reset_keys: list[str],
    state_ids: np.ndarray,
    step_keys: list[str],
    actions: np.ndarray | None,
    pick: int | None,
    recorded: set[str],
    seeded: tuple[list[int | None], dict[str, Any]] | None = None,
    frozen: Mapping[str, Ended] | None = None,
    step_past_end: bool = False,
) -> tuple[StageBatch, StageBatch]:
    """Carry out one call on the routes in ``book``: each pod its resets (to ``state_ids``, or
    the envs' own reset with ``seeded`` = (seeds, options)), then its steps, pods concurrently; a
    pod with both fixed-state resets and steps gets them in one ``/v1/step`` request.
    Returns ``(reset_batch, step_batch)``; records the state ids reset to in ``book``.

    Step keys in ``frozen`` are not sent: their rows answer what their env was when it ended
    (reward 0, the flags held at every action, ``num_steps`` 0). ``step_past_end`` asks the pods
    to apply every action of a chunk, also after an env's end.

    Raises:
        PodUnavailableError, RoutingChangedError, ...: :func:`~vecsim.client.errors.call_error`
            of the pods' failures, carrying the answering pods' rows (``pick``: which batch).
    """
    submitted = time.perf_counter()
    routes = book.routes()
    space = info.observation_space
    reset_batch = empty_batch(space, reset_keys, routes)
    reset_batch.state_ids = state_ids.copy()
    chunk = actions.shape[1] if actions is not None and actions.ndim == single_action_ndim(info) + 1 else None
    step_batch = empty_batch(space, step_keys, routes, chunk)
    work: dict[str, _PodWork] = {}
    for row, key in enumerate(reset_keys):
        work.setdefault(routes[key].pod, _PodWork()).reset_rows.append(row)
    frozen = frozen or {}
    for row, key in enumerate(step_keys):
        if key in frozen:
            _put_frozen(step_batch, row, frozen[key])
        else:
            work.setdefault(routes[key].pod, _PodWork()).step_rows.append(row)
    # Rows whose pod answered: they are delivered even when another pod of the call fails.
    answered = _PodWork(step_rows=[row for row, key in enumerate(step_keys) if key in frozen])

    def env_ids(keys: Sequence[str]) -> np.ndarray:
        return np.array([routes[k].env_index for k in keys], dtype=np.int64)

    async def send(pod: str, op: str, row_list: list[int], all_keys: Sequence[str], field: str,
                   values: np.ndarray, batch: StageBatch, refill: list[int] | None = None) -> None:
        """One request; a step with ``refill`` (reset rows) also resets those envs in it."""
        rows = np.asarray(row_list)
        keys = [all_keys[r] for r in rows]
        body = {"env_indices": env_ids(keys)}
        if op == "reset" and seeded is not None:
            body["seeds"] = [seeded[0][r] for r in rows]
            if seeded[1]:
                body["options"] = seeded[1]
        else:
            body[field] = values[rows]
        if op == "step" and step_past_end and chunk is not None:
            body["step_past_end"] = True
        record = [k for k in keys if k in recorded]
        if record:
            body["record_env_indices"] = env_ids(record)
        reset_rows = np.asarray(refill or [], dtype=np.int64)
        resetting = [reset_keys[r] for r in reset_rows]
        if resetting:
            body["reset_env_indices"] = env_ids(resetting)
            body["reset_state_ids"] = state_ids[reset_rows]
        extra = info.chunk_answer_bytes(len(keys), chunk, len(record)) if op == "step" else 0
        answer = await post(pod, op, body, [*resetting, *keys], extra)
        try:
            if resetting:
                reset = answer.get("reset")
                said = np.asarray(reset.get("env_indices", ())) if isinstance(reset, dict) else None
                if said is None or not np.array_equal(said, body["reset_env_indices"]):
                    raise PodRequestError(pod, None, f"answer's reset is not for env ids {body['reset_env_indices'].tolist()}")
                fill_batch(reset_batch, reset, reset_rows, pod, check_tasks=True)
            fill_batch(batch, answer, rows, pod, check_tasks=op == "reset", chunk=chunk if op == "step" else None)
        except PodRequestError as exc:
            # An answer of the wrong shape or tasks: the pod's rows are unusable, not the call.
            raise PodUnavailableError({pod: [*resetting, *keys]}, exc.detail) from None
        for j, key in enumerate(record):
            frames = answer.get("frames") or {}
            batch.frames[key] = {camera: np.asarray(images)[j] for camera, images in frames.items()}

    async def one_pod(pod: str, todo: _PodWork) -> None:
        reset_done = False
        try:
            if todo.reset_rows and todo.step_rows and seeded is None and actions is not None and actions.size:
                # A refill: the resets ride in the step's request, and run beside its steps.
                await send(pod, "step", todo.step_rows, step_keys, "actions", actions, step_batch, todo.reset_rows)
                answered.reset_rows.extend(todo.reset_rows)
                answered.step_rows.extend(todo.step_rows)
                return
            if todo.reset_rows:
                await send(pod, "reset", todo.reset_rows, reset_keys, "state_ids", state_ids, reset_batch)
                answered.reset_rows.extend(todo.reset_rows)
                reset_done = True
            if todo.step_rows:
                await send(pod, "step", todo.step_rows, step_keys, "actions", actions, step_batch)
                answered.step_rows.extend(todo.step_rows)
        except PodUnavailableError as exc:
            # Name everything of this call the pod did not answer: after a failed reset, its
            # steps were never sent.
            unanswered = [] if reset_done else [reset_keys[r] for r in todo.reset_rows]
            unanswered += [step_keys[r] for r in todo.step_rows]
            raise PodUnavailableError({pod: unanswered}, exc.reason) from None

    if not work:
        results: list[BaseException | None] = []
    elif len(work) == 1:
        # One pod (a stage of one pod, a vector env of one): awaited here, without the task and
        # the two event-loop turns that gather spends on it.
        try:
            results = [await one_pod(*next(iter(work.items())))]
        except Exception as exc:  # noqa: BLE001 - as gather(return_exceptions=True) keeps it
            results = [exc]
    else:
        results = await asyncio.gather(*(one_pod(p, w) for p, w in work.items()), return_exceptions=True)
    book.set_state_ids([reset_keys[r] for r in answered.reset_rows], [int(state_ids[r]) for r in answered.reset_rows])
    finished = time.perf_counter()
    for batch in (reset_batch, step_batch):
        batch.submitted_at, batch.finished_at = submitted, finished
    errors = [r for r in results if isinstance(r, BaseException)]
    if errors:
        partial = (
            take_rows(reset_batch, sorted(answered.reset_rows)),
            take_rows(step_batch, sorted(answered.step_rows)),
        )
        raise call_error(errors, partial if pick is None else partial[pick])
    return reset_batch, step_batch



def _put_frozen(batch: StageBatch, row: int, ended: Ended) -> None:
    """Row ``row`` of a step answer as a frozen env's: its ended observation and held flags."""
    trees.put_rows(batch.obs, trees.map_leaves(lambda leaf: np.asarray(leaf)[None], ended.obs), np.array([row]))
    batch.reward[row] = 0.0
    batch.terminated[row] = ended.terminated
    batch.truncated[row] = ended.truncated
    batch.success[row] = ended.success
    batch.num_steps[row] = 0


def single_action_ndim(info: JobInfo) -> int:
    """The ndim of one call's actions of one action each (``[n, *action shape]``); one more: chunks."""
    space = info.action_space
    return 1 + len(space.shape or ()) if space is not None else 2
