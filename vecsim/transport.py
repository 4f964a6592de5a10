"""How the client's bytes reach a pod: httpx's API over a maintained HTTP library.

The client speaks httpx's transport interface and takes any ``httpx.AsyncBaseTransport``:
``httpx.ASGITransport(app)`` runs a pod in-process, ``httpx.AsyncHTTPTransport`` is httpx's own,
:class:`AiohttpTransport` puts aiohttp's client under httpx's API, and
:class:`~vecsim.http1.HttptoolsTransport` is HTTP/1.1 connections parsed by httptools.
:func:`make_transport` builds the default, :data:`DEFAULT_KIND`, the one ``bench/bench_transport.py``
measured fastest on vecsim's answers (docs/benchmarks.md). A pod's requests go straight to the
transport (:func:`fetch`: the transport's own lean path where it has one, else :func:`exchange`);
:func:`make_async_client` puts an ``httpx.AsyncClient`` over one for the rest.

Answers are streamed, never read whole by the transport: :func:`read_answer` reads one under a
size cap (a Content-Length over the cap is refused before a byte of body is read; a body that
grows past it is dropped as soon as it does) and decodes a gzip or deflate Content-Encoding once,
a bounded piece at a time, so a compressed bomb stops at the cap without holding the event loop.
Failures surface as httpx exceptions (:class:`AnswerTooLargeError` is an ``httpx.DecodingError``).
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator
from typing import Any, Literal

import aiohttp
import httpx
from yarl import URL

from vecsim.answers import AnswerReader, AnswerTooLargeError
from vecsim.http1 import KEEPALIVE_S, HttptoolsTransport

__all__ = [
    "DEFAULT_KIND",
    "DEFAULT_MAX_ANSWER_BYTES",
    "MAX_CONTROL_ANSWER_BYTES",
    "AiohttpTransport",
    "AnswerTooLargeError",
    "TransportKind",
    "make_async_client",
    "exchange",
    "fetch",
    "get_answer",
    "make_transport",
    "read_answer",
    "send_capped",
]

TransportKind = Literal["httptools", "aiohttp", "httpx"]

# The transport bench/bench_transport.py measured fastest on a pod's answers (docs/benchmarks.md).
DEFAULT_KIND: TransportKind = "httptools"

# The cap on one answer when nothing better is known (before a job's spaces are read).
DEFAULT_MAX_ANSWER_BYTES = 64 << 20
# The cap on a JSON answer of the control plane (a routing table, a pod's /v1/info): a job of
# thousands of pods and tasks stays far below it.
MAX_CONTROL_ANSWER_BYTES = 16 << 20

# aiohttp's read buffer: bodies of megabytes move in fewer, larger pieces.
_READ_BUFSIZE = 1 << 20
# URLs (and timeout settings) an AiohttpTransport keeps converted: a client's pods' paths.
_CACHED_URLS = 1024


class _AiohttpBody(httpx.AsyncByteStream):
    """An aiohttp response body as httpx's stream: pieces as they arrive, aiohttp's errors as httpx's."""

    def __init__(self, response: aiohttp.ClientResponse, request: httpx.Request) -> None:
        self._response = response
        self._request = request

    async def __aiter__(self) -> AsyncIterator[bytes]:
        try:
            async for piece in self._response.content.iter_any():
                yield piece
        except aiohttp.ClientError as exc:
            raise _httpx_error(exc, self._request) from None

    async def aclose(self) -> None:
        self._response.release()


def _httpx_error(exc: Exception, request: httpx.Request) -> httpx.HTTPError:
    """The httpx exception that says what aiohttp's ``exc`` says."""
    where = f"{request.method} {request.url}"
    if isinstance(exc, aiohttp.ConnectionTimeoutError):
        return httpx.ConnectTimeout(f"{where}: {exc}", request=request)
    if isinstance(exc, aiohttp.ServerTimeoutError):
        return httpx.ReadTimeout(f"{where}: {exc or 'timed out'}", request=request)
    if isinstance(exc, aiohttp.ClientConnectorError):
        return httpx.ConnectError(f"{where}: {exc}", request=request)
    if isinstance(exc, aiohttp.InvalidURL):
        return httpx.UnsupportedProtocol(f"{where}: {exc}", request=request)
    if isinstance(exc, (aiohttp.ServerDisconnectedError, aiohttp.ClientPayloadError, aiohttp.ClientResponseError)):
        return httpx.RemoteProtocolError(f"{where}: {type(exc).__name__}: {exc}", request=request)
    return httpx.ReadError(f"{where}: {type(exc).__name__}: {exc}", request=request)


class AiohttpTransport(httpx.AsyncBaseTransport):
    """aiohttp's client behind httpx's transport interface.

    The response's body is left unread and undecoded (``auto_decompress`` off): it streams to
    whoever reads the httpx response. httpx's ``connect`` and ``read`` timeouts map to aiohttp's
    ``sock_connect`` and ``sock_read`` (each read, as in httpx); aiohttp has no write or pool
    timeout, so callers bound a whole request with ``asyncio.timeout``. uvicorn speaks HTTP/1.1 only, so each call in flight
    holds a connection: ``max_connections`` bounds them in all (``None``: no bound; the client
    bounds its calls itself). The session is made on first use, on the loop that uses it.
    """

    def __init__(self, *, max_connections: int | None = None) -> None:
        self._max_connections = max_connections
        self._session: aiohttp.ClientSession | None = None
        # What each request would otherwise convert anew: a client talks to a few URLs with one
        # set of timeouts (both bounded all the same).
        self._urls: dict[str, URL] = {}
        self._timeouts: dict[tuple[float | None, float | None], aiohttp.ClientTimeout] = {}

    def _get_session(self) -> aiohttp.ClientSession:
        if self._session is None:
            connector = aiohttp.TCPConnector(
                limit=self._max_connections or 0, limit_per_host=0, keepalive_timeout=KEEPALIVE_S
            )
            self._session = aiohttp.ClientSession(
                connector=connector,
                auto_decompress=False,
                read_bufsize=_READ_BUFSIZE,
                cookie_jar=aiohttp.DummyCookieJar(),
                timeout=aiohttp.ClientTimeout(total=None),
                # The request's own headers go as they are: aiohttp adds none of these.
                skip_auto_headers=("User-Agent", "Accept", "Accept-Encoding", "Content-Type"),
            )
        return self._session

    def _url(self, url: httpx.URL) -> URL:
        """``url`` as yarl's, parsed once per URL (the last :data:`_CACHED_URLS` of them)."""
        text = str(url)
        parsed = self._urls.get(text)
        if parsed is None:
            if len(self._urls) >= _CACHED_URLS:
                self._urls.clear()
            parsed = self._urls[text] = URL(text, encoded=True)
        return parsed

    def _timeout(self, phases: dict[str, float | None]) -> aiohttp.ClientTimeout:
        key = (phases.get("connect"), phases.get("read"))
        timeout = self._timeouts.get(key)
        if timeout is None:
            if len(self._timeouts) >= _CACHED_URLS:
                self._timeouts.clear()
            timeout = self._timeouts[key] = aiohttp.ClientTimeout(total=None, sock_connect=key[0], sock_read=key[1])
        return timeout

    async def handle_async_request(self, request: httpx.Request) -> httpx.Response:
        """Send ``request`` through aiohttp.

        Returns:
            the response with its status and headers; its body streams on reading.

        Raises:
            httpx.ConnectError, httpx.ConnectTimeout, httpx.RemoteProtocolError, httpx.ReadError,
            httpx.UnsupportedProtocol: what aiohttp met, as httpx names it.
        """
        timeout = self._timeout(request.extensions.get("timeout", {}))
        # Whole here (a request made with content= is read already): aiohttp sends it with its
        # own Content-Length, never chunked.
        body = await request.aread()
        headers = [
            (k.decode("latin-1"), v.decode("latin-1"))
            for k, v in request.headers.raw
            if k.lower() not in (b"transfer-encoding", b"content-length")
        ]
        try:
            response = await self._get_session().request(
                request.method,
                self._url(request.url),
                headers=headers,
                data=body or None,
                allow_redirects=False,
                timeout=timeout,
            )
        except aiohttp.ClientError as exc:
            raise _httpx_error(exc, request) from None
        return httpx.Response(
            response.status,
            headers=list(response.raw_headers),
            stream=_AiohttpBody(response, request),
            extensions={
                "http_version": f"HTTP/{response.version.major}.{response.version.minor}".encode(),
                "reason_phrase": (response.reason or "").encode("latin-1"),
            },
        )

    async def aclose(self) -> None:
        """Close the aiohttp session and its connections."""
        if self._session is not None:
            await self._session.close()
            self._session = None


def make_transport(kind: TransportKind = DEFAULT_KIND) -> httpx.AsyncBaseTransport:
    """A transport of ``kind``: ``"httptools"`` (:class:`~vecsim.http1.HttptoolsTransport`),
    ``"aiohttp"`` (:class:`AiohttpTransport`) or ``"httpx"`` (``httpx.AsyncHTTPTransport``,
    environment proxies ignored: pods are reached directly).

    Raises:
        ValueError: unknown ``kind``.
    """
    if kind == "httptools":
        return HttptoolsTransport()
    if kind == "aiohttp":
        return AiohttpTransport()
    if kind == "httpx":
        limits = httpx.Limits(max_connections=None, max_keepalive_connections=None, keepalive_expiry=KEEPALIVE_S)
        return httpx.AsyncHTTPTransport(limits=limits, trust_env=False)
    raise ValueError(f"kind: {kind!r} is not one of 'httptools', 'aiohttp', 'httpx'")


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


async def read_answer(response: httpx.Response, max_bytes: int) -> bytes:
    """Read a streamed response's body, decoded, refusing more than ``max_bytes`` of it.

    The body is read raw (``aiter_raw``) and a gzip or deflate Content-Encoding decoded here,
    once, at most a MiB per step with the event loop free between steps. The response is closed
    on return or error.

    Returns:
        the decoded body.

    Raises:
        AnswerTooLargeError: Content-Length, the bytes received or the decoded bytes exceed
            ``max_bytes``.
        httpx.DecodingError: an unreadable Content-Length, an unsupported or corrupt encoding.
        httpx.HTTPError: what the transport met while receiving.
    """
    try:
        reader = AnswerReader.of(response, max_bytes)
        async for piece in response.aiter_raw():
            for _ in reader.feed(piece):
                await asyncio.sleep(0)
        return reader.finish()
    finally:
        await response.aclose()


# What no longer holds of an answer once its body is read and decoded: how it travelled.
_TRAVEL_HEADERS = frozenset({"content-encoding", "content-length", "transfer-encoding"})


async def send_capped(http: httpx.AsyncClient, request: httpx.Request, max_bytes: int) -> httpx.Response:
    """Send ``request`` through ``http`` and read the answer whole under the cap ``max_bytes``, as
    :func:`read_answer` does: how the client reads the controller's answer and the controller a
    pod's (the client reaches pods through :func:`exchange`). Callers bound the whole exchange with ``asyncio.timeout``.

    Returns:
        the response, its body read and decoded (no Content-Encoding left to decode).

    Raises:
        AnswerTooLargeError, httpx.DecodingError: as :func:`read_answer`.
        httpx.HTTPError: what the transport met while sending or receiving.
    """
    response = await http.send(request, stream=True)
    return _with_body(response, await read_answer(response, max_bytes))


def _with_body(response: httpx.Response, content: bytes) -> httpx.Response:
    """``response`` carrying ``content``, its body as read and decoded, without the headers of
    how it travelled (encoding, length, chunking)."""
    headers = [(k, v) for k, v in response.headers.multi_items() if k.lower() not in _TRAVEL_HEADERS]
    return httpx.Response(response.status_code, headers=headers, content=content, request=response.request)


async def exchange(transport: httpx.AsyncBaseTransport, request: httpx.Request, max_bytes: int) -> tuple[int, bytes]:
    """Send ``request`` through ``transport`` itself and read its answer as :func:`read_answer`
    does: the client's path to a pod over a transport without a lean path (:func:`fetch`). No
    ``httpx.AsyncClient`` around the transport: a pod's requests use none of what it adds
    (redirects, auth, cookies, event hooks, default headers; ``request`` carries its own), and it
    cost ~0.3 ms of client CPU a call (docs/benchmarks.md).

    Returns:
        the answer's status code and its body, decoded.

    Raises:
        AnswerTooLargeError, httpx.DecodingError: as :func:`read_answer`.
        httpx.HTTPError: what the transport met (another transport may raise its own errors).
    """
    response = await transport.handle_async_request(request)
    response.request = request
    return response.status_code, await read_answer(response, max_bytes)


async def fetch(
    transport: httpx.AsyncBaseTransport,
    method: str,
    url: str,
    headers: tuple[tuple[str, str], ...],
    body: bytes,
    max_bytes: int,
) -> tuple[int, bytes]:
    """Send one request to a pod and read its answer as :func:`read_answer` does: through the
    transport's lean path when it has one (:meth:`~vecsim.http1.HttptoolsTransport.fetch`, no
    httpx objects made: ~0.25 ms a call less on a pod's answers, docs/benchmarks.md), else as
    an ``httpx.Request`` through :func:`exchange`. ``body`` goes with a Content-Length (the lean
    path sends one with every request, 0 for an empty one; ``exchange`` none with an empty GET).
    Callers bound it in time with ``asyncio.timeout``.

    Returns:
        the answer's status code and its body, decoded.

    Raises:
        AnswerTooLargeError, httpx.DecodingError: as :func:`read_answer`.
        httpx.HTTPError: what the transport met (another transport may raise its own errors).
    """
    if isinstance(transport, HttptoolsTransport):
        return await transport.fetch(method, url, headers, body, max_bytes)
    request = httpx.Request(method, url, headers=list(headers), content=body or None)
    return await exchange(transport, request, max_bytes)


def get_answer(
    url: str, *, timeout_s: float, max_bytes: int = MAX_CONTROL_ANSWER_BYTES, headers: dict[str, str] | None = None
) -> httpx.Response:
    """``GET url`` from a blocking caller (the controller's routing table, a pod's ``/v1/info``),
    read whole under the cap ``max_bytes`` like :func:`send_capped`, within ``timeout_s`` in all.

    Returns:
        the response, its body read and decoded (no Content-Encoding left to decode).

    Raises:
        AnswerTooLargeError, httpx.DecodingError: as :func:`read_answer`.
        httpx.TimeoutException: no whole answer within ``timeout_s``.
        httpx.HTTPError: what the transport met.
    """
    deadline = time.monotonic() + timeout_s
    with httpx.Client(timeout=timeout_s, trust_env=False) as http:
        request = http.build_request("GET", url, headers=headers)
        response = http.send(request, stream=True)
        try:
            reader = AnswerReader.of(response, max_bytes)
            for piece in response.iter_raw():
                for _ in reader.feed(piece):
                    pass
                if time.monotonic() > deadline:
                    raise httpx.ReadTimeout(f"{url}: no whole answer within {timeout_s} s", request=request)
            content = reader.finish()
        finally:
            response.close()
    return _with_body(response, content)
