"""Which :class:`~vecsim.transport.Transport` the client uses: the choice, in one place."""

from __future__ import annotations

from typing import Any, Literal

import httpx

from .base import Transport
from .httptools_impl import HttptoolsTransport
from .httpx_impl import HttpxTransport

__all__ = ["DEFAULT_KIND", "TransportKind", "as_transport", "make_async_client", "make_transport"]

TransportKind = Literal["httptools", "httpx"]

# The kind bench/bench_transport.py measured fastest on a pod's answers (docs/api.md, "Transport").
DEFAULT_KIND: TransportKind = "httptools"


def make_transport(kind: TransportKind = DEFAULT_KIND) -> Transport:
    """A transport of ``kind``: ``"httptools"`` (:class:`HttptoolsTransport`) or ``"httpx"``
    (:class:`HttpxTransport` over httpx's own connections, environment proxies ignored: pods are
    reached directly).

    Raises:
        ValueError: unknown ``kind``.
    """
    if kind == "httptools":
        return HttptoolsTransport()
    if kind == "httpx":
        return HttpxTransport()
    raise ValueError(f"kind: {kind!r} is not one of 'httptools', 'httpx'")


def as_transport(transport: Transport | httpx.AsyncBaseTransport | None) -> Transport:
    """``transport`` as the client's interface: None is :func:`make_transport`'s default, a
    :class:`Transport` itself, any other httpx transport (``httpx.ASGITransport(app)``, ...)
    wrapped in :class:`HttpxTransport`.

    Raises:
        TypeError: ``transport`` is no httpx transport.
    """
    if transport is None:
        return make_transport()
    if isinstance(transport, Transport):
        return transport
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
