"""JobClient: a client's connection to one job's pods, and what the pods said of the job.

The base of :class:`~vecsim.client.stage.StageClient`, which adds trajectories and stages. It
holds the event loop thread the calls run on, the transport, a connection per pod of the routing
table in use (:class:`~vecsim.client.pods.PodSet`), the table's re-read from the controller
(:class:`~vecsim.client.refresh.RoutingRefresher`) and the job as the pods' ``/v1/info``
describes it (:class:`~vecsim.client.jobinfo.JobInfo`: spaces, instructions, reset kinds, state
counts), read on first use.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Coroutine, Mapping
from typing import Any, TypeVar

import httpx
from gymnasium import Space
from gymnasium.error import ClosedEnvironmentError

from vecsim.auth import token_from_env
from vecsim.client.calls import PendingCall
from vecsim.client.jobinfo import JobInfo
from vecsim.client.pods import EventLoopThread, PodSet, check_limits
from vecsim.client.refresh import RoutingRefresher
from vecsim.client.routebook import RouteBook
from vecsim.config import RoutingTable
from vecsim.transport import as_transport

logger = logging.getLogger(__name__)

__all__ = ["JobClient"]

T = TypeVar("T")


class JobClient:
    """The pods of the job that ``routing`` routes to, reached over ``transport`` from an event
    loop thread of the client's own; the arguments are :class:`~vecsim.client.stage.StageClient`'s.
    """

    def __init__(
        self,
        routing: RoutingTable,
        *,
        controller_url: str | None,
        timeout_s: float,
        transport: httpx.AsyncBaseTransport | None,
        max_answer_bytes: int | None,
        token: str | None,
    ) -> None:
        """Start the loop thread and a connection per pod of ``routing`` (no request yet).

        Raises:
            ValueError: a ``timeout_s`` or ``max_answer_bytes`` that is not a positive number.
        """
        check_limits(timeout_s, max_answer_bytes)
        self._book = RouteBook(routing)
        self.controller_url = controller_url.rstrip("/") if controller_url else None
        self.timeout_s = float(timeout_s)
        self.max_answer_bytes = max_answer_bytes
        self._transport = as_transport(transport)
        self._info = JobInfo()
        self._closed = False
        self._loop = EventLoopThread()
        self._refresher = RoutingRefresher(self._book, self._info, self.controller_url, self.timeout_s, self._transport)
        self._pods = PodSet(
            self._book,
            self._info,
            self._refresher,
            self._transport,
            self.timeout_s,
            token if token is not None else token_from_env(),
            max_answer_bytes,
        )

    @property
    def routing(self) -> RoutingTable:
        """The routing table in use (re-read after a 409 when a controller is known)."""
        return self._book.table

    @property
    def observation_space(self) -> Space | None:
        """One env's observation space, read from the pods' ``/v1/info`` (None if no pod has envs)."""
        return self._job().observation_space

    @property
    def action_space(self) -> Space | None:
        """One env's action space as the pods take it (a Dict or Tuple one flattened), read from
        the pods' ``/v1/info`` (None if no pod has envs); :attr:`served_action_space`: the envs' own."""
        return self._job().action_space

    @property
    def served_action_space(self) -> Space | None:
        return self._job().served_action_space

    @property
    def instructions(self) -> dict[str, str]:
        """Each task's instruction, read from the pods' ``/v1/info``."""
        return dict(self._job().instructions)

    @property
    def reset_kinds(self) -> dict[str, str]:
        """How each task's envs reset by default, from the pods' ``/v1/info``: ``"seed"`` (the
        env's own seeded reset: a gym task without cameras) or ``"state_id"`` (fixed states)."""
        return dict(self._job().reset_kinds)

    @property
    def num_states(self) -> dict[str, int]:
        """How many fixed initial states each task has (state ids ``0..n-1``), from the pods'
        ``/v1/info``: the trainer needs no task registry of its own."""
        return dict(self._job().num_states)

    def submit(self, coro: Coroutine[Any, Any, T]) -> PendingCall[T]:
        """Run ``coro`` on the client's event loop and return its pending result.

        For chaining calls without a round trip through the caller: inside ``coro``, ``await``
        the client's calls (``await client.call(...)``).

        Raises:
            ClosedEnvironmentError: the client is closed.
        """
        self._check_open()
        return PendingCall(self._loop.submit(coro), loop=self._loop)

    def _check_open(self) -> None:
        if self._closed:
            raise ClosedEnvironmentError(f"the {type(self).__name__} is closed")

    def _job(self) -> JobInfo:
        """What the pods said of the job, read from their ``/v1/info`` on first use."""
        if self._info.spaces is None:
            self._check_open()
            if threading.current_thread() is self._loop.thread:
                raise RuntimeError("the pods' spaces must be read before calls are made from the client's loop")
            self._adopt_info(self._loop.run(self._pods.infos(self._book.pods_with_envs())))
        return self._info

    def _adopt_info(self, infos: Mapping[str, Mapping[str, Any]]) -> None:
        """Take instructions and spaces from pods' ``/v1/info`` answers (pods with envs only)."""
        self._info.adopt(infos)
        self._pods.sync()  # the answer caps follow from the spaces just read

    def _disconnect(self) -> None:
        """Close the transport (every pod connection) and the loop thread."""
        if self._loop.running:  # not so at interpreter exit, where daemon threads stop where they stand
            try:
                self._loop.run(self._transport.aclose(), timeout=min(self.timeout_s, 5.0))
            except (TimeoutError, RuntimeError) as exc:
                logger.warning("closing pod connections: %s", exc)
        self._loop.close()
