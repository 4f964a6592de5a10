"""How the client reaches pods: one transport, on one background event loop.

The client code above this module sees three calls per pod (``info``, ``reset``, ``step``) and
three outcomes besides an answer: :class:`~vecsim.client.errors.PodUnavailableError` (no usable
answer in time: whatever went wrong on the way, in the connection, the HTTP, the size or the
encoding of the answer), :class:`~vecsim.client.errors.StaleGenerationError` (409, the caller re-reads the routing table) and
:class:`~vecsim.client.errors.PodRequestError` (the pod refused the request, or its answer is not
the one asked for). Which transport carries the bytes is the caller's choice
(``vecsim.transport``).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import json
import logging
import math
import sys
import threading
import time
import uuid
from collections.abc import Callable, Coroutine
from typing import TYPE_CHECKING, Any, TypeVar

import httpx
import numpy as np

import vecsim
from vecsim import wire
from vecsim.auth import bearer_headers
from vecsim.client.errors import PodRequestError, PodUnavailableError, StaleGenerationError
from vecsim.client.jobinfo import JobInfo
from vecsim.client.routebook import RouteBook
from vecsim.transport import DEFAULT_MAX_ANSWER_BYTES, Transport
from vecsim.transport.httptools_impl import IDEMPOTENCY_KEY

if TYPE_CHECKING:
    from vecsim.client.refresh import RoutingRefresher

logger = logging.getLogger(__name__)

T = TypeVar("T")


class EventLoopThread:
    """An asyncio event loop running in a daemon thread, so sync code can keep calls in flight.

    A call submitted here can be cancelled from any thread, and :meth:`cancel` waits until the
    coroutine has actually ended on the loop (its ``finally`` blocks run, its requests aborted),
    so whatever the caller does next starts after it.
    """

    def __init__(self, name: str = "vecsim-client") -> None:
        self.loop = asyncio.new_event_loop()
        # The task running each submitted call, by its future; touched on the loop only.
        self._tasks: dict[concurrent.futures.Future[Any], asyncio.Task[Any]] = {}
        self.thread = threading.Thread(target=self.loop.run_forever, name=name, daemon=True)
        self.thread.start()

    @property
    def running(self) -> bool:
        """Whether the loop's thread can still run calls: not after :meth:`close`, nor at
        interpreter exit, where daemon threads stop where they stand."""
        return self.thread.is_alive() and not self.loop.is_closed() and not sys.is_finalizing()

    def submit(self, coro: Coroutine[Any, Any, T]) -> concurrent.futures.Future[T]:
        """Schedule ``coro`` on the loop; return a future of its result. Cancelling the future
        cancels the coroutine (without waiting for it: see :meth:`cancel`)."""
        future: concurrent.futures.Future[T] = concurrent.futures.Future()

        def start() -> None:
            if future.cancelled():  # cancelled before it started: it never runs
                coro.close()
                return
            task = self.loop.create_task(coro)
            self._tasks[future] = task
            task.add_done_callback(lambda _task: self._finish(future, task))

        def stop_task() -> None:
            task = self._tasks.get(future)
            if task is not None:
                task.cancel()

        def on_done(done: concurrent.futures.Future[T]) -> None:
            if done.cancelled() and not self.loop.is_closed():
                self.loop.call_soon_threadsafe(stop_task)

        future.add_done_callback(on_done)
        self.loop.call_soon_threadsafe(start)
        return future

    def _finish(self, future: concurrent.futures.Future[T], task: asyncio.Task[T]) -> None:
        """Hand a finished task's outcome to its future (on the loop)."""
        self._tasks.pop(future, None)
        if task.cancelled():
            future.cancel()
            return
        if not future.set_running_or_notify_cancel():  # the caller cancelled it first
            return
        exc = task.exception()
        if exc is not None:
            future.set_exception(exc)
        else:
            future.set_result(task.result())

    def cancel(self, future: concurrent.futures.Future[Any], timeout: float = 5.0) -> None:
        """Cancel the call behind ``future`` and wait (up to ``timeout`` s) until its coroutine
        has ended on the loop. A call that already ended is left as it is."""
        future.cancel()
        if threading.current_thread() is self.thread or not self.running:
            return

        try:
            # Runs after the call's start and its cancellation: the loop takes callbacks in order.
            self.submit(self.ended(future)).result(timeout)
        except TimeoutError:
            logger.warning("a cancelled call did not end within %s s; going on without it", timeout)

    async def ended(self, future: concurrent.futures.Future[Any]) -> None:
        """Return once the coroutine behind ``future`` has ended (await it on the loop)."""
        task = self._tasks.get(future)
        if task is not None:
            await asyncio.wait([task])

    def run(self, coro: Coroutine[Any, Any, T], timeout: float | None = None) -> T:
        """Run ``coro`` on the loop and return its result (raises what it raises). Interrupted
        (Ctrl-C) or out of ``timeout``, the coroutine is cancelled before the error goes on."""
        future = self.submit(coro)
        try:
            return future.result(timeout)
        except BaseException:
            if not future.done():
                self.cancel(future)
            raise

    def close(self, timeout: float = 5.0) -> None:
        """Stop the loop and join its thread; safe to call twice, and a no-op where the thread
        can no longer run (at interpreter exit, daemon threads are stopped where they stand).

        A loop that does not stop within ``timeout`` seconds (its thread held up in a callback) is
        left to its daemon thread, with a warning, rather than waited for: closing must not hang
        a trainer's exit, Ctrl-C's included. Closing again once that thread has ended closes it.
        """
        if self.loop.is_closed():
            return
        if threading.current_thread() is self.thread:
            self.loop.stop()  # the loop cannot be closed from inside; its thread ends
            return
        if sys.is_finalizing():
            return
        if self.thread.is_alive():
            self.loop.call_soon_threadsafe(self.loop.stop)
            self.thread.join(timeout)
            if self.thread.is_alive():
                logger.warning(
                    "the client's event loop did not stop within %s s; leaving it to its daemon thread", timeout
                )
                return
        self.loop.close()


def new_idempotency_key() -> str:
    """A new ``Idempotency-Key``: one per logical reset or step call to one pod."""
    return uuid.uuid4().hex


def _detail(status: int, content: bytes) -> str:
    """What a refusal says: its JSON ``detail``, else the start of its body or its status's phrase."""
    try:
        body = json.loads(content)
    except ValueError:
        return content.decode("utf-8", errors="replace")[:500] or httpx.codes.get_reason_phrase(status)
    if isinstance(body, dict) and "detail" in body:
        return str(body["detail"])
    return str(body)[:500]


def refusal(pod: str, status: int, content: bytes, held: list[str], generation: int | None = None) -> Exception:
    """The client's error for a pod's answer other than 200, decided here alone: a 409 to a
    request that carried ``generation`` is a :class:`StaleGenerationError`, a 503 (envs not
    built, the pod restarting) a :class:`PodUnavailableError` naming ``held``, and any other a
    :class:`PodRequestError` naming the status and the answer's detail."""
    if status == 409 and generation is not None:
        return StaleGenerationError(pod, generation, _detail(status, content))
    if status == 503:
        return PodUnavailableError({pod: held}, f"503: {_detail(status, content)}")
    return PodRequestError(pod, status, _detail(status, content))


# Headers every request to a pod carries besides its own: the Content-Encodings read_answer decodes.
_BASE_HEADERS = {"Accept-Encoding": "gzip, deflate", "User-Agent": f"vecsim/{vecsim.__version__}"}


class PodConnection:
    """One pod's data plane: ``POST /v1/reset``, ``POST /v1/step`` in wire format, ``GET /v1/info``.

    Lives on the client's event loop and hands each request straight to ``transport`` (a
    :class:`vecsim.transport.Transport`, shared by all pods: its ``fetch``), its URLs
    and headers built once per pod. Every call, answer included, is bounded by
    ``timeout_s`` as a whole, and an answer by ``max_answer_bytes`` (the client sets it from the
    job's spaces). Resets and steps carry the job's ``token`` (``Authorization: Bearer``) when one
    is given.
    """

    def __init__(
        self,
        name: str,
        url: str,
        transport: Transport,
        timeout_s: float,
        token: str | None = None,
        max_answer_bytes: int = DEFAULT_MAX_ANSWER_BYTES,
    ) -> None:
        self.name = name
        self.url = url.rstrip("/")
        self.timeout_s = timeout_s
        self.max_answer_bytes = max_answer_bytes
        self._transport = transport
        auth = bearer_headers(token)
        self._info_headers = tuple(_BASE_HEADERS.items())
        self._wire_headers = tuple(
            {**_BASE_HEADERS, "Content-Type": wire.CONTENT_TYPE, "Accept": wire.CONTENT_TYPE, **auth}.items()
        )
        self._json_headers = tuple(
            {**_BASE_HEADERS, "Content-Type": "application/json", "Accept": "application/json", **auth}.items()
        )

    async def _request(
        self,
        method: str,
        path: str,
        held: list[str],
        headers: tuple[tuple[str, str], ...],
        body: bytes = b"",
        extra_answer_bytes: int = 0,
    ) -> tuple[int, bytes]:
        """Send one request and read its answer
        whole, within the timeout and the size cap (``max_answer_bytes``, plus
        ``extra_answer_bytes`` for what this request asks for beyond one observation per env:
        per-action flags and recorded frames of a chunk).

        Returns:
            the answer's status code and its body, decoded.

        Raises:
            PodUnavailableError: anything that kept a usable answer from arriving.
        """
        try:
            # asyncio.timeout, not wait_for: wait_for wraps every request in a task of its own.
            async with asyncio.timeout(self.timeout_s):
                max_bytes = self.max_answer_bytes + extra_answer_bytes
                return await self._transport.fetch(method, self.url + path, headers, body, max_bytes)
        except TimeoutError:
            reason = f"{method} {path} at {self.url}: TimeoutError: no answer within {self.timeout_s} s"
            raise PodUnavailableError({self.name: held}, reason) from None
        except Exception as exc:  # noqa: BLE001 - whatever broke the exchange, it is this pod's failure alone
            reason = f"{method} {path} at {self.url}: {type(exc).__name__}: {exc}".rstrip(": ")
            raise PodUnavailableError({self.name: held}, reason) from None

    async def info(self) -> dict[str, Any]:
        """Return the pod's ``GET /v1/info`` answer.

        Raises:
            PodUnavailableError, PodRequestError.
        """
        status, content = await self._request("GET", "/v1/info", [], self._info_headers)
        if status != 200:
            raise refusal(self.name, status, content, [])
        try:
            info = json.loads(content)
        except ValueError as exc:
            raise PodRequestError(self.name, None, f"answer to /v1/info is not JSON: {exc}") from None
        if not isinstance(info, dict):
            raise PodRequestError(self.name, None, "answer to /v1/info is not a JSON object")
        return info

    async def call_json(self, op: str, body: dict[str, Any], held: list[str]) -> dict[str, Any]:
        """POST ``body`` to ``/v1/<op>`` as JSON and return the JSON answer (the attribute
        endpoints, whose results are JSON values of any shape).

        Raises:
            ValueError: ``body`` is not JSON (NaN, infinity, an object JSON has no form for).
            PodUnavailableError: no usable answer (none in time, a 503, not a JSON object).
            PodRequestError: any other refusal (a 409 included: the caller re-reads nothing here).
        """
        try:
            text = json.dumps(body, ensure_ascii=False, separators=(",", ":"), allow_nan=False).encode()
        except (TypeError, ValueError) as exc:  # the caller's values, before anything is sent
            raise ValueError(f"/v1/{op}: the values are not JSON ({exc}); attributes take JSON values only") from None
        # Attribute results (a render() frame, say) are not sized by the observation space the cap
        # follows from: they may take the default cap.
        extra = max(0, DEFAULT_MAX_ANSWER_BYTES - self.max_answer_bytes)
        status, content = await self._request("POST", f"/v1/{op}", held, self._json_headers, text, extra)
        if status != 200:
            raise refusal(self.name, status, content, held)
        try:
            answer = json.loads(content)
        except ValueError as exc:
            raise PodUnavailableError({self.name: held}, f"answer to /v1/{op} is not JSON: {exc}") from None
        if not isinstance(answer, dict):
            raise PodUnavailableError({self.name: held}, f"answer to /v1/{op} is not a JSON object")
        return answer

    async def call(
        self,
        op: str,
        body: dict[str, Any],
        held: list[str],
        extra_answer_bytes: int = 0,
        idempotency_key: str | None = None,
    ) -> dict[str, Any]:
        """POST ``body`` to ``/v1/<op>`` in wire format and return the decoded answer.

        ``held`` names the traj_keys this call carries, for the error if the pod is unavailable;
        ``extra_answer_bytes`` raises the answer's cap for this call (see ``_request``). The
        request carries ``idempotency_key`` (a new one when None) as its ``Idempotency-Key``:
        the pod applies it at most once, and answers a re-send of it from memory.

        Raises:
            PodUnavailableError: no usable answer: none within the timeout, a 503 (envs not
                built), or a 200 whose body is not valid wire or not for the env ids asked.
            StaleGenerationError: 409, the pod holds another generation than the request carried.
            PodRequestError: any other refusal (the request was at fault).
        """
        headers = (*self._wire_headers, (IDEMPOTENCY_KEY, idempotency_key or new_idempotency_key()))
        status, content = await self._request("POST", f"/v1/{op}", held, headers, wire.encode(body), extra_answer_bytes)
        if status != 200:
            raise refusal(self.name, status, content, held, body.get("generation"))
        # A broken answer is this pod's failure alone, like no answer: its envs' state is unknown.
        try:
            answer = wire.decode(content)
        except wire.WireError as exc:
            raise PodUnavailableError({self.name: held}, f"answer to /v1/{op} is not valid wire: {exc}") from None
        if not isinstance(answer, dict):
            raise PodUnavailableError({self.name: held}, f"answer to /v1/{op} is not a mapping")
        sent = np.asarray(body["env_indices"])
        got = np.asarray(answer.get("env_indices", ()))
        if got.shape != sent.shape or not np.array_equal(got, sent):
            raise PodUnavailableError(
                {self.name: held}, f"answer to /v1/{op} is for env ids {got.tolist()}, asked {sent.tolist()}"
            )
        return answer


def check_limits(timeout_s: float, max_answer_bytes: int | None) -> None:
    """Raises ``ValueError``: ``timeout_s`` not a positive number, or ``max_answer_bytes`` (when
    given) under 1."""
    if not (timeout_s > 0 and math.isfinite(timeout_s)):
        raise ValueError(f"timeout_s must be a positive number, got {timeout_s}")
    if max_answer_bytes is not None and max_answer_bytes < 1:
        raise ValueError(f"max_answer_bytes must be a positive number of bytes, got {max_answer_bytes}")


class PodSet:
    """One :class:`PodConnection` per pod of the route book's table, and the one way a call
    reaches a pod: :meth:`post`, at the table's generation.

    ``refresher`` (a :class:`~vecsim.client.refresh.RoutingRefresher`) re-reads the table after a
    409; each connection's answer cap follows from ``info``'s spaces (``max_answer_bytes``, when
    given, caps every pod alike). ``observe``, when set, is told ``(pod, op, begin, end)``
    (``time.perf_counter()``) of every :meth:`post`: benchmarks time each pod's round trip by it.
    """

    def __init__(
        self,
        book: RouteBook,
        info: JobInfo,
        refresher: RoutingRefresher,
        transport: Transport,
        timeout_s: float,
        token: str | None,
        max_answer_bytes: int | None,
    ) -> None:
        self.book, self.info, self.refresher = book, info, refresher
        self.timeout_s = timeout_s
        self.max_answer_bytes = max_answer_bytes
        self.observe: Callable[[str, str, float, float], None] | None = None
        self._transport = transport
        self._token = token
        self._connections: dict[str, PodConnection] = {}
        self._lock = threading.RLock()
        self.sync()

    def __getitem__(self, pod: str) -> PodConnection:
        return self._connections[pod]

    def sync(self) -> None:
        """Make one connection per pod of the table (a pod whose URL changed gets a new one), each
        with its answer cap (runs on the caller's thread and on the loop)."""
        with self._lock:
            table = self.book.table
            # A pod of several stages ('slices') answers at most all its envs, whatever the stage.
            envs: dict[str, int] = {}
            for stage in table.stages:
                for routed in stage.pods:
                    envs[routed.pod] = envs.get(routed.pod, 0) + routed.num_envs
            for stage in table.stages:
                for routed in stage.pods:
                    known = self._connections.get(routed.pod)
                    if known is None or known.url != routed.url.rstrip("/"):
                        self._connections[routed.pod] = PodConnection(
                            routed.pod, routed.url, self._transport, self.timeout_s, self._token
                        )
                    self._connections[routed.pod].max_answer_bytes = self.info.answer_cap(
                        envs[routed.pod], self.max_answer_bytes
                    )

    async def infos(self, pods: list[str]) -> dict[str, dict[str, Any]]:
        """The ``/v1/info`` answers of ``pods``, read concurrently.

        Raises:
            PodUnavailableError, PodRequestError: as :meth:`PodConnection.info`.
        """
        answers = await asyncio.gather(*(self[pod].info() for pod in pods))
        return dict(zip(pods, answers))

    async def post(
        self, pod: str, op: str, body: dict[str, Any], keys: list[str], extra_answer_bytes: int = 0
    ) -> dict[str, Any]:
        """POST to one pod with the current generation; after a 409, re-read routing and retry once.

        Raises:
            what :meth:`PodConnection.call` raises; ``StaleGenerationError`` for a second 409;
            what the refresher's ``after_stale`` raises (``RoutingChangedError``: ``keys`` moved).
        """
        begin = time.perf_counter()
        try:
            return await self._post(pod, op, body, keys, extra_answer_bytes)
        finally:
            if self.observe is not None:
                self.observe(pod, op, begin, time.perf_counter())

    async def _post(
        self, pod: str, op: str, body: dict[str, Any], keys: list[str], extra_answer_bytes: int
    ) -> dict[str, Any]:
        generation = self.book.generation
        key = new_idempotency_key()  # one call: the same key after a 409, the pod answers it once
        try:
            return await self[pod].call(op, {"generation": generation, **body}, keys, extra_answer_bytes, key)
        except StaleGenerationError as stale:
            await self.refresher.after_stale(self, pod, generation, stale.detail, keys)
        try:
            body = {**body, "generation": self.book.generation}
            return await self[pod].call(op, body, keys, extra_answer_bytes, key)
        except StaleGenerationError as stale:
            raise StaleGenerationError(pod, self.book.generation, stale.detail) from None
