"""Re-reading the controller's routing table: before a new batch (so a reassignment finished
before it costs it nothing), and after a pod answers 409 (stale generation), finding the
trajectories whose envs went away. The table and the routes live in the route book; this module
is the I/O that keeps them current.
"""

from __future__ import annotations

import asyncio
import logging
import time
from typing import Any

import httpx

from vecsim.client.errors import ClientError, PodRequestError, PodUnavailableError, StaleGenerationError
from vecsim.client.jobinfo import JobInfo
from vecsim.client.pods import EventLoopThread, PodSet, refusal
from vecsim.client.routebook import RouteBook
from vecsim.client.routing import stage_by_id
from vecsim.config import RoutingTable
from vecsim.transport import MAX_CONTROL_ANSWER_BYTES, Transport, get_answer

# The client's one logger name: what it says about routing is found where users look for it.
logger = logging.getLogger("vecsim.client.stage")

__all__ = ["RoutingRefresher", "controller_routing", "fetch_routing"]


def _read_routing(status: int, content: bytes, url: str) -> RoutingTable:
    """The routing table in a controller's answer to ``GET /v1/routing``.

    Raises:
        PodRequestError: a refusal or an answer that is not a routing table.
    """
    if status != 200:
        raise PodRequestError("controller", status, content[:500].decode("utf-8", "replace"))
    try:
        return RoutingTable.model_validate_json(content)
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
                table = _read_routing(response.status_code, response.content, url)
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
        logger.log(
            level, "waiting for the controller at %s (%.0f s of %s s): %s", url, now - started, wait_ready_s, seen
        )
        time.sleep(min(pause, left))
        pause = min(pause * 2, _WAIT_MAX_S)


def read_pod_info(url: str, timeout_s: float) -> tuple[str, dict[str, Any]]:
    """A standalone pod's ``GET /v1/info`` answer, with its URL (no trailing slash).

    Raises:
        PodUnavailableError: the pod did not answer, or answered 503.
        PodRequestError: the pod refused, or its answer is not JSON.
    """
    try:
        response = get_answer(f"{url.rstrip('/')}/v1/info", timeout_s=timeout_s)
    except httpx.HTTPError as exc:
        raise PodUnavailableError({url: []}, f"GET /v1/info: {type(exc).__name__}: {exc}") from None
    if response.status_code != 200:
        raise refusal(url, response.status_code, response.content, [])
    try:
        return url.rstrip("/"), response.json()
    except ValueError as exc:
        raise PodRequestError(url, None, f"answer to /v1/info is not JSON: {exc}") from None


async def controller_routing(transport: Transport, controller_url: str, timeout_s: float) -> RoutingTable:
    """The controller's routing table now, read on the running loop through ``transport`` (the
    client's own, which its pods are reached through too).

    Raises:
        PodUnavailableError: the controller did not answer within ``timeout_s``.
        PodRequestError: it refused, or answered something that is not a routing table.
    """
    url = f"{controller_url}/v1/routing"
    try:
        async with asyncio.timeout(timeout_s):
            status, content = await transport.fetch("GET", url, (), b"", MAX_CONTROL_ANSWER_BYTES)
    except (TimeoutError, httpx.HTTPError) as exc:
        raise PodUnavailableError({"controller": []}, f"GET {url}: {type(exc).__name__}: {exc}") from None
    return _read_routing(status, content, url)


class RoutingRefresher:
    """Keeps a route book's table current from a controller (``controller_url`` None: no
    controller, the table in use stays and a 409 is a :class:`StaleGenerationError`).

    ``transport`` is the client's, which the table is read through. The client's
    :class:`~vecsim.client.pods.PodSet` comes with each re-read: its connections follow a new
    table, and it reads the pods' ``/v1/info``.
    """

    def __init__(
        self,
        book: RouteBook,
        info: JobInfo,
        controller_url: str | None,
        timeout_s: float,
        transport: Transport,
    ) -> None:
        self.book, self.info = book, info
        self.controller_url = controller_url
        self.timeout_s = timeout_s
        self._transport = transport
        self._lock: asyncio.Lock | None = None  # made on the loop, at the first 409

    def before_batch(self, loop: EventLoopThread, pods: PodSet) -> None:
        """Take the controller's table if it has moved on and is ready (the caller checked that no
        call is in flight). When the controller does not answer (within ``timeout_s``, 5 s at
        most), the table in use stays: the pods' 409 catch a stale one."""
        if self.controller_url is None:
            return
        try:
            new = loop.run(self._routing(min(self.timeout_s, _REFRESH_TIMEOUT_S)))
            stage_by_id(new)
            if new.generation == self.book.generation or not new.ready:
                return
            old = self.book.generation
            self.book.take_table(new)
        except (ClientError, ValueError) as exc:
            logger.warning(
                "routing table not re-read before a new batch (%s); placing it on generation %d",
                exc,
                self.book.generation,
            )
            return
        logger.info("routing table moved from generation %d to %d; new batches go there", old, new.generation)
        pods.sync()
        # The envs' builds now, so that a later 409 tells a rebuilt pod from a renumbered one.
        names = self.book.pods_with_envs()

        async def builds() -> list[Any]:
            return await asyncio.gather(*(pods[p].info() for p in names), return_exceptions=True)

        for pod, info in zip(names, loop.run(builds())):
            self.info.instances[pod] = None if isinstance(info, BaseException) else info.get("instance")

    async def _routing(self, timeout_s: float) -> RoutingTable:
        assert self.controller_url is not None
        return await controller_routing(self._transport, self.controller_url, timeout_s)

    async def after_stale(self, pods: PodSet, pod: str, generation: int, detail: str, keys: list[str]) -> None:
        """After ``pod`` answered 409 at ``generation``: re-read the table once per generation.

        Raises:
            StaleGenerationError: no controller to re-read from.
            RoutingChangedError: ``keys`` (some of them) lost their envs.
            PodUnavailableError, PodRequestError: the controller did not answer, or refused.
        """
        if self._lock is None:
            self._lock = asyncio.Lock()
        async with self._lock:
            if self.book.generation == generation:
                await self._take_new_routing(pods, pod, generation, detail)
        self.book.check_lost(keys)

    async def _take_new_routing(self, pods: PodSet, pod: str, generation: int, detail: str) -> None:
        if self.controller_url is None:
            raise StaleGenerationError(
                pod, generation, f"{detail} (no controller_url to re-read the routing table from)"
            )
        new = await self._routing(self.timeout_s)
        logger.info(
            "pod %s answered 409 at generation %d; routing table now at generation %d", pod, generation, new.generation
        )
        moved = self.book.take_table(new)
        pods.sync()
        holders = self.book.holders()
        # Same blocks, new generation: the envs survived unless the pod built them anew (restart).
        infos = await asyncio.gather(*(pods[name].info() for name in holders), return_exceptions=True)
        for name, info in zip(holders, infos):
            if isinstance(info, BaseException):
                continue  # an unreachable pod fails the retry itself, naming its trajectories
            before, now = self.info.instances.get(name), info.get("instance")
            if before is not None and now is not None and before != now:
                moved.extend(self.book.lose_pod(name))
            self.info.instances[name] = now
        if moved:
            logger.warning("routing generation %d: trajectories %s lost their envs", new.generation, moved)
