"""uvicorn as the pod and the controller run it: connections that send nothing are not kept.

uvicorn closes a kept-alive connection that stays idle (``timeout_keep_alive``), but not a new
connection that never sends a request, nor one whose request head never ends; and it accepts
connections until the process runs out of file descriptors, after which every new connection,
health probes included, is dropped. :func:`bounded_protocol` makes uvicorn's own protocol class
(httptools) do two more things:

- a request head must arrive whole within ``header_timeout_s`` of the connection opening (or of
  its first byte, on a kept-alive connection); else the connection is closed;
- at most ``max_connections`` connections are kept: one more arriving closes the connection idle
  longest (no request in progress), so a flood of silent sockets cannot lock out a probe that
  sends its request at once.

:func:`uvicorn_limits` gives the uvicorn keyword arguments for both.
"""

from __future__ import annotations

import asyncio
import logging
import resource
from typing import Any

from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

__all__ = ["bounded_protocol", "connection_limit", "uvicorn_limits"]

log = logging.getLogger(__name__)

# File descriptors a server keeps for itself (listening socket, logs, env workers' pipes and
# shared memory) before counting what connections may use.
_RESERVED_FDS_SHARE = 2


def connection_limit(wanted: int) -> int:
    """``wanted``, lowered to half the process's file-descriptor limit (the other half is for the
    server itself), at least 4."""
    soft, _hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft == resource.RLIM_INFINITY:
        return wanted
    return max(4, min(wanted, soft // _RESERVED_FDS_SHARE))


def bounded_protocol(header_timeout_s: float, max_connections: int) -> type[HttpToolsProtocol]:
    """uvicorn's httptools protocol with a request-head deadline and a bound on open connections
    (see the module docstring)."""

    class BoundedHttpToolsProtocol(HttpToolsProtocol):
        def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
            super().connection_made(transport)
            self._busy = False
            self._idle_since = self.loop.time()
            self._head_timer: asyncio.TimerHandle | None = None
            self._arm_head_timer()
            if len(self.connections) > max_connections:
                self._evict_idlest()

        def _arm_head_timer(self) -> None:
            if self._head_timer is None:
                self._head_timer = self.loop.call_later(header_timeout_s, self._head_timed_out)

        def _disarm_head_timer(self) -> None:
            if self._head_timer is not None:
                self._head_timer.cancel()
                self._head_timer = None

        def _head_timed_out(self) -> None:
            self._head_timer = None
            if not self.transport.is_closing():
                log.info("closing a connection from %s: no request head within %s s", self.client, header_timeout_s)
                self.transport.close()

        def _evict_idlest(self) -> None:
            idle = [c for c in self.connections if not getattr(c, "_busy", True) and not c.transport.is_closing()]
            if idle:
                victim = min(idle, key=lambda c: c._idle_since)
                log.warning("over %d connections: closing the one idle longest", max_connections)
                victim.transport.close()

        def on_message_begin(self) -> None:
            super().on_message_begin()
            self._busy = True
            self._arm_head_timer()

        def on_headers_complete(self) -> None:
            self._disarm_head_timer()
            super().on_headers_complete()

        def on_response_complete(self) -> None:
            self._busy = False
            self._idle_since = self.loop.time()
            super().on_response_complete()

        def connection_lost(self, exc: Exception | None) -> None:
            self._disarm_head_timer()
            super().connection_lost(exc)

    return BoundedHttpToolsProtocol


def uvicorn_limits(header_timeout_s: float, keep_alive_s: float, max_connections: int) -> dict[str, Any]:
    """uvicorn keyword arguments (``uvicorn.Config``/``uvicorn.run``) that bound idle and slow
    connections and their number (``max_connections`` lowered by :func:`connection_limit`)."""
    return {
        "http": bounded_protocol(header_timeout_s, connection_limit(max_connections)),
        "timeout_keep_alive": keep_alive_s,
    }
