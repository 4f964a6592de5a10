"""A :class:`~vecsim.transport.Transport` over an httpx transport that serves an app in-process:
``httpx.ASGITransport(app)``, a pod served in the test's own process (tests, notebooks). The
request is handed straight to the wrapped transport, with no ``httpx.AsyncClient`` around it: a
pod's calls use none of what a client adds (redirects, auth, cookies, hooks), and it costs client
CPU on every call.

Sockets are :class:`~vecsim.transport.HttptoolsTransport`'s: httpx's own connections
(``httpx.AsyncHTTPTransport``) reuse a connection with junk left on it, read an early 413 as a
failed write, and bound neither the chunks of an answer nor its cost (docs/api.md, "Transport").
"""

from __future__ import annotations

import httpx

from .answers import read_answer
from .base import Transport

__all__ = ["HttpxTransport"]


class HttpxTransport(Transport):
    """:meth:`fetch` through ``transport`` (an in-process one: ``httpx.ASGITransport(app)``);
    closing this closes it."""

    def __init__(self, transport: httpx.AsyncBaseTransport) -> None:
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
