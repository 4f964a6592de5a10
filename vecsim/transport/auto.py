"""Which :class:`~vecsim.transport.Transport` the client uses: the choice, in one place."""

from __future__ import annotations

from typing import Any, Literal

import httpx

from .base import Transport
from .httptools_impl import HttptoolsTransport
from .httpx_impl import HttpxTransport

__all__ = ["DEFAULT_KIND", "TransportKind", "as_transport", "make_async_client", "make_transport"]

TransportKind = Literal["httptools"]

# The one kind that reaches pods over sockets: it bounds every part of an answer (docs/api.md,
# "Transport"). httpx's own connections were the other kind until they failed the same tests.
DEFAULT_KIND: TransportKind = "httptools"


def make_transport(kind: TransportKind = DEFAULT_KIND) -> Transport:
    """A transport of ``kind``: ``"httptools"`` (:class:`HttptoolsTransport`).

    Raises:
        ValueError: unknown ``kind``.
    """
    if kind == "httptools":
        return HttptoolsTransport()
    raise ValueError(f"kind: {kind!r} is not one of 'httptools'")


def as_transport(transport: Transport | httpx.AsyncBaseTransport | None) -> Transport:
    """``transport`` as the client's interface: None is :func:`make_transport`'s default, a
    :class:`Transport` itself, an in-process httpx transport (``httpx.ASGITransport(app)``, ...)
    wrapped in :class:`HttpxTransport`.

    Raises:
        TypeError: ``transport`` is no httpx transport, or is ``httpx.AsyncHTTPTransport``
            (httpx's own connections do not bound a hostile answer; pass None instead).
    """
    if transport is None:
        return make_transport()
    if isinstance(transport, Transport):
        return transport
    if isinstance(transport, httpx.AsyncHTTPTransport):
        raise TypeError(
            "transport: httpx.AsyncHTTPTransport reaches pods without vecsim's bounds on an answer "
            "(chunks, junk left on a reused connection, an early 413); pass None for the default transport"
        )
    if isinstance(transport, httpx.AsyncBaseTransport):
        return HttpxTransport(transport)
    raise TypeError(f"transport must be an httpx.AsyncBaseTransport, got {type(transport).__name__}")


def make_async_client(
    transport: httpx.AsyncBaseTransport | None = None, *, timeout: float | None = None, **client_kwargs: Any
) -> httpx.AsyncClient:
    """An ``httpx.AsyncClient`` on ``transport`` (default: :func:`make_transport`'s).

    ``timeout`` bounds each phase httpx knows of (connect, read, write, pool) where the transport
    honours them; callers bound a whole request with ``asyncio.timeout``.
    """
    client_kwargs.setdefault("trust_env", False)
    return httpx.AsyncClient(
        transport=transport if transport is not None else make_transport(), timeout=timeout, **client_kwargs
    )
