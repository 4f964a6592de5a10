"""One stage call: its answer (:class:`StageBatch`), its handle (:class:`PendingCall`), and how it
is carried out: the actions checked, each pod sent its rows, the answers written into batch
arrays allocated before the requests go out, and a pod's failure kept to its own trajectories.

No routing decisions here: the routes come from the route book, the HTTP from the client's
:class:`~vecsim.client.pods.PodSet` (one pod, one request, with the routing generation and its
409 handling). What a call's actions are (one action or a chunk of K per trajectory) is said
once, by :func:`step_actions`, and travels with the call as :class:`StepActions`.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import time
from collections.abc import Generator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

import numpy as np
from gymnasium import Space
from gymnasium.error import ResetNeeded
from gymnasium.spaces import Box
from gymnasium.vector.utils import create_empty_array

from vecsim import trees, wire
from vecsim.client.errors import PodRequestError, PodUnavailableError, call_error
from vecsim.client.pods import EventLoopThread, PodSet
from vecsim.client.routebook import RouteBook
from vecsim.client.routing import TrajRoute
from vecsim.info import take_rows as info_rows
from vecsim.spaces import in_kind_of

__all__ = [
    "Ended",
    "PendingCall",
    "StageBatch",
    "StepActions",
    "check_actions",
    "check_attr",
    "check_call",
    "completed",
    "empty_batch",
    "run_attr",
    "run_call",
    "step_actions",
    "take_rows",
]

T = TypeVar("T")


@dataclass
class StageBatch:
    """The answer to one reset or step call: row ``j`` belongs to ``traj_keys[j]``.

    ``state_ids`` are the trajectories' state ids (the ones just reset to, after a reset). After
    a reset ``reward`` is 0 and ``terminated``/``truncated`` are False. ``submitted_at`` and
    ``finished_at`` are ``time.perf_counter()`` stamps of the call.

    A step of chunks (K actions per trajectory) answers ``reward``, ``terminated``, ``truncated``
    and ``success`` of shape ``[n, K]`` (0/false after a trajectory's env stopped), ``obs`` after
    each one's last applied action, ``num_steps`` ``[n]`` the actions each applied, and ``frames``
    ``{traj_key: {camera: uint8[K, H, W, 3]}}`` for the trajectories asked to be recorded, and
    ``chunk`` is K (also with no rows). A one-action step answers ``[n]`` arrays, ``num_steps``
    of ones and ``chunk`` None; a reset, zeros and None.

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
    chunk: int | None = None

    @property
    def n(self) -> int:
        return len(self.traj_keys)

    def ended(self) -> np.ndarray:
        """Per row: whether its env terminated or truncated (at any action of a chunk)."""
        flags = self.terminated | self.truncated
        return flags if self.chunk is None else flags.any(axis=1)

    def last(self, values: np.ndarray) -> np.ndarray:
        """Per row, the per-action ``values`` (``reward``, ``success``, ...) at the row's last
        applied action (a chunk's: action ``num_steps - 1``, the first one if it applied none)."""
        if self.chunk is None:
            return values
        return values[np.arange(self.n), np.maximum(self.num_steps.astype(np.int64) - 1, 0)]


@dataclass(frozen=True)
class StepActions:
    """One call's actions, as :func:`step_actions` checked them: row ``j`` of ``array`` for
    ``traj_keys[j]``, ``[n, *action shape]`` (one action each, ``chunk`` None) or
    ``[n, K, *action shape]`` (a chunk of ``chunk`` = K each)."""

    traj_keys: list[str]
    array: np.ndarray
    chunk: int | None

    def rows(self, index: Sequence[int], at_most: int | None = None) -> StepActions:
        """The actions of rows ``index``, in that order; chunks cut to their first ``at_most``
        actions (one action each stays as it is)."""
        keys = [self.traj_keys[i] for i in index]
        array = self.array[np.asarray(index, dtype=np.int64)]
        if self.chunk is None or at_most is None or at_most >= self.chunk:
            return StepActions(keys, array, self.chunk)
        return StepActions(keys, array[:, :at_most], at_most)


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
    env_info: list[tuple[np.ndarray, dict[str, Any]]] = []
    for pod_rows, batched in batch.env_info:
        at = [j for j, r in enumerate(pod_rows) if int(r) in new_row]
        if at:  # all or some of this pod's rows: their part of its info
            part = batched if len(at) == len(pod_rows) else info_rows(batched, at)
            env_info.append((np.array([new_row[int(pod_rows[j])] for j in at], dtype=np.int64), part))
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
        chunk=batch.chunk,
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
    # The flags where the env ended: its last applied action (num_steps of K; the last action
    # for an env stepped past its end).
    terminated, truncated, success = (
        batch.last(values) for values in (batch.terminated, batch.truncated, batch.success)
    )
    return {
        batch.traj_keys[j]: Ended(
            trees.row(batch.obs, int(j)), bool(terminated[j]), bool(truncated[j]), bool(success[j])
        )
        for j in np.flatnonzero(batch.ended())
    }


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
        chunk=chunk,
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


def step_actions(space: Space | None, traj_keys: Sequence[str], actions: Any) -> StepActions:
    """Say what a call's actions are, once for every layer: ``actions`` (row ``j`` for
    ``traj_keys[j]``) as ``[n, *action shape]`` (one action each) or ``[n, K, *action shape]``
    (a chunk each; Box action spaces only, :func:`vecsim.wire.chunk_length`'s rule), in the dtype
    sent where it is of the action space's kind (:func:`vecsim.spaces.in_kind_of`; ``space`` None:
    float32 of any shape, one action each).

    Raises:
        ValueError: actions not numeric, of another shape or count than ``traj_keys``, a chunk
            of a non-Box space, or NaN or inf (names the traj_key).
    """
    keys = list(traj_keys)
    shape = tuple(space.shape) if space is not None and space.shape is not None else None
    dtype = space.dtype if space is not None and space.dtype is not None else np.float32
    try:
        array = in_kind_of(np.asarray(actions), dtype)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"actions are not numeric: {exc}") from None
    chunk = None if shape is None else wire.chunk_length(array.shape, shape)
    if chunk is not None and not isinstance(space, Box):
        raise ValueError(
            f"actions have shape {list(array.shape)}; chunks of actions are for Box action spaces, this job's is {space}"
        )
    if shape is not None:
        expected = (len(keys), *shape) if chunk is None else (len(keys), chunk, *shape)
        if array.shape != expected:
            raise ValueError(
                f"actions have shape {list(array.shape)}, expected {list(expected)} for {len(keys)} traj_keys "
                f"(or chunks [{len(keys)}, K, {', '.join(map(str, shape))}])"
            )
    if array.dtype.kind == "f" and len(keys):
        # One finiteness check for the whole batch: per-row checks cost more than a cheap scene's step.
        finite = np.isfinite(array.reshape(len(keys), -1)).all(axis=1)
        if not finite.all():
            raise ValueError(f"traj_key {keys[int(np.flatnonzero(~finite)[0])]!r}: action holds NaN or inf")
    return StepActions(keys, array, chunk)


def check_actions(space: Space | None, step: Mapping[str, Any]) -> StepActions:
    """:func:`step_actions` of a mapping ``{traj_key: action or chunk}``, each value checked
    alone first so that an error names its traj_key.

    Raises:
        ValueError: as :func:`step_actions`, or values that are not one form (one action, or
            chunks of one length).
    """
    shape = tuple(space.shape) if space is not None and space.shape is not None else None
    dtype = space.dtype if space is not None and space.dtype is not None else np.float32
    rows = []
    first: int | None = None  # K of the call's first value; None: one action
    checked: tuple[int, ...] | None = None  # the shape of the rows checked so far
    for index, (key, action) in enumerate(step.items()):
        try:
            row = in_kind_of(np.asarray(action), dtype)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"traj_key {key!r}: action is not numeric: {exc}") from None
        rows.append(row)
        if row.shape == checked:
            continue  # as the rows before it
        this = None if shape is None else wire.chunk_length((1, *row.shape), shape)
        if shape is not None and row.shape[this is not None :] != shape:
            raise ValueError(
                f"traj_key {key!r}: action has shape {list(row.shape)}, expected {list(shape)} "
                f"or a chunk [K, {', '.join(map(str, shape))}]"
            )
        if this is not None and not isinstance(space, Box):
            raise ValueError(
                f"traj_key {key!r}: action has shape {list(row.shape)}, expected {list(shape or ())}; "
                f"chunks of actions are for Box action spaces, this job's is {space}"
            )
        if index and this != first:
            sent = "one action" if this is None else f"a chunk of {this}"
            said = "one action" if first is None else f"chunks of {first}"
            raise ValueError(
                f"traj_key {key!r}: {sent}, the call's first traj_key sent {said}; one call, one chunk length"
            )
        first, checked = this, row.shape
    return step_actions(space, list(step), np.stack(rows))


@dataclass
class CallArgs:
    """One call's arguments, checked against the route book by :func:`check_call`: the
    trajectories reset (to ``state_ids``, or the envs' own reset with ``seeded`` = (seeds,
    options)), the routes of every key, the stepped keys whose frames are ``recorded`` and the
    ``frozen`` ones (ended: answered unstepped)."""

    reset_keys: list[str]
    state_ids: np.ndarray
    routes: dict[str, TrajRoute]
    recorded: set[str]
    seeded: tuple[list[int | None], dict[str, Any]] | None
    frozen: dict[str, Ended]


def check_call(
    book: RouteBook,
    reset: Sequence[str] | Mapping[str, int],
    step_keys: list[str],
    record: Sequence[str],
    seeds: Mapping[str, int | None] | None,
    options: Mapping[str, Any] | None,
    ended_envs: str,
) -> CallArgs:
    """Check a call's keys against ``book``: ``reset`` (keys, or keys to new state ids),
    ``step_keys``, ``record`` (stepped keys), ``seeds`` (in place of state ids); ``ended_envs`` as
    :class:`~vecsim.client.stage.StageClient`'s says what stepping an ended trajectory does.

    Raises:
        ValueError: a key both reset and stepped, repeated, not live, recorded but not stepped,
            a negative state id (names the key); ``seeds`` with ``reset``, ``options`` without.
        RoutingChangedError: a key whose env went away when the routing changed.
        ResetNeeded: (``ended_envs`` ``"raise"``) a stepped trajectory that ended.
    """
    if seeds is not None:
        if reset:
            raise ValueError("give reset (fixed initial states) or seeds (the envs' own reset), not both")
        reset = list(seeds)
    elif options:
        raise ValueError("options go with seeds (the envs' own reset)")
    recorded = set(record)
    if recorded - set(step_keys):
        raise ValueError(f"record: traj_keys {sorted(recorded - set(step_keys))} are not stepped in this call")
    new_ids = dict(reset) if isinstance(reset, Mapping) and seeds is None else None
    reset_keys = list(reset)
    both = set(reset_keys) & set(step_keys)
    if both:
        raise ValueError(f"traj_keys {sorted(both)} are both reset and stepped in one call")
    if len(set(reset_keys)) != len(reset_keys) or len(set(step_keys)) != len(step_keys):
        raise ValueError("traj_keys repeat within one call")
    book.check_lost([*reset_keys, *step_keys])
    routes = book.live([*reset_keys, *step_keys])
    ended = book.ended()
    stepped_ended = [k for k in step_keys if k in ended]
    if stepped_ended and ended_envs == "raise":
        raise ResetNeeded(
            f"traj_keys {stepped_ended} ended (terminated or truncated) and were not reset; reset them, or "
            "make the client with ended_envs='step' (step them on) or 'freeze' (answer them unstepped)"
        )
    state_ids = np.array(
        [new_ids[k] if new_ids is not None else routes[k].state_id for k in reset_keys], dtype=np.int64
    )
    if new_ids is not None:
        for key, sid in zip(reset_keys, state_ids):
            if sid < 0:
                raise ValueError(f"traj_key {key!r}: state_id must be >= 0, got {sid}")
    return CallArgs(
        reset_keys=reset_keys,
        state_ids=state_ids,
        routes=routes,
        recorded=recorded,
        seeded=None if seeds is None else ([seeds[k] for k in reset_keys], dict(options or {})),
        frozen={k: ended[k] for k in stepped_ended} if ended_envs == "freeze" else {},
    )


def _note_ended(book: RouteBook, reset_batch: StageBatch, step_batch: StageBatch) -> None:
    """Keep track of which trajectories ended: reset ones did not, stepped ones may have (not
    those whose env raised)."""
    failed = {key for key, _type, _message in step_batch.errors}
    book.note_ended(reset_batch.traj_keys, {k: e for k, e in ended_rows(step_batch).items() if k not in failed})


async def run_call(
    pods: PodSet, args: CallArgs, actions: StepActions | None, pick: int | None, step_past_end: bool = False
) -> tuple[StageBatch, StageBatch]:
    """Carry out one call (``args``, ``actions``) on the routes in ``pods.book``: each pod its
    resets, then its steps, pods concurrently; a pod with both fixed-state resets and steps gets
    them in one ``/v1/step`` request. Returns ``(reset_batch, step_batch)``; records in the book
    the state ids reset to and which trajectories ended.

    Step keys in ``args.frozen`` are not sent: their rows answer what their env was when it
    ended (reward 0, the flags held at every action, ``num_steps`` 0). ``step_past_end`` asks the
    pods to apply every action of a chunk, also after an env's end.

    Raises:
        PodUnavailableError, RoutingChangedError, ...: :func:`~vecsim.client.errors.call_error`
            of the pods' failures, carrying the answering pods' rows (``pick``: which batch).
    """
    submitted = time.perf_counter()
    book, info = pods.book, pods.info
    reset_keys, state_ids, recorded, seeded, frozen = (
        args.reset_keys,
        args.state_ids,
        args.recorded,
        args.seeded,
        args.frozen,
    )
    routes = book.routes()
    space = info.observation_space
    reset_batch = empty_batch(space, reset_keys, routes)
    reset_batch.state_ids = state_ids.copy()
    step_keys = actions.traj_keys if actions is not None else []
    chunk = actions.chunk if actions is not None else None
    step_batch = empty_batch(space, step_keys, routes, chunk)
    work: dict[str, _PodWork] = {}
    for row, key in enumerate(reset_keys):
        work.setdefault(routes[key].pod, _PodWork()).reset_rows.append(row)
    for row, key in enumerate(step_keys):
        if key in frozen:
            _put_frozen(step_batch, row, frozen[key])
        else:
            work.setdefault(routes[key].pod, _PodWork()).step_rows.append(row)
    # Rows whose pod answered: they are delivered even when another pod of the call fails.
    answered = _PodWork(step_rows=[row for row, key in enumerate(step_keys) if key in frozen])

    def env_ids(keys: Sequence[str]) -> np.ndarray:
        return np.array([routes[k].env_index for k in keys], dtype=np.int64)

    async def send(
        pod: str,
        op: str,
        row_list: list[int],
        all_keys: Sequence[str],
        field: str,
        values: np.ndarray,
        batch: StageBatch,
        refill: list[int] | None = None,
    ) -> None:
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
        answer = await pods.post(pod, op, body, [*resetting, *keys], extra)
        try:
            if resetting:
                reset = answer.get("reset")
                said = np.asarray(reset.get("env_indices", ())) if isinstance(reset, dict) else None
                if said is None or not np.array_equal(said, body["reset_env_indices"]):
                    raise PodRequestError(
                        pod, None, f"answer's reset is not for env ids {body['reset_env_indices'].tolist()}"
                    )
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
            if todo.reset_rows and todo.step_rows and seeded is None and actions is not None and actions.array.size:
                # A refill: the resets ride in the step's request, and run beside its steps.
                await send(
                    pod, "step", todo.step_rows, step_keys, "actions", actions.array, step_batch, todo.reset_rows
                )
                answered.reset_rows.extend(todo.reset_rows)
                answered.step_rows.extend(todo.step_rows)
                return
            if todo.reset_rows:
                await send(pod, "reset", todo.reset_rows, reset_keys, "state_ids", state_ids, reset_batch)
                answered.reset_rows.extend(todo.reset_rows)
                reset_done = True
            if todo.step_rows:
                await send(pod, "step", todo.step_rows, step_keys, "actions", actions.array, step_batch)  # type: ignore[union-attr]
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
        _note_ended(book, *partial)
        raise call_error(errors, partial if pick is None else partial[pick])
    _note_ended(book, reset_batch, step_batch)
    return reset_batch, step_batch


def check_attr(book: RouteBook, op: str, keys: Sequence[str]) -> dict[str, TrajRoute]:
    """The live routes, checked for an attribute call ``op`` on ``keys``.

    Raises:
        ValueError: an unknown op, or keys that are not live trajectories (names them).
    """
    if op not in ("get_attr", "call", "set_attr"):
        raise ValueError(f"op must be get_attr, call or set_attr, got {op!r}")
    routes = book.routes()
    unknown = [k for k in keys if k not in routes]
    if unknown:
        raise ValueError(f"traj_keys {unknown} are not live trajectories")
    return routes


async def run_attr(
    pods: PodSet, op: str, keys: list[str], name: str, payload: Any, routes: Mapping[str, TrajRoute]
) -> tuple[list[Any], list[tuple[str, str, str]]]:
    """Carry out an attribute call (``op`` ``get_attr``, ``call`` or ``set_attr``) of ``name`` on
    the envs of ``keys``, all their pods concurrently (as JSON; a 409 is a refusal here).
    Returns one result per key and ``(traj_key, exception type name, message)`` per env that
    raised (see :meth:`~vecsim.client.stage.StageClient.env_attr`)."""
    by_pod: dict[str, list[int]] = {}
    for row, key in enumerate(keys):
        by_pod.setdefault(routes[key].pod, []).append(row)

    async def one_pod(pod: str, rows: list[int]) -> dict[str, Any]:
        body: dict[str, Any] = {
            "generation": pods.book.generation,
            "env_indices": [routes[keys[r]].env_index for r in rows],
            "name": name,
        }
        if op == "call":
            body["args"], body["kwargs"] = payload
        elif op == "set_attr":
            body["values"] = [payload[r] for r in rows]
        return await pods[pod].call_json(op, body, [keys[r] for r in rows])

    answers = await asyncio.gather(*(one_pod(pod, rows) for pod, rows in by_pod.items()))
    results: list[Any] = [None] * len(keys)
    errors: list[tuple[str, str, str]] = []
    for (pod, rows), answer in zip(by_pod.items(), answers):
        for row, result in zip(rows, answer.get("results") or []):
            results[row] = result
        raised = answer.get("errors") or {}
        row_of = {routes[keys[r]].env_index: r for r in rows}
        for env, kind, message in zip(raised.get("env_indices", ()), raised.get("type", ()), raised.get("message", ())):
            if env in row_of:
                errors.append((keys[row_of[env]], str(kind), str(message)))
    return results, errors


def _put_frozen(batch: StageBatch, row: int, ended: Ended) -> None:
    """Row ``row`` of a step answer as a frozen env's: its ended observation and held flags."""
    trees.put_rows(batch.obs, trees.map_leaves(lambda leaf: np.asarray(leaf)[None], ended.obs), np.array([row]))
    batch.reward[row] = 0.0
    batch.terminated[row] = ended.terminated
    batch.truncated[row] = ended.truncated
    batch.success[row] = ended.success
    batch.num_steps[row] = 0
