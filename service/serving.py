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
  sends its request at once;
- what one event-loop turn writes to a connection leaves in one write (:class:`CoalescingWrites`):
  uvicorn writes an answer's head and its body separately, two sends that make the client read
  twice, each a system call and, for the client, one more turn of its event loop per answer.

:func:`uvicorn_limits` gives the uvicorn keyword arguments for both.
"""

from __future__ import annotations

import asyncio
import logging
import resource
from typing import Any

from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

__all__ = ["CoalescingWrites", "bounded_protocol", "connection_limit", "uvicorn_limits"]

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


# Above this many bytes an answer's body is written apart from its head: joining them would copy
# the body, which costs more than the second send saves.
COALESCE_MAX_BYTES = 256 * 1024


class CoalescingWrites:
    """An ``asyncio.Transport`` in front of another that holds writes and hands them to it as one
    write on :meth:`flush` (the protocol calls it when an answer is complete), at the end of the
    event-loop turn they were made in at the latest (a ``100 Continue``, a streamed answer), and
    at once on ``close``, ``write_eof`` or when they pass :data:`COALESCE_MAX_BYTES`. Everything
    else goes straight to the transport it wraps; the order of the bytes never changes.
    """

    def __init__(self, transport: asyncio.Transport, loop: asyncio.AbstractEventLoop) -> None:
        self._transport = transport
        self._loop = loop
        self._held: list[bytes] = []
        self._held_bytes = 0

    def write(self, data: bytes | bytearray | memoryview) -> None:
        if not data:
            return
        if self._held_bytes + len(data) > COALESCE_MAX_BYTES:
            self.flush()
            self._transport.write(data)
            return
        if not self._held:
            self._loop.call_soon(self.flush)
        self._held.append(bytes(data))
        self._held_bytes += len(data)

    def writelines(self, list_of_data: Any) -> None:
        for data in list_of_data:
            self.write(data)

    def flush(self) -> None:
        """Hand what is held to the wrapped transport now (a no-op when nothing is)."""
        if not self._held:
            return
        held, self._held, self._held_bytes = self._held, [], 0
        if not self._transport.is_closing():
            self._transport.write(held[0] if len(held) == 1 else b"".join(held))

    def get_write_buffer_size(self) -> int:
        return self._transport.get_write_buffer_size() + self._held_bytes

    def write_eof(self) -> None:
        self.flush()
        self._transport.write_eof()

    def close(self) -> None:
        self.flush()
        self._transport.close()

    def abort(self) -> None:
        self._held, self._held_bytes = [], 0
        self._transport.abort()

    def __getattr__(self, name: str) -> Any:
        # is_closing, get_extra_info, pause_reading, resume_reading, set_protocol, ...
        return getattr(self._transport, name)


def bounded_protocol(header_timeout_s: float, max_connections: int) -> type[HttpToolsProtocol]:
    """uvicorn's httptools protocol with a request-head deadline, a bound on open connections and
    one write per answer (see the module docstring)."""

    class BoundedHttpToolsProtocol(HttpToolsProtocol):
        def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
            super().connection_made(CoalescingWrites(transport, self.loop))  # type: ignore[arg-type]
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
            # The answer is whole: its head and body leave now, as one write.
            self.transport.flush()  # type: ignore[attr-defined]
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
