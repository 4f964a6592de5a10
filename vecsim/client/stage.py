"""StageClient: trajectories routed to pods, stepped one pipeline stage at a time.

Usage, top to bottom::

    client = StageClient.from_controller("http://127.0.0.1:8000")
    routes = client.reset_trajectories([("tiny/lift", 0), ("tiny/stack", 3), ...])
    first = client.reset_stage(0).result()          # or: await client.reset_stage(0)
    pending = client.step_stage(0, {key: action for key, action in ...})
    ...                                             # work on another stage meanwhile
    batch = pending.result()
    pending = client.step_stage(0, {key: chunk for key, chunk in ...})   # chunks [K, action dim]

Every call returns a :class:`PendingCall` at once (awaitable, or ``.result()`` from sync code);
the HTTP runs on the client's own event loop thread, all pods of a call concurrently, over one
keep-alive connection pool per pod, and the answers land in batch arrays allocated before the
requests go out. Each stage is a small state machine like gymnasium's ``AsyncVectorEnv``: idle, or
waiting on one call; a second call on a waiting stage raises ``AlreadyPendingCallError``.

A pod that fails a call (no answer in time, refused connection, 503, envs moved by the routing)
fails it for its own trajectories only: the error names them and carries the rows of the pods
that did answer (``error.answered``), whose envs have advanced and must not be lost.
"""

from __future__ import annotations

import asyncio
import atexit
import concurrent.futures
import dataclasses
import itertools
import logging
import math
import threading
import time
import weakref
from collections.abc import Coroutine, Generator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

import httpx
import numpy as np
from gymnasium import Space
from gymnasium.spaces import Box, Dict
from gymnasium.error import AlreadyPendingCallError, ClosedEnvironmentError
from gymnasium.vector.utils import create_empty_array

from vecsim.auth import token_from_env
from vecsim.client.errors import (
    ClientError,
    PodRequestError,
    PodUnavailableError,
    RoutingChangedError,
    StaleGenerationError,
    call_error,
)
from vecsim.client.pods import EventLoopThread, PodConnection
from vecsim.client.routing import (
    TrajRoute,
    changed_routes,
    place_requests,
    routing_from_pod_infos,
    stage_by_id,
    validate_routes,
)
from vecsim.config import RoutingTable
from vecsim.spaces import space_from_json
from vecsim.transport import DEFAULT_MAX_ANSWER_BYTES, MAX_CONTROL_ANSWER_BYTES, get_answer, make_async_client, read_answer

logger = logging.getLogger(__name__)

__all__ = ["PendingCall", "StageBatch", "StageClient", "fetch_routing"]

T = TypeVar("T")

# Bytes an env's answer may hold besides its observation: reward, flags, env id, task id, info.
_PER_ENV_EXTRA_BYTES = 4096
# A chunk's answer carries reward, terminated, truncated and success per action of each env.
_PER_ACTION_BYTES = 16


def _leaves(value: Any) -> list[np.ndarray]:
    """The arrays of a nested dict/tuple made by ``create_empty_array``."""
    if isinstance(value, np.ndarray):
        return [value]
    items = value.values() if isinstance(value, dict) else value if isinstance(value, tuple) else ()
    return [leaf for item in items for leaf in _leaves(item)]


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


def _completed(value: Any, pick: int | None) -> PendingCall[Any]:
    future: concurrent.futures.Future[Any] = concurrent.futures.Future()
    future.set_result(value)
    return PendingCall(future, pick)


def _read_routing(response: httpx.Response, url: str) -> RoutingTable:
    """The routing table in a controller's answer to ``GET /v1/routing``.

    Raises:
        PodRequestError: a refusal or an answer that is not a routing table.
    """
    if response.status_code != 200:
        raise PodRequestError("controller", response.status_code, response.text[:500])
    try:
        return RoutingTable.model_validate(response.json())
    except ValueError as exc:
        raise PodRequestError("controller", None, f"invalid routing table from {url}: {exc}") from None


# A new batch waits at most this long for a fresh routing table before it goes on the one in use.
_REFRESH_TIMEOUT_S = 5.0
# Waiting for a controller: the first retry comes soon, later ones no more often than this.
_WAIT_FIRST_S = 0.1
_WAIT_MAX_S = 2.0
# While waiting, what the controller answered is logged at INFO this often (at DEBUG between).
_WAIT_LOG_EVERY_S = 5.0


def fetch_routing(controller_url: str, timeout_s: float = 10.0, wait_ready_s: float = 0.0) -> RoutingTable:
    """Return the controller's routing table (``GET /v1/routing``).

    With ``wait_ready_s > 0``, tries again with growing pauses (up to 2 s) until the table says
    ready or the time is up, through a controller that is down, not listening yet (connection
    refused, its name not resolving yet), restarting (no answer, 5xx), without a job yet (404) or
    without a plan yet (a table not ready), saying at INFO every 5 s what it last saw.

    Raises:
        PodUnavailableError: the controller did not answer (named as pod ``controller``), and no
            waiting was asked for.
        TimeoutError: waited ``wait_ready_s`` without a ready table; says what it last saw.
        PodRequestError: the controller refused the request (4xx; 404 only when no waiting was
            asked for) or answered something that is not a routing table.
    """
    url = f"{controller_url.rstrip('/')}/v1/routing"
    started = time.monotonic()
    deadline = started + wait_ready_s
    pause = _WAIT_FIRST_S
    attempts = 0
    next_info = started
    while True:
        attempts += 1
        left = deadline - time.monotonic()
        try:
            # A request never outlives the wait: a controller that accepts and stalls is waited
            # for like one that is down.
            response = get_answer(url, timeout_s=timeout_s if wait_ready_s <= 0 else max(min(timeout_s, left), 0.1))
        except httpx.HTTPError as exc:
            if wait_ready_s <= 0:
                raise PodUnavailableError({"controller": []}, f"GET {url}: {type(exc).__name__}: {exc}") from None
            seen = f"no answer ({type(exc).__name__}: {exc})"
        else:
            # 404: listening, but the job is not put yet (the runner does that once it answers).
            if (response.status_code >= 500 or response.status_code == 404) and wait_ready_s > 0:
                seen = f"HTTP {response.status_code}: {response.text[:200]}"
            else:
                table = _read_routing(response, url)
                if table.ready or wait_ready_s <= 0:
                    return table
                seen = f"a routing table not ready yet (generation {table.generation}, {len(table.stages)} stage(s))"
        now = time.monotonic()
        left = deadline - now
        if left <= 0:
            raise TimeoutError(
                f"waited {wait_ready_s} s ({attempts} tries) for a ready routing table at {url}; last saw {seen}"
            )
        level = logging.INFO if now >= next_info else logging.DEBUG
        if level == logging.INFO:
            next_info = now + _WAIT_LOG_EVERY_S
        logger.log(level, "waiting for the controller at %s (%.0f s of %s s): %s", url, now - started, wait_ready_s, seen)
        time.sleep(min(pause, left))
        pause = min(pause * 2, _WAIT_MAX_S)


def _fill_rows(dst: Any, src: Any, rows: np.ndarray, where: str, pod: str) -> None:
    """Copy a pod's batched answer ``src`` into rows ``rows`` of the preallocated ``dst`` (a
    tuple travels as a dict keyed "0", "1", ...: vecsim.spaces.tuples_as_dicts)."""
    if isinstance(dst, tuple):
        keys = [str(i) for i in range(len(dst))]
        if not isinstance(src, dict) or sorted(src) != sorted(keys):
            got = sorted(src) if isinstance(src, dict) else type(src).__name__
            raise PodRequestError(pod, None, f"answer {where} has keys {got}, expected {keys}")
        for key, sub in zip(keys, dst):
            _fill_rows(sub, src[key], rows, f"{where}.{key}", pod)
        return
    if isinstance(dst, dict):
        if not isinstance(src, dict) or set(src) != set(dst):
            got = sorted(src) if isinstance(src, dict) else type(src).__name__
            raise PodRequestError(pod, None, f"answer {where} has keys {got}, expected {sorted(dst)}")
        for key in dst:
            _fill_rows(dst[key], src[key], rows, f"{where}.{key}", pod)
        return
    src = np.asarray(src)
    if src.shape != (len(rows), *dst.shape[1:]):
        raise PodRequestError(
            pod, None, f"answer {where} has shape {list(src.shape)}, expected {[len(rows), *dst.shape[1:]]}"
        )
    dst[rows] = src


def _take_rows(batch: StageBatch, rows: list[int]) -> StageBatch:
    """Return the batch of rows ``rows`` of ``batch`` (in that order), timing stamps included."""
    index = np.asarray(rows, dtype=np.int64)

    def take(value: Any) -> Any:
        if isinstance(value, dict):
            return {key: take(item) for key, item in value.items()}
        if isinstance(value, tuple):
            return tuple(take(item) for item in value)
        return value[index]

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
        obs=take(batch.obs),
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


# Clients not closed yet: closed at interpreter exit while their loop threads still run, so
# that a script ending in an exception or Ctrl-C exits quietly, its connections closed.
_open_clients: weakref.WeakSet[StageClient] = weakref.WeakSet()


@atexit.register
def _close_open_clients() -> None:
    for client in list(_open_clients):
        client.close()


@dataclass
class _PodWork:
    """What one call asks of one pod: resets first, then steps (rows index the call's batches)."""

    reset_rows: list[int] = field(default_factory=list)
    step_rows: list[int] = field(default_factory=list)


class StageClient:
    """Routes trajectories to pod envs and steps them stage by stage (see the module docstring).

    ``routing`` is the job's routing table; ``controller_url``, when given, is where the table is
    re-read after a pod answers 409 (stale generation) and before each new batch is placed.
    ``timeout_s`` bounds every HTTP request as a whole, answer included: a pod that does not
    answer within it raises :class:`PodUnavailableError`. ``transport`` is how bytes reach the
    pods, any ``httpx.AsyncBaseTransport`` (``httpx.ASGITransport(app)`` runs a pod in-process);
    left out, ``vecsim.transport.make_transport()``. The client closes it. ``max_answer_bytes``
    caps one pod's answer; left out, each pod's cap follows from the job's observation space
    and the pod's env count (twice what its envs can produce, plus a MiB). ``token`` is the
    job's shared token, sent with every reset and step; left out, ``VECSIM_TOKEN`` is used
    (none: the pods must run without one).
    """

    def __init__(
        self,
        routing: RoutingTable,
        *,
        controller_url: str | None = None,
        timeout_s: float = 30.0,
        transport: httpx.AsyncBaseTransport | None = None,
        max_answer_bytes: int | None = None,
        token: str | None = None,
    ) -> None:
        if not (timeout_s > 0 and math.isfinite(timeout_s)):
            raise ValueError(f"timeout_s must be a positive number, got {timeout_s}")
        if max_answer_bytes is not None and max_answer_bytes < 1:
            raise ValueError(f"max_answer_bytes must be a positive number of bytes, got {max_answer_bytes}")
        stage_by_id(routing)
        self.controller_url = controller_url.rstrip("/") if controller_url else None
        self.timeout_s = float(timeout_s)
        self.max_answer_bytes = max_answer_bytes
        self._transport = transport
        self._http: httpx.AsyncClient | None = None
        self._token = token if token is not None else token_from_env()
        self._lock = threading.Lock()
        self._table = routing
        self._pods: dict[str, PodConnection] = {}
        self._routes: dict[str, TrajRoute] = {}
        self._pending: dict[int, PendingCall[Any]] = {}
        self._batches = itertools.count()
        self._spaces: tuple[Space, Space] | None = None
        self._env_answer_bytes: int | None = None  # what one env's answer can take, from the spaces
        self._instructions: dict[str, str] = {}
        self._reset_kinds: dict[str, str] = {}
        self._num_states: dict[str, int] = {}
        self._instances: dict[str, str | None] = {}  # pod -> its envs' build ("instance" in /v1/info)
        self._lost: dict[str, int] = {}  # traj_key -> generation at which its env went away
        self._closed = False
        self._loop = EventLoopThread()
        self._refresh_lock: asyncio.Lock | None = None
        _open_clients.add(self)
        self._sync_pods()

    @classmethod
    def from_controller(
        cls,
        controller_url: str,
        *,
        timeout_s: float = 30.0,
        wait_ready_s: float = 0.0,
        transport: httpx.AsyncBaseTransport | None = None,
        max_answer_bytes: int | None = None,
        token: str | None = None,
    ) -> StageClient:
        """Return a client over the controller's routing table (see :func:`fetch_routing`, which
        waits up to ``wait_ready_s`` for a controller that is down, restarting or not planned).

        Raises:
            PodUnavailableError, PodRequestError, TimeoutError: as :func:`fetch_routing`.
        """
        table = fetch_routing(controller_url, timeout_s=timeout_s, wait_ready_s=wait_ready_s)
        return cls(
            table,
            controller_url=controller_url,
            timeout_s=timeout_s,
            transport=transport,
            max_answer_bytes=max_answer_bytes,
            token=token,
        )

    @classmethod
    def from_pods(
        cls,
        urls: Sequence[str],
        *,
        timeout_s: float = 30.0,
        transport: httpx.AsyncBaseTransport | None = None,
        max_answer_bytes: int | None = None,
        token: str | None = None,
    ) -> StageClient:
        """Return a client over standalone pods (no controller), reading each pod's ``/v1/info``.

        Raises:
            PodUnavailableError: a pod did not answer.
            ValueError: the pods do not make a routing table (names the problem).
        """

        def info(url: str) -> tuple[str, dict[str, Any]]:
            try:
                response = get_answer(f"{url.rstrip('/')}/v1/info", timeout_s=timeout_s)
            except httpx.HTTPError as exc:
                raise PodUnavailableError({url: []}, f"GET /v1/info: {type(exc).__name__}: {exc}") from None
            if response.status_code != 200:
                raise PodRequestError(url, response.status_code, response.text[:500])
            try:
                return url.rstrip("/"), response.json()
            except ValueError as exc:
                raise PodRequestError(url, None, f"answer to /v1/info is not JSON: {exc}") from None

        infos = [info(u) for u in urls]
        client = cls(
            routing_from_pod_infos(infos),
            timeout_s=timeout_s,
            transport=transport,
            max_answer_bytes=max_answer_bytes,
            token=token,
        )
        try:
            client._adopt_info({i["pod"]: i for _, i in infos if i.get("num_envs")})
        except BaseException:
            client.close()
            raise
        return client

    # -- what the client routes over ------------------------------------------------------------

    @property
    def routing(self) -> RoutingTable:
        """The routing table in use (re-read after a 409 when a controller is known)."""
        return self._table

    @property
    def num_stages(self) -> int:
        return len(self._table.stages)

    @property
    def routes(self) -> dict[str, TrajRoute]:
        """A copy of the live trajectories' routes, in placement order."""
        with self._lock:
            return dict(self._routes)

    def stage_traj_keys(self, stage_id: int) -> list[str]:
        """Return the live traj_keys of a stage, in placement order.

        Raises:
            ValueError: no such stage.
        """
        self._check_stage(stage_id)
        with self._lock:
            return [key for key, route in self._routes.items() if route.stage_id == stage_id]

    @property
    def observation_space(self) -> Space | None:
        """One env's observation space, read from the pods' ``/v1/info`` (None if no pod has envs)."""
        spaces = self._load_info()
        return spaces[0] if spaces else None

    @property
    def action_space(self) -> Space | None:
        """One env's action space, read from the pods' ``/v1/info`` (None if no pod has envs)."""
        spaces = self._load_info()
        return spaces[1] if spaces else None

    @property
    def instructions(self) -> dict[str, str]:
        """Each task's instruction, read from the pods' ``/v1/info``."""
        self._load_info()
        return dict(self._instructions)

    @property
    def reset_kinds(self) -> dict[str, str]:
        """How each task's envs reset by default, from the pods' ``/v1/info``: ``"seed"`` (the
        env's own seeded reset: a gym task without cameras) or ``"state_id"`` (fixed states)."""
        self._load_info()
        return dict(self._reset_kinds)

    @property
    def num_states(self) -> dict[str, int]:
        """How many fixed initial states each task has (state ids ``0..n-1``), from the pods'
        ``/v1/info``: the trainer needs no task registry of its own."""
        self._load_info()
        return dict(self._num_states)

    # -- placing trajectories -------------------------------------------------------------------

    def reset_trajectories(
        self, requests: Sequence[tuple[str, int]], traj_keys: Sequence[str] | None = None
    ) -> dict[str, TrajRoute]:
        """Place a new batch of trajectories: request ``i`` on stage ``stage_of(i, S)``.

        Replaces the live trajectories (no HTTP here; :meth:`reset_stage` puts the envs in their
        state ids). ``traj_keys`` defaults to fresh keys ``"<batch>-<i>"``. Returns
        ``{traj_key: TrajRoute}`` in request order. An empty batch is a no-op returning ``{}``.

        Raises:
            CapacityError: a stage lacks envs for a task (names task, stage and requests).
            ValueError: a malformed request or traj_keys.
            AlreadyPendingCallError: a call is still in flight.
            ClosedEnvironmentError: the client is closed.
        """
        self._check_open()
        self._refresh_routing()
        batch = next(self._batches)
        keys = list(traj_keys) if traj_keys is not None else [f"{batch}-{i}" for i in range(len(requests))]
        routes = place_requests(self._table, requests, keys)
        self._replace_routes(routes)
        return dict(routes)

    def _refresh_routing(self) -> None:
        """Before a new batch: take the controller's routing table if it has moved on and is
        ready, so that a reassignment finished before the batch costs the batch nothing.

        Without a controller, with calls in flight, or when the controller does not answer (within
        ``timeout_s``, 5 s at most), the table in use stays: the pods' 409 catch a stale one.
        """
        if self.controller_url is None:
            return
        with self._lock:
            if self._busy_stages(set(self._pending)):
                return
        try:
            new = self._loop.run(self._controller_routing(min(self.timeout_s, _REFRESH_TIMEOUT_S)))
            stage_by_id(new)
        except (ClientError, ValueError) as exc:
            logger.warning(
                "routing table not re-read before a new batch (%s); placing it on generation %d",
                exc,
                self._table.generation,
            )
            return
        if new.generation == self._table.generation or not new.ready:
            return
        logger.info("routing table moved from generation %d to %d; new batches go there",
                    self._table.generation, new.generation)  # fmt: skip
        with self._lock:
            self._table = new
            self._sync_pods()
        # The envs' builds now, so that a later 409 tells a rebuilt pod from a renumbered one.
        pods = [p.pod for stage in new.stages for p in stage.pods if p.num_envs > 0]

        async def builds() -> list[Any]:
            return await asyncio.gather(*(self._pods[p].info() for p in pods), return_exceptions=True)

        infos = self._loop.run(builds())
        with self._lock:
            for pod, info in zip(pods, infos):
                self._instances[pod] = None if isinstance(info, BaseException) else info.get("instance")

    def set_routes(self, routes: Mapping[str, TrajRoute]) -> None:
        """Make ``routes`` the live trajectories, as given (for callers that place envs themselves).

        Raises:
            ValueError: a route that does not fit the routing table, or two sharing an env.
            AlreadyPendingCallError, ClosedEnvironmentError: as :meth:`reset_trajectories`.
        """
        self._check_open()
        validate_routes(self._table, routes)
        self._replace_routes(dict(routes))

    def _replace_routes(self, routes: dict[str, TrajRoute]) -> None:
        with self._lock:
            busy = self._busy_stages(set(self._pending))
            if busy:
                raise AlreadyPendingCallError(
                    f"stages {busy} have calls in flight; wait for them before placing a new batch",
                    "reset",
                )
            self._routes = routes
            self._lost = {}

    # -- calls ----------------------------------------------------------------------------------

    def reset_stage(self, stage_id: int, traj_keys: Sequence[str] | None = None) -> PendingCall[StageBatch]:
        """Reset a stage's trajectories (all, or ``traj_keys``) to their state ids; don't wait.

        A stage without trajectories (or an empty ``traj_keys``) is a no-op: an empty batch.

        Raises:
            ValueError: no such stage, or a key not live on it.
            RoutingChangedError: a key whose env went away when the routing changed.
            AlreadyPendingCallError: the stage already waits on a call.
            ClosedEnvironmentError: the client is closed.

        The result raises what the call met: ``PodUnavailableError`` (no answer within
        ``timeout_s``), ``PodRequestError`` (refused), ``StaleGenerationError`` (409 after a
        re-read, or no controller to re-read from), ``RoutingChangedError`` (the re-read routing
        moved these trajectories' envs). A ``PodUnavailableError`` or ``RoutingChangedError``
        names only the failed pods' trajectories and carries the other pods' rows in its
        ``answered`` (a ``StageBatch``): their envs did reset or step, and they go on from there.
        """
        self._check_stage(stage_id)
        keys = self.stage_traj_keys(stage_id) if traj_keys is None else list(traj_keys)
        self._check_keys(keys, stage_id)
        return self._submit(reset=keys, step={}, pick=0)

    def step_stage(
        self, stage_id: int, actions_by_traj_key: Mapping[str, Any], record: Sequence[str] = ()
    ) -> PendingCall[StageBatch]:
        """Step the given trajectories of a stage, one action or one chunk each; don't wait.

        Each value is one action (``[action dim]``) or a chunk of K actions (``[K, action dim]``,
        the same K for every trajectory of the call, at most the pods' ``max_chunk``): a chunk
        is applied in order and stops at the trajectory's first termination or truncation, and
        the pod renders once, after the last applied action. ``record`` names traj_keys (of a
        chunk call) whose frame after every applied action the answer carries in ``frames``.
        An empty mapping is a no-op (an empty batch). Rows of the answer follow the mapping's order.

        Raises:
            ValueError: no such stage, a key not live on it, an action of the wrong shape or not
                finite, or chunks of different lengths (names the traj_key).
            RoutingChangedError, AlreadyPendingCallError, ClosedEnvironmentError: as
                :meth:`reset_stage`, whose notes on the result's errors hold here too.
        """
        self._check_stage(stage_id)
        self._check_keys(list(actions_by_traj_key), stage_id)
        return self._submit(reset=(), step=actions_by_traj_key, pick=1, record=record)

    def call(
        self,
        *,
        reset: Sequence[str] | Mapping[str, int] = (),
        step: Mapping[str, Any] | None = None,
        record: Sequence[str] = (),
        seeds: Mapping[str, int | None] | None = None,
        options: Mapping[str, Any] | None = None,
    ) -> PendingCall[tuple[StageBatch, StageBatch]]:
        """Reset some trajectories and step others in one round, over any stages; don't wait.

        ``reset`` lists traj_keys to reset to their route's state id, or maps traj_keys to new
        state ids (their routes take them on success). ``step`` maps traj_keys to actions or
        chunks, and ``record`` names stepped keys whose every frame is wanted, as in
        :meth:`step_stage`. ``seeds`` (instead of ``reset``) maps traj_keys to a seed or None:
        their envs reset as the envs' own ``reset(seed=..., options=options)``, not to a fixed
        state (the routes keep their state ids). Each pod gets its resets first, then its steps; pods run
        concurrently. The result is the pair
        ``(reset_batch, step_batch)``; nothing to do is a no-op answering two empty batches. The
        result's errors are :meth:`reset_stage`'s; ``answered`` is a pair here too.

        Raises:
            ValueError: unknown traj_keys, a key both reset and stepped, bad state ids or actions.
            RoutingChangedError: a key whose env went away when the routing changed.
            AlreadyPendingCallError: a stage involved already waits on a call.
            ClosedEnvironmentError: the client is closed.
        """
        if seeds is not None:
            if reset:
                raise ValueError("give reset (fixed initial states) or seeds (the envs' own reset), not both")
            return self._submit(reset=list(seeds), step=step or {}, pick=None, record=record, seeds=seeds, options=options)
        if options:
            raise ValueError("options go with seeds (the envs' own reset)")
        return self._submit(reset=reset, step=step or {}, pick=None, record=record)

    def env_attr(
        self, op: str, keys: Sequence[str], name: str, payload: Any = None
    ) -> PendingCall[tuple[list[Any], list[tuple[str, str, str]]]]:
        """Get (``op`` ``get_attr``), call (``call``; ``payload`` ``(args, kwargs)``) or set
        (``set_attr``; ``payload`` one value per key) attribute ``name`` of the envs of ``keys``,
        all their pods concurrently; don't wait.

        The result is ``(results, errors)``: one JSON result per key (None where its env raised or
        for ``set_attr``) and ``(traj_key, exception type name, message)`` per env that raised.
        It raises what a call's result raises (``PodRequestError`` for a 4xx: a bad name or value).

        Raises:
            ValueError: an unknown op or key.
            ClosedEnvironmentError: the client is closed.
        """
        self._check_open()
        if op not in ("get_attr", "call", "set_attr"):
            raise ValueError(f"op must be get_attr, call or set_attr, got {op!r}")
        with self._lock:
            routes = dict(self._routes)
        unknown = [k for k in keys if k not in routes]
        if unknown:
            raise ValueError(f"traj_keys {unknown} are not live trajectories")
        return self.submit(self._env_attr(op, list(keys), name, payload, routes))

    async def _env_attr(
        self, op: str, keys: list[str], name: str, payload: Any, routes: Mapping[str, TrajRoute]
    ) -> tuple[list[Any], list[tuple[str, str, str]]]:
        by_pod: dict[str, list[int]] = {}
        for row, key in enumerate(keys):
            by_pod.setdefault(routes[key].pod, []).append(row)

        async def one_pod(pod: str, rows: list[int]) -> dict[str, Any]:
            body: dict[str, Any] = {
                "generation": self._table.generation,
                "env_ids": [routes[keys[r]].env_index for r in rows],
                "name": name,
            }
            if op == "call":
                body["args"], body["kwargs"] = payload
            elif op == "set_attr":
                body["values"] = [payload[r] for r in rows]
            return await self._pods[pod].call_json(op, body, [keys[r] for r in rows])

        answers = await asyncio.gather(*(one_pod(pod, rows) for pod, rows in by_pod.items()))
        results: list[Any] = [None] * len(keys)
        errors: list[tuple[str, str, str]] = []
        for (pod, rows), answer in zip(by_pod.items(), answers):
            for row, result in zip(rows, answer.get("results") or []):
                results[row] = result
            raised = answer.get("errors") or {}
            row_of = {routes[keys[r]].env_index: r for r in rows}
            for env, kind, message in zip(raised.get("env_ids", ()), raised.get("type", ()), raised.get("message", ())):
                if env in row_of:
                    errors.append((keys[row_of[env]], str(kind), str(message)))
        return results, errors

    def submit(self, coro: Coroutine[Any, Any, T]) -> PendingCall[T]:
        """Run ``coro`` on the client's event loop and return its pending result.

        For chaining calls without a round trip through the caller: inside ``coro``, ``await``
        the client's calls (``await client.call(...)``).

        Raises:
            ClosedEnvironmentError: the client is closed.
        """
        self._check_open()
        return PendingCall(self._loop.submit(coro), loop=self._loop)

    def _submit(
        self,
        *,
        reset: Sequence[str] | Mapping[str, int],
        step: Mapping[str, Any],
        pick: int | None,
        record: Sequence[str] = (),
        seeds: Mapping[str, int | None] | None = None,
        options: Mapping[str, Any] | None = None,
    ) -> PendingCall[Any]:
        self._check_open()
        step = dict(step)
        recorded = set(record)
        if recorded - set(step):
            raise ValueError(f"record: traj_keys {sorted(recorded - set(step))} are not stepped in this call")
        reset_map = dict(reset) if isinstance(reset, Mapping) else None
        reset_keys = list(reset)
        both = set(reset_keys) & set(step)
        if both:
            raise ValueError(f"traj_keys {sorted(both)} are both reset and stepped in one call")
        if len(set(reset_keys)) != len(reset_keys) or len(set(step)) != len(step):
            raise ValueError("traj_keys repeat within one call")
        self._check_lost([*reset_keys, *step])
        with self._lock:
            routes = dict(self._routes)
        for key in itertools.chain(reset_keys, step):
            if key not in routes:
                raise ValueError(f"traj_key {key!r} is not a live trajectory; place it with reset_trajectories first")
        state_ids = np.array(
            [reset_map[k] if reset_map is not None and seeds is None else routes[k].state_id for k in reset_keys],
            dtype=np.int64,
        )
        if reset_map is not None and seeds is None:
            for key, sid in zip(reset_keys, state_ids):
                if sid < 0:
                    raise ValueError(f"traj_key {key!r}: state_id must be >= 0, got {sid}")
        # Spaces first, so even an empty answer has the job's observation structure (0 rows).
        self._load_info()
        if not reset_keys and not step:
            return _completed((self._empty_batch(), self._empty_batch()), pick)
        actions = self._check_actions(step) if step else None
        single_ndim = 1 + len(self.action_space.shape or ()) if self.action_space is not None else 2
        if recorded and (actions is None or actions.ndim != single_ndim + 1):
            raise ValueError("record: frames are recorded for chunk steps only; send [K, action dim] per traj_key")
        stages = {routes[k].stage_id for k in itertools.chain(reset_keys, step)}
        with self._lock:
            busy = self._busy_stages(stages)
            if busy:
                raise AlreadyPendingCallError(f"stage(s) {busy} already wait on a call; take its result first", "step")
            seeded = None if seeds is None else ([seeds[k] for k in reset_keys], dict(options or {}))
            future = self._loop.submit(self._run(reset_keys, state_ids, list(step), actions, pick, recorded, seeded))
            pending: PendingCall[Any] = PendingCall(future, pick, self._loop)
            for stage in stages:
                self._pending[stage] = pending
        future.add_done_callback(lambda _f: self._release(stages, pending))
        return pending

    def _busy_stages(self, stages: set[int]) -> list[int]:
        """Those of ``stages`` whose call is still running (call with the lock held). A finished
        call counts as over even before its done-callback has released its stages: a caller whose
        ``result()`` returned may call again at once."""
        return sorted(s for s in stages if s in self._pending and not self._pending[s].done())

    def _release(self, stages: set[int], pending: PendingCall[Any]) -> None:
        with self._lock:
            for stage in stages:
                if self._pending.get(stage) is pending:
                    del self._pending[stage]

    def close(self) -> None:
        """Close every pod connection and the loop thread; later calls raise ClosedEnvironmentError."""
        if self._closed:
            return
        self._closed = True
        _open_clients.discard(self)
        with self._lock:
            pending, self._pending = list(self._pending.values()), {}
        for call in pending:
            call.cancel()
        if self._loop.running:  # not so at interpreter exit (see _close_open_clients)
            try:
                self._loop.run(self._aclose(), timeout=min(self.timeout_s, 5.0))
            except (TimeoutError, RuntimeError) as exc:
                logger.warning("closing pod connections: %s", exc)
        self._loop.close()

    async def _aclose(self) -> None:
        if self._http is not None:
            await self._http.aclose()
        elif self._transport is not None:
            await self._transport.aclose()

    def __enter__(self) -> StageClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- checks ---------------------------------------------------------------------------------

    def _check_open(self) -> None:
        if self._closed:
            raise ClosedEnvironmentError("the StageClient is closed")

    def _check_stage(self, stage_id: int) -> None:
        self._check_open()
        if stage_id not in {s.stage_id for s in self._table.stages}:
            raise ValueError(f"stage {stage_id} is not in the routing table (stages 0..{self.num_stages - 1})")

    def _check_keys(self, keys: list[str], stage_id: int) -> None:
        self._check_lost(keys)
        with self._lock:
            for key in keys:
                route = self._routes.get(key)
                if route is None:
                    raise ValueError(
                        f"traj_key {key!r} is not a live trajectory; place it with reset_trajectories first"
                    )
                if route.stage_id != stage_id:
                    raise ValueError(f"traj_key {key!r} runs on stage {route.stage_id}, not stage {stage_id}")

    def _check_lost(self, keys: list[str]) -> None:
        with self._lock:
            lost = [key for key in keys if key in self._lost]
        if lost:
            raise RoutingChangedError(self._lost[lost[0]], lost)

    def _check_actions(self, step: Mapping[str, Any]) -> np.ndarray:
        """Return the call's actions as ``[n, *action shape]``, or its chunks (Box action spaces
        only) as ``[n, K, *action shape]``, in the action space's dtype."""
        space = self.action_space
        shape = tuple(space.shape) if space is not None and space.shape is not None else None
        dtype = space.dtype if space is not None and space.dtype is not None else np.float32
        rows = []
        chunk: int | None = None  # K of the call's chunks; None: one action per trajectory
        for index, (key, action) in enumerate(step.items()):
            try:
                row = np.asarray(action, dtype=dtype)
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

    # -- what runs on the loop ------------------------------------------------------------------

    def _http_client(self) -> httpx.AsyncClient:
        """The one ``httpx.AsyncClient`` every pod is reached through (made on the client's loop)."""
        if self._http is None:
            self._http = make_async_client(self._transport)
        return self._http

    def _sync_pods(self) -> None:
        """Make one connection per pod of the table (a pod whose URL changed gets a new one), each
        with its answer cap."""
        for stage in self._table.stages:
            for routed in stage.pods:
                known = self._pods.get(routed.pod)
                if known is None or known.url != routed.url.rstrip("/"):
                    self._pods[routed.pod] = PodConnection(
                        routed.pod, routed.url, self._http_client, self.timeout_s, self._token
                    )
                self._pods[routed.pod].max_answer_bytes = self._answer_cap(routed.num_envs)

    def _answer_cap(self, num_envs: int) -> int:
        """The most bytes a pod of ``num_envs`` envs may answer with (see the class docstring)."""
        if self.max_answer_bytes is not None:
            return self.max_answer_bytes
        if not self._spaces:
            return DEFAULT_MAX_ANSWER_BYTES
        if self._env_answer_bytes is None:
            one_env = create_empty_array(self._spaces[0], n=1, fn=np.zeros)
            # Besides the observation, each env answers a few flags, its reward, ids and info.
            self._env_answer_bytes = sum(leaf.nbytes for leaf in _leaves(one_env)) + _PER_ENV_EXTRA_BYTES
        return 2 * max(num_envs, 1) * self._env_answer_bytes + (1 << 20)

    def _chunk_answer_bytes(self, num_envs: int, chunk: int | None, num_recorded: int) -> int:
        """What a chunk step's answer carries beyond one observation per env: K per-action flags
        per env and, for each recorded env, K frames of every camera."""
        if chunk is None:
            return 0
        frames = 0
        if num_recorded and self._spaces:
            images = self._spaces[0].spaces.get("images") if isinstance(self._spaces[0], Dict) else None
            if images is not None:
                frames = sum(int(np.prod(space.shape)) * space.dtype.itemsize for space in images.spaces.values())
        return chunk * (num_envs * _PER_ACTION_BYTES + num_recorded * frames)

    def _load_info(self) -> tuple[Space, Space] | None:
        if self._spaces is None:
            self._check_open()
            if threading.current_thread() is self._loop.thread:
                raise RuntimeError("the pods' spaces must be read before calls are made from the client's loop")
            self._loop.run(self._fetch_info())
        return self._spaces or None

    async def _fetch_info(self) -> None:
        pods = [p.pod for s in self._table.stages for p in s.pods if p.num_envs > 0]
        infos = await asyncio.gather(*(self._pods[p].info() for p in pods))
        self._adopt_info(dict(zip(pods, infos)))

    def _adopt_info(self, infos: Mapping[str, Mapping[str, Any]]) -> None:
        """Take instructions and spaces from pods' ``/v1/info`` answers (pods with envs only)."""
        spaces_json = None
        first = next(iter(infos), None)
        for pod, info in infos.items():
            self._instances[pod] = info.get("instance")
            for task in info.get("tasks", []):
                self._instructions.setdefault(task["task_id"], task.get("instruction", ""))
                self._reset_kinds.setdefault(task["task_id"], task.get("reset", "state_id"))
                if "num_states" in task:
                    self._num_states.setdefault(task["task_id"], int(task["num_states"]))
            here = (info.get("observation_space"), info.get("action_space"))
            if here[0] is None or here[1] is None:
                raise PodUnavailableError({pod: []}, "envs not built yet (no spaces in /v1/info)")
            if spaces_json is None:
                spaces_json = here
            elif here != spaces_json:
                raise PodRequestError(pod, None, f"its spaces differ from pod {first}'s; one job, one space")
        if spaces_json is not None:
            self._spaces = (space_from_json(spaces_json[0]), space_from_json(spaces_json[1]))
        else:
            self._spaces = ()  # type: ignore[assignment]
        with self._lock:
            self._sync_pods()  # the answer caps follow from the spaces just read

    def _empty_batch(
        self,
        keys: list[str] | None = None,
        routes: Mapping[str, TrajRoute] | None = None,
        chunk: int | None = None,
    ) -> StageBatch:
        # Only cached spaces: this runs on the loop, and a no-op must not need the network.
        keys = keys or []
        n = len(keys)
        space = self._spaces[0] if self._spaces else None
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

    async def _run(
        self,
        reset_keys: list[str],
        state_ids: np.ndarray,
        step_keys: list[str],
        actions: np.ndarray | None,
        pick: int | None,
        recorded: set[str],
        seeded: tuple[list[int | None], dict[str, Any]] | None = None,
    ) -> tuple[StageBatch, StageBatch]:
        submitted = time.perf_counter()
        routes = self.routes
        reset_batch = self._empty_batch(reset_keys, routes)
        reset_batch.state_ids = state_ids.copy()
        single_ndim = 1 + len(self.action_space.shape or ()) if self.action_space is not None else 2
        chunk = actions.shape[1] if actions is not None and actions.ndim == single_ndim + 1 else None
        step_batch = self._empty_batch(step_keys, routes, chunk)
        work: dict[str, _PodWork] = {}
        for row, key in enumerate(reset_keys):
            work.setdefault(routes[key].pod, _PodWork()).reset_rows.append(row)
        for row, key in enumerate(step_keys):
            work.setdefault(routes[key].pod, _PodWork()).step_rows.append(row)
        # Rows whose pod answered: they are delivered even when another pod of the call fails.
        answered = _PodWork()

        async def send(pod: str, op: str, row_list: list[int], all_keys: Sequence[str], field: str,
                       values: np.ndarray, batch: StageBatch) -> None:  # fmt: skip
            rows = np.asarray(row_list)
            keys = [all_keys[r] for r in rows]
            body = {"env_ids": np.array([routes[k].env_index for k in keys], dtype=np.int64)}
            if op == "reset" and seeded is not None:
                body["seeds"] = [seeded[0][r] for r in rows]
                if seeded[1]:
                    body["options"] = seeded[1]
            else:
                body[field] = values[rows]
            record = [k for k in keys if k in recorded]
            if record:
                body["record_env_ids"] = np.array([routes[k].env_index for k in record], dtype=np.int64)
            extra = self._chunk_answer_bytes(len(keys), chunk, len(record)) if op == "step" else 0
            answer = await self._post(pod, op, body, keys, extra)
            try:
                self._fill(batch, answer, rows, pod, check_tasks=op == "reset", chunk=chunk if op == "step" else None)
            except PodRequestError as exc:
                # An answer of the wrong shape or tasks: the pod's rows are unusable, not the call.
                raise PodUnavailableError({pod: keys}, exc.detail) from None
            for j, key in enumerate(record):
                frames = answer.get("frames") or {}
                batch.frames[key] = {camera: np.asarray(images)[j] for camera, images in frames.items()}

        async def one_pod(pod: str, todo: _PodWork) -> None:
            reset_done = False
            try:
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

        results = await asyncio.gather(*(one_pod(p, w) for p, w in work.items()), return_exceptions=True)
        with self._lock:
            for row in answered.reset_rows:
                key = reset_keys[row]
                if key in self._routes:
                    self._routes[key] = dataclasses.replace(self._routes[key], state_id=int(state_ids[row]))
        finished = time.perf_counter()
        for batch in (reset_batch, step_batch):
            batch.submitted_at, batch.finished_at = submitted, finished
        errors = [r for r in results if isinstance(r, BaseException)]
        if errors:
            partial = (
                _take_rows(reset_batch, sorted(answered.reset_rows)),
                _take_rows(step_batch, sorted(answered.step_rows)),
            )
            raise call_error(errors, partial if pick is None else partial[pick])
        return reset_batch, step_batch

    def _fill(
        self,
        batch: StageBatch,
        answer: dict[str, Any],
        rows: np.ndarray,
        pod: str,
        check_tasks: bool,
        chunk: int | None = None,
    ) -> None:
        _fill_rows(batch.obs, answer.get("obs"), rows, "obs", pod)
        env_info = answer.get("env_info")
        if env_info:
            batch.env_info.append((rows, env_info))
        errors = answer.get("errors")
        if errors:
            row_of = {int(env): int(row) for env, row in zip(answer["env_ids"], rows)}
            for env, kind, message in zip(errors.get("env_ids", ()), errors.get("type", ()), errors.get("message", ())):
                if int(env) in row_of:
                    batch.errors.append((batch.traj_keys[row_of[int(env)]], str(kind), str(message)))
        info = answer.get("info") or {}
        _fill_rows(batch.success, info.get("success"), rows, "info.success", pod)
        if check_tasks:
            said = list(info.get("task_id") or [])
            expected = [batch.task_ids[r] for r in rows]
            if said != expected:
                raise PodRequestError(pod, None, f"reset envs run tasks {said}, the routing table says {expected}")
        else:
            _fill_rows(batch.reward, answer.get("reward"), rows, "reward", pod)
            _fill_rows(batch.terminated, answer.get("terminated"), rows, "terminated", pod)
            _fill_rows(batch.truncated, answer.get("truncated"), rows, "truncated", pod)
            if chunk is None:
                batch.num_steps[rows] = 1
            else:
                _fill_rows(batch.num_steps, answer.get("num_steps"), rows, "num_steps", pod)

    async def _post(
        self, pod: str, op: str, body: dict[str, Any], keys: list[str], extra_answer_bytes: int = 0
    ) -> dict[str, Any]:
        """POST to one pod with the current generation; after a 409, re-read routing and retry once."""
        generation = self._table.generation
        try:
            return await self._pods[pod].call(op, {"generation": generation, **body}, keys, extra_answer_bytes)
        except StaleGenerationError as stale:
            await self._refresh_after_stale(pod, generation, stale.detail, keys)
        try:
            body = {**body, "generation": self._table.generation}
            return await self._pods[pod].call(op, body, keys, extra_answer_bytes)
        except StaleGenerationError as stale:
            raise StaleGenerationError(pod, self._table.generation, stale.detail) from None

    async def _refresh_after_stale(self, pod: str, generation: int, detail: str, keys: list[str]) -> None:
        """Re-read the routing table once per generation; raise if ``keys`` (or others) lost their envs."""
        if self._refresh_lock is None:
            self._refresh_lock = asyncio.Lock()
        async with self._refresh_lock:
            if self._table.generation == generation:
                await self._adopt_new_routing(pod, generation, detail)
        with self._lock:
            lost = [key for key in keys if key in self._lost]
        if lost:
            raise RoutingChangedError(self._lost[lost[0]], lost)

    async def _controller_routing(self, timeout_s: float) -> RoutingTable:
        """The controller's routing table now.

        Raises:
            PodUnavailableError: the controller did not answer within ``timeout_s``.
            PodRequestError: it refused, or answered something that is not a routing table.
        """
        url = f"{self.controller_url}/v1/routing"
        try:
            async with asyncio.timeout(timeout_s), httpx.AsyncClient(timeout=timeout_s, trust_env=False) as http:
                answer = await http.send(http.build_request("GET", url), stream=True)
                content = await read_answer(answer, MAX_CONTROL_ANSWER_BYTES)
                response = httpx.Response(answer.status_code, content=content, request=answer.request)
        except (TimeoutError, httpx.HTTPError) as exc:
            raise PodUnavailableError({"controller": []}, f"GET {url}: {type(exc).__name__}: {exc}") from None
        return _read_routing(response, url)

    async def _adopt_new_routing(self, pod: str, generation: int, detail: str) -> None:
        if self.controller_url is None:
            raise StaleGenerationError(
                pod, generation, f"{detail} (no controller_url to re-read the routing table from)"
            )
        new = await self._controller_routing(self.timeout_s)
        logger.info(
            "pod %s answered 409 at generation %d; routing table now at generation %d", pod, generation, new.generation
        )
        with self._lock:
            moved = changed_routes(self._table, new, self._routes)
            self._table = new
            self._sync_pods()
            holders = sorted({r.pod for k, r in self._routes.items() if k not in moved})
        # Same blocks, new generation: the envs survived unless the pod built them anew (restart).
        infos = await asyncio.gather(*(self._pods[name].info() for name in holders), return_exceptions=True)
        with self._lock:
            for name, info in zip(holders, infos):
                if isinstance(info, BaseException):
                    continue  # an unreachable pod fails the retry itself, naming its trajectories
                before, now = self._instances.get(name), info.get("instance")
                if before is not None and now is not None and before != now:
                    moved.extend(k for k, r in self._routes.items() if r.pod == name)
                self._instances[name] = now
            for key in moved:
                del self._routes[key]
                self._lost[key] = new.generation
        if moved:
            logger.warning("routing generation %d: trajectories %s lost their envs", new.generation, moved)
