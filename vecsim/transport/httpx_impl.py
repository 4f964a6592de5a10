"""A :class:`~vecsim.transport.Transport` over any httpx transport: ``httpx.AsyncHTTPTransport``
(httpx's own connections) or ``httpx.ASGITransport(app)`` (a pod served in-process, as tests and
notebooks do). The request is handed straight to the wrapped transport, with no
``httpx.AsyncClient`` around it: a pod's calls use none of what a client adds (redirects, auth,
cookies, hooks), and it costs client CPU on every call.
"""

from __future__ import annotations

import httpx

from .answers import read_answer
from .base import KEEPALIVE_S, Transport

__all__ = ["HttpxTransport"]


class HttpxTransport(Transport):
    """:meth:`fetch` through ``transport`` (default: ``httpx.AsyncHTTPTransport`` with
    environment proxies ignored, idle connections kept ``keepalive_s``); closing this closes it."""

    def __init__(self, transport: httpx.AsyncBaseTransport | None = None, *, keepalive_s: float = KEEPALIVE_S) -> None:
        if transport is None:
            limits = httpx.Limits(max_connections=None, max_keepalive_connections=None, keepalive_expiry=keepalive_s)
            transport = httpx.AsyncHTTPTransport(limits=limits, trust_env=False)
        self.wrapped = transport

    async def handle_async_request(self, request: httpx.Request) -> httpx.Response:
        return await self.wrapped.handle_async_request(request)

    async def fetch(
        self, method: str, url: str, headers: tuple[tuple[str, str], ...], body: bytes, max_bytes: int
    ) -> tuple[int, bytes]:
        """As :meth:`Transport.fetch`; an empty body goes without a Content-Length (httpx's rule)."""
        request = httpx.Request(method, url, headers=list(headers), content=body or None)
        response = await self.wrapped.handle_async_request(request)
        response.request = request
        return response.status_code, await read_answer(response, max_bytes)

    async def aclose(self) -> None:
        await self.wrapped.aclose()
