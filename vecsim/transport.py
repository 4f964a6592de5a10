"""How the client's bytes reach a pod: httpx transports that move large bodies fast.

The client speaks httpx (``httpx.AsyncClient``); the transport underneath is swappable:

- :class:`AsyncioHTTPTransport` (kind ``"asyncio"``): a lean HTTP/1.1 client on asyncio's
  buffered protocols. A response body with a Content-Length is received by the kernel straight
  into the buffer that becomes ``response.content``: no per-chunk objects, no join.
- :class:`AiohttpTransport` (kind ``"aiohttp"``): aiohttp's client behind the httpx API.
- kind ``"httpx"``: httpx's own ``AsyncHTTPTransport``, the baseline.

``make_async_client(kind="fast")`` picks :data:`FAST_KIND`, chosen by ``bench/bench_transport.py``
(see docs/benchmarks.md), and returns a :class:`VecsimAsyncClient`: an ``httpx.AsyncClient`` that
sends plain requests on a lean path past httpx's auth, redirect and stream layers, frees read
bodies promptly and parses each URL string once. Whatever the transport, failures
surface as httpx exceptions:
``httpx.ConnectError``, ``httpx.ConnectTimeout``, ``httpx.ReadTimeout``, ``httpx.WriteTimeout``,
``httpx.PoolTimeout``, ``httpx.RemoteProtocolError``, ``httpx.ReadError``, and
:class:`TotalTimeout` for the whole-request deadline, so the client handles one family.

Bodies are read whole (no streaming): pods answer with one message per call. uvicorn speaks
HTTP/1.1 only, so every in-flight call holds one keep-alive connection to its pod.
"""

from __future__ import annotations

import asyncio
import datetime
import io
import logging
import time
from collections import deque
from collections.abc import Callable
from typing import Any, Literal

import aiohttp
import httpx
from httpx._exceptions import request_context
from yarl import URL

__all__ = [
    "DEFAULT_LIMITS",
    "DEFAULT_TIMEOUT",
    "FAST_KIND",
    "AiohttpTransport",
    "AsyncioHTTPTransport",
    "DeadlineTransport",
    "TotalTimeout",
    "TransportKind",
    "VecsimAsyncClient",
    "make_async_client",
    "make_transport",
]

logger = logging.getLogger(__name__)
# httpx logs every request it sends at INFO; the lean path logs the same line.
_httpx_logger = logging.getLogger("httpx")

TransportKind = Literal["fast", "asyncio", "aiohttp", "httpx"]

# The transport that bench/bench_transport.py measured fastest on large bodies.
FAST_KIND: Literal["asyncio", "aiohttp"] = "asyncio"

# Step calls can wait seconds for rendering; connecting to a live pod on the cluster network
# should not.
DEFAULT_TIMEOUT = httpx.Timeout(60.0, connect=5.0)
# One connection per pod per in-flight call, for many pods. Idle connections are dropped before
# uvicorn's default 5 s keep-alive would close them under us.
DEFAULT_LIMITS = httpx.Limits(max_connections=512, max_keepalive_connections=512, keepalive_expiry=4.0)

_MAX_HEAD_BYTES = 64 * 1024
_MAX_LINE_BYTES = 8 * 1024
_SCRATCH_BYTES = 64 * 1024
# Distinct URL strings a client keeps parsed (a few endpoints per pod, many pods).
_URL_CACHE_SIZE = 4096
# Below this a request body rides in the same write as its head.
_COALESCE_BYTES = 64 * 1024


class TotalTimeout(httpx.TimeoutException):
    """The whole request (pool wait, connect, send, receive) took longer than its deadline."""


# -------------------------------------------------------------------------- total deadline


class DeadlineTransport(httpx.AsyncBaseTransport):
    """Wraps a transport with a deadline for the whole request, body included.

    The deadline is ``request.extensions["total_timeout"]`` if set, else the ``total_timeout``
    given here; ``None`` means none.
    """

    def __init__(self, inner: httpx.AsyncBaseTransport, total_timeout: float | None = None) -> None:
        self.inner = inner
        self.total_timeout = total_timeout

    async def handle_async_request(self, request: httpx.Request) -> httpx.Response:
        """Send ``request`` through the inner transport within the deadline.

        Returns:
            the response, its body already read.

        Raises:
            TotalTimeout: the deadline passed; any other error of the inner transport.
        """
        total = request.extensions.get("total_timeout", self.total_timeout)
        if total is None:
            return await self.inner.handle_async_request(request)
        deadline = asyncio.timeout(total)
        try:
            async with deadline:
                response = await self.inner.handle_async_request(request)
                try:
                    content = await response.aread()
                finally:
                    await response.aclose()
        except TimeoutError:
            if not deadline.expired():
                raise
            raise TotalTimeout(
                f"{request.method} {request.url} took longer than its total timeout of {total} s",
                request=request,
            ) from None
        # A fresh, unread response: the client reads it (no copy) and times it as usual.
        return httpx.Response(
            response.status_code,
            headers=response.headers.raw,
            stream=httpx.ByteStream(content),
            extensions=response.extensions,
        )

    async def aclose(self) -> None:
        """Close the inner transport."""
        await self.inner.aclose()


# ------------------------------------------------------------------ asyncio HTTP/1.1 transport


class _ReadTimedOut(Exception):
    """Internal: no byte arrived for the read timeout."""


class _Connection(asyncio.BufferedProtocol):
    """One HTTP/1.1 connection: a buffered protocol with awaitable reads.

    Bytes land in ``_pending`` through a scratch buffer, except while :meth:`read_exact` has
    lent its target buffer: then ``get_buffer`` hands out the target itself, so the kernel
    writes the body where it will stay.
    """

    def __init__(self, origin: tuple[str, int]) -> None:
        self.origin = origin
        self.transport: asyncio.Transport | None = None
        self.idle_since = 0.0
        self.closed = False
        self._loop = asyncio.get_running_loop()
        self._scratch = memoryview(bytearray(_SCRATCH_BYTES))
        self._pending = bytearray()
        self._target: memoryview | None = None
        self._filled = 0
        self._eof = False
        self._error: BaseException | None = None
        self._waiter: asyncio.Future[None] | None = None
        self._last_progress = 0.0
        self._timer: asyncio.TimerHandle | None = None
        self._write_paused = False
        self._drain_waiter: asyncio.Future[None] | None = None

    # asyncio.BufferedProtocol -------------------------------------------------------------

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]

    def get_buffer(self, sizehint: int) -> memoryview:
        if self._target is not None and self._filled < len(self._target):
            return self._target[self._filled :]
        return self._scratch

    def buffer_updated(self, nbytes: int) -> None:
        self._last_progress = self._loop.time()
        if self._target is not None and self._filled < len(self._target):
            self._filled += nbytes
            if self._filled == len(self._target):
                self._wake()
        else:
            self._pending += self._scratch[:nbytes]
            self._wake()

    def eof_received(self) -> bool:
        self._eof = True
        self._wake()
        return False

    def connection_lost(self, exc: Exception | None) -> None:
        self.closed = True
        self._eof = True
        self._error = exc
        self._wake()
        if self._drain_waiter is not None and not self._drain_waiter.done():
            self._drain_waiter.set_result(None)

    def pause_writing(self) -> None:
        self._write_paused = True

    def resume_writing(self) -> None:
        self._write_paused = False
        if self._drain_waiter is not None and not self._drain_waiter.done():
            self._drain_waiter.set_result(None)

    # helpers -------------------------------------------------------------------------------

    def _wake(self) -> None:
        if self._waiter is not None and not self._waiter.done():
            self._waiter.set_result(None)

    @property
    def reusable(self) -> bool:
        """Open, nothing unread, nothing half-done: safe to send the next request on."""
        return not (self.closed or self._eof or self._pending or self.transport.is_closing())

    def close(self) -> None:
        self.closed = True
        if self.transport is not None:
            self.transport.close()

    def _check_read_timeout(self, timeout: float) -> None:
        waiter = self._waiter
        if waiter is None or waiter.done():
            return
        idle = self._loop.time() - self._last_progress
        if idle >= timeout:
            waiter.set_exception(_ReadTimedOut())
        else:
            # Bytes arrived meanwhile: httpx's read timeout is per read, not per response.
            self._timer = self._loop.call_later(timeout - idle, self._check_read_timeout, timeout)

    async def _wait(self, timeout: float | None) -> None:
        """Wait for the next wake-up: bytes, a full target, EOF, or ``_ReadTimedOut``."""
        self._waiter = self._loop.create_future()
        self._last_progress = self._loop.time()
        self._timer = None if timeout is None else self._loop.call_later(timeout, self._check_read_timeout, timeout)
        try:
            await self._waiter
        finally:
            if self._timer is not None:
                self._timer.cancel()
            self._waiter = None

    def _closed_early(self, what: str) -> Exception:
        if self._error is not None:
            return httpx.ReadError(f"connection to {self._where()} failed while reading {what}: {self._error}")
        return httpx.RemoteProtocolError(f"{self._where()} closed the connection before sending all of {what}")

    def _where(self) -> str:
        return f"{self.origin[0]}:{self.origin[1]}"

    # reads and writes --------------------------------------------------------------------

    async def write(self, data: bytes | memoryview, timeout: float | None) -> None:
        """Send ``data``, waiting (up to ``timeout``) while the socket's buffer is full."""
        if self.closed or self.transport.is_closing():
            raise httpx.WriteError(f"connection to {self._where()} is closed")
        self.transport.write(data)
        if self._write_paused:
            self._drain_waiter = self._loop.create_future()
            try:
                async with asyncio.timeout(timeout):
                    await self._drain_waiter
            except TimeoutError:
                raise httpx.WriteTimeout(f"sending to {self._where()} stalled for {timeout} s") from None
            finally:
                self._drain_waiter = None
            if self.closed:
                raise httpx.WriteError(f"connection to {self._where()} closed while sending")

    async def read_until(self, delimiter: bytes, limit: int, timeout: float | None, what: str) -> bytes:
        """Bytes up to and including ``delimiter`` (at most ``limit`` of them)."""
        start = 0
        while True:
            end = self._pending.find(delimiter, start)
            if end >= 0:
                end += len(delimiter)
                data = bytes(self._pending[:end])
                del self._pending[:end]
                return data
            if len(self._pending) > limit:
                raise httpx.RemoteProtocolError(f"{self._where()} sent a {what} over {limit} bytes")
            if self._eof:
                raise self._closed_early(what)
            start = max(0, len(self._pending) - len(delimiter) + 1)
            await self._wait(timeout)

    async def read_exact(self, n: int, timeout: float | None) -> bytes:
        """Exactly ``n`` bytes, received (beyond what is already here) straight into the result."""
        if n <= len(self._pending):
            data = bytes(self._pending[:n])
            del self._pending[:n]
            return data
        # BytesIO lends its buffer for the kernel to fill and hands it back as bytes without a
        # copy (CPython), where bytes(bytearray) would copy the whole body once more; bytes(n)
        # comes from calloc, so large bodies are not even zeroed by hand first.
        body = io.BytesIO(bytes(n))
        target = body.getbuffer()
        have = len(self._pending)
        target[:have] = self._pending
        self._pending.clear()
        self._target, self._filled = target, have
        try:
            while self._filled < n:
                if self._eof:
                    raise self._closed_early(f"a body (got {self._filled} of {n} bytes)")
                await self._wait(timeout)
        finally:
            self._target = None
        del target
        return body.getvalue()

    async def read_to_eof(self, timeout: float | None) -> bytes:
        """Everything until the server closes the connection."""
        chunks = []
        while True:
            if self._pending:
                chunks.append(bytes(self._pending))
                self._pending.clear()
            if self._eof:
                if self._error is not None:
                    raise self._closed_early("a body")
                return b"".join(chunks)
            await self._wait(timeout)


def _header_value(headers: list[tuple[bytes, bytes]], name: bytes) -> list[bytes]:
    return [v for k, v in headers if k.lower() == name]


def _parse_head(head: bytes, where: str) -> tuple[bytes, int, bytes, list[tuple[bytes, bytes]]]:
    lines = head[:-4].split(b"\r\n")
    parts = lines[0].split(b" ", 2)
    if len(parts) < 2 or not parts[0].startswith(b"HTTP/1.") or not (len(parts[1]) == 3 and parts[1].isdigit()):
        raise httpx.RemoteProtocolError(f"{where} sent a bad status line: {lines[0][:100]!r}")
    headers = []
    for line in lines[1:]:
        name, sep, value = line.partition(b":")
        if not sep or not name or name != name.strip() or line[:1] in (b" ", b"\t"):
            raise httpx.RemoteProtocolError(f"{where} sent a bad header line: {line[:100]!r}")
        headers.append((name, value.strip(b" \t")))
    return parts[0], int(parts[1]), parts[2] if len(parts) == 3 else b"", headers


def _content_length(headers: list[tuple[bytes, bytes]], where: str) -> int | None:
    values = {v.strip() for raw in _header_value(headers, b"content-length") for v in raw.split(b",")}
    if not values:
        return None
    if len(values) != 1 or not next(iter(values)).isdigit():
        raise httpx.RemoteProtocolError(f"{where} sent a bad Content-Length: {sorted(values)!r:.100}")
    return int(values.pop())


class AsyncioHTTPTransport(httpx.AsyncBaseTransport):
    """A lean HTTP/1.1 client transport on asyncio, with a keep-alive pool per origin.

    Honours httpx's per-request timeouts (connect, read per chunk, write, pool) and ``limits``
    (max_connections in total, max_keepalive_connections, keepalive_expiry). Plain ``http``
    only; proxies are not used. Must be used from one event loop.
    """

    def __init__(self, *, limits: httpx.Limits = DEFAULT_LIMITS) -> None:
        self._limits = limits
        self._idle: dict[tuple[str, int], list[_Connection]] = {}
        self._all: set[_Connection] = set()
        self._connecting = 0
        self._waiters: deque[asyncio.Future[None]] = deque()
        self._closed = False

    # pool ------------------------------------------------------------------------------

    def _wake_one(self) -> None:
        while self._waiters:
            waiter = self._waiters.popleft()
            if not waiter.done():
                waiter.set_result(None)
                return

    def _discard(self, conn: _Connection) -> None:
        conn.close()
        self._all.discard(conn)
        self._wake_one()

    def _take_idle(self, origin: tuple[str, int]) -> _Connection | None:
        idle = self._idle.get(origin)
        now = asyncio.get_running_loop().time()
        expiry = self._limits.keepalive_expiry
        while idle:
            conn = idle.pop()
            if conn.reusable and (expiry is None or now - conn.idle_since < expiry):
                return conn
            self._discard(conn)
        return None

    def _evict_idle(self) -> bool:
        """Close one idle connection (the oldest) to make room; False if none is idle."""
        candidates = [(conns[0].idle_since, origin) for origin, conns in self._idle.items() if conns]
        if not candidates:
            return False
        _, origin = min(candidates)
        self._discard(self._idle[origin].pop(0))
        return True

    async def _acquire(self, request: httpx.Request, origin: tuple[str, int], timeouts: dict[str, Any]) -> _Connection:
        loop = asyncio.get_running_loop()
        limit = self._limits.max_connections
        pool_deadline = None if timeouts.get("pool") is None else loop.time() + timeouts["pool"]
        while True:
            conn = self._take_idle(origin)
            if conn is not None:
                return conn
            if limit is None or len(self._all) + self._connecting < limit or self._evict_idle():
                break
            waiter = loop.create_future()
            self._waiters.append(waiter)
            try:
                remaining = None if pool_deadline is None else max(0.0, pool_deadline - loop.time())
                async with asyncio.timeout(remaining):
                    await waiter
            except TimeoutError:
                raise httpx.PoolTimeout(
                    f"no connection free for {request.url} within {timeouts['pool']} s "
                    f"(max_connections={limit})",
                    request=request,
                ) from None
            finally:
                if waiter in self._waiters:
                    self._waiters.remove(waiter)
        return await self._connect(request, origin, timeouts.get("connect"))

    async def _connect(self, request: httpx.Request, origin: tuple[str, int], timeout: float | None) -> _Connection:
        loop = asyncio.get_running_loop()
        host, port = origin
        self._connecting += 1  # holds a slot of max_connections while connecting
        conn = None
        try:
            async with asyncio.timeout(timeout):
                _, conn = await loop.create_connection(lambda: _Connection(origin), host, port)
        except TimeoutError:
            raise httpx.ConnectTimeout(
                f"connecting to {host}:{port} took longer than {timeout} s", request=request
            ) from None
        except OSError as exc:
            raise httpx.ConnectError(f"cannot connect to {host}:{port}: {exc}", request=request) from None
        finally:
            self._connecting -= 1
            if conn is None:
                self._wake_one()
        self._all.add(conn)
        logger.debug("connected to %s:%d (%d connections open)", host, port, len(self._all))
        return conn

    def _release(self, conn: _Connection, keep: bool) -> None:
        idle_count = sum(len(c) for c in self._idle.values())
        max_idle = self._limits.max_keepalive_connections
        if keep and not self._closed and conn.reusable and (max_idle is None or idle_count < max_idle):
            conn.idle_since = asyncio.get_running_loop().time()
            self._idle.setdefault(conn.origin, []).append(conn)
            self._wake_one()
        else:
            self._discard(conn)

    # one exchange ------------------------------------------------------------------------

    async def _send(self, conn: _Connection, request: httpx.Request, timeouts: dict[str, Any]) -> None:
        url = request.url
        for name, value in request.headers.raw:
            if b"\r" in name or b"\n" in name or b"\r" in value or b"\n" in value:
                raise httpx.LocalProtocolError(f"header {name!r} holds a line break", request=request)
        head = b"".join(
            [
                request.method.encode("ascii"),
                b" ",
                url.raw_path,
                b" HTTP/1.1\r\n",
                *(b"%s: %s\r\n" % pair for pair in request.headers.raw),
                b"\r\n",
            ]
        )
        chunked = b"chunked" in b",".join(_header_value(request.headers.raw, b"transfer-encoding")).lower()
        write_timeout = timeouts.get("write")
        pending = head
        async for chunk in request.stream:
            if not chunk:
                continue
            if chunked:
                chunk = b"%x\r\n%s\r\n" % (len(chunk), chunk)
            if len(pending) + len(chunk) <= _COALESCE_BYTES:
                pending += chunk
                continue
            if pending:
                await conn.write(pending, write_timeout)
                pending = b""
            await conn.write(chunk, write_timeout)
        if chunked:
            pending += b"0\r\n\r\n"
        if pending:
            await conn.write(pending, write_timeout)

    async def _receive(
        self, conn: _Connection, request: httpx.Request, read_timeout: float | None
    ) -> tuple[httpx.Response, bool]:
        where = conn._where()
        while True:
            head = await conn.read_until(b"\r\n\r\n", _MAX_HEAD_BYTES, read_timeout, "response head")
            version, status, reason, headers = _parse_head(head, where)
            if not 100 <= status < 200 or status == 101:
                break
        if status == 101:
            raise httpx.RemoteProtocolError(f"{where} switched protocols, which this transport does not speak")
        connection = b",".join(_header_value(headers, b"connection")).lower()
        keep = b"close" not in connection and (version != b"HTTP/1.0" or b"keep-alive" in connection)
        transfer = b",".join(_header_value(headers, b"transfer-encoding")).lower()
        length = _content_length(headers, where)
        if request.method == "HEAD" or status in (204, 304):
            body = b""
        elif transfer:
            if transfer.rsplit(b",", 1)[-1].strip() == b"chunked":
                body = await self._read_chunked(conn, read_timeout, where)
            else:
                body, keep = await conn.read_to_eof(read_timeout), False
        elif length is not None:
            body = await conn.read_exact(length, read_timeout)
        else:
            body, keep = await conn.read_to_eof(read_timeout), False
        response = httpx.Response(
            status,
            headers=headers,
            stream=httpx.ByteStream(body),
            extensions={"http_version": version, "reason_phrase": reason},
        )
        return response, keep

    async def _read_chunked(self, conn: _Connection, timeout: float | None, where: str) -> bytes:
        chunks = []
        while True:
            line = await conn.read_until(b"\r\n", _MAX_LINE_BYTES, timeout, "chunk size line")
            size_text = line[:-2].split(b";", 1)[0].strip()
            try:
                size = int(size_text, 16)
            except ValueError:
                raise httpx.RemoteProtocolError(f"{where} sent a bad chunk size {size_text[:50]!r}") from None
            if size < 0:
                raise httpx.RemoteProtocolError(f"{where} sent a bad chunk size {size_text[:50]!r}")
            if size == 0:
                while await conn.read_until(b"\r\n", _MAX_LINE_BYTES, timeout, "trailer line") != b"\r\n":
                    pass
                return b"".join(chunks)
            chunks.append(await conn.read_exact(size, timeout))
            if await conn.read_exact(2, timeout) != b"\r\n":
                raise httpx.RemoteProtocolError(f"{where} sent a chunk without its CRLF")

    async def handle_async_request(self, request: httpx.Request) -> httpx.Response:
        """Send ``request`` on a pooled connection and read the whole response.

        Returns:
            the response, its body in memory.

        Raises:
            httpx.UnsupportedProtocol: the URL is not ``http``.
            httpx.PoolTimeout, httpx.ConnectTimeout, httpx.ConnectError, httpx.WriteTimeout,
            httpx.WriteError, httpx.ReadTimeout, httpx.ReadError, httpx.RemoteProtocolError,
            httpx.LocalProtocolError: as their names say.
        """
        if self._closed:
            raise RuntimeError("the transport is closed")
        url = request.url
        if url.scheme != "http":
            raise httpx.UnsupportedProtocol(
                f"{url}: AsyncioHTTPTransport speaks plain http only, not {url.scheme!r}", request=request
            )
        origin = (url.host, url.port or 80)
        timeouts = request.extensions.get("timeout", {})
        conn = await self._acquire(request, origin, timeouts)
        keep = False
        try:
            await self._send(conn, request, timeouts)
            response, keep = await self._receive(conn, request, timeouts.get("read"))
        except _ReadTimedOut:
            raise httpx.ReadTimeout(
                f"no data from {conn._where()} for {timeouts.get('read')} s", request=request
            ) from None
        except httpx.TransportError as exc:
            exc.request = request
            raise
        finally:
            self._release(conn, keep and "close" not in request.headers.get("connection", "").lower())
        return response

    async def aclose(self) -> None:
        """Close every connection, idle or busy; later requests raise RuntimeError."""
        self._closed = True
        for conn in list(self._all):
            self._discard(conn)
        self._idle.clear()


# --------------------------------------------------------------------------- aiohttp transport


class AiohttpTransport(httpx.AsyncBaseTransport):
    """aiohttp's client behind httpx's API.

    Timeouts map to aiohttp's: ``connect`` to ``sock_connect``, ``pool`` + ``connect`` to
    ``connect``, ``read`` to ``sock_read`` (per read, as in httpx). aiohttp has no write
    timeout; use a total timeout (:class:`DeadlineTransport`) to bound a stalled send.
    """

    def __init__(self, *, limits: httpx.Limits = DEFAULT_LIMITS, read_bufsize: int = 1 << 20) -> None:
        self._limits = limits
        self._read_bufsize = read_bufsize
        self._session: aiohttp.ClientSession | None = None

    def _get_session(self) -> aiohttp.ClientSession:
        if self._session is None:
            connector = aiohttp.TCPConnector(
                limit=self._limits.max_connections or 0,
                limit_per_host=0,
                keepalive_timeout=self._limits.keepalive_expiry,
            )
            self._session = aiohttp.ClientSession(
                connector=connector,
                auto_decompress=False,  # httpx decodes Content-Encoding itself
                read_bufsize=self._read_bufsize,
                cookie_jar=aiohttp.DummyCookieJar(),  # httpx keeps the cookies
                timeout=aiohttp.ClientTimeout(total=None),
            )
        return self._session

    async def handle_async_request(self, request: httpx.Request) -> httpx.Response:
        """Send ``request`` through aiohttp and read the whole response.

        Returns:
            the response, its body in memory.

        Raises:
            httpx.ConnectTimeout, httpx.ConnectError, httpx.ReadTimeout, httpx.ReadError,
            httpx.RemoteProtocolError, httpx.UnsupportedProtocol: mapped from aiohttp's errors.
        """
        t = request.extensions.get("timeout", {})
        connect, pool = t.get("connect"), t.get("pool")
        timeout = aiohttp.ClientTimeout(
            total=None,
            connect=None if connect is None or pool is None else connect + pool,
            sock_connect=connect,
            sock_read=t.get("read"),
        )
        body = b"".join([chunk async for chunk in request.stream])
        # The body is whole here, so aiohttp sends it with a Content-Length, never chunked.
        headers = [
            (k.decode("latin-1"), v.decode("latin-1"))
            for k, v in request.headers.raw
            if k.lower() not in (b"transfer-encoding", b"content-length")
        ]
        try:
            async with self._get_session().request(
                request.method,
                URL(str(request.url), encoded=True),
                headers=headers,
                data=body or None,
                allow_redirects=False,
                timeout=timeout,
                skip_auto_headers=("User-Agent", "Accept", "Accept-Encoding", "Content-Type"),
            ) as resp:
                content = await resp.read()
                return httpx.Response(
                    resp.status,
                    headers=list(resp.raw_headers),
                    stream=httpx.ByteStream(content),
                    extensions={
                        "http_version": f"HTTP/{resp.version.major}.{resp.version.minor}".encode(),
                        "reason_phrase": (resp.reason or "").encode("latin-1"),
                    },
                )
        except aiohttp.ConnectionTimeoutError as exc:
            raise httpx.ConnectTimeout(f"connecting to {request.url.host}: {exc}", request=request) from None
        except aiohttp.ServerTimeoutError as exc:
            raise httpx.ReadTimeout(f"reading from {request.url.host}: {exc or 'timed out'}", request=request) from None
        except aiohttp.ClientConnectorError as exc:
            raise httpx.ConnectError(f"cannot connect to {request.url.host}: {exc}", request=request) from None
        except (aiohttp.ServerDisconnectedError, aiohttp.ClientPayloadError, aiohttp.ClientResponseError) as exc:
            raise httpx.RemoteProtocolError(f"{request.url.host}: {exc}", request=request) from None
        except aiohttp.InvalidURL as exc:
            raise httpx.UnsupportedProtocol(f"{request.url}: {exc}", request=request) from None
        except aiohttp.ClientError as exc:
            raise httpx.ReadError(f"{request.url.host}: {exc}", request=request) from None

    async def aclose(self) -> None:
        """Close the aiohttp session and its connections."""
        if self._session is not None:
            await self._session.close()
            self._session = None


# ------------------------------------------------------------------------------------ factory


class VecsimAsyncClient(httpx.AsyncClient):
    """``httpx.AsyncClient`` tuned for many calls to the same few URLs with large answers.

    - A lean path for the requests vecsim makes: :meth:`request` (and so ``get``, ``post``,
      ``put``, ...) without ``data``, ``files``, ``params``, ``cookies``, ``auth`` or
      ``follow_redirects``, on a client without auth, params, cookies, event hooks, mounts or
      redirect following, builds the request once and hands it to the transport directly,
      skipping httpx's auth flow, redirect loop, stream wrapper and chunked read. What callers
      see stays httpx's: the same request (client headers merged, Host, Content-Length, the
      client's or the call's timeouts), the same response (``request``, ``elapsed``,
      ``next_request`` for a redirect, cookies the server sets kept by the client), the same
      exceptions. Anything else takes httpx's own path.
    - A read response lets go of its body as soon as you do. httpx links a response and its
      stream both ways, so a response, and its body, live on until the next garbage
      collection; with bodies of megabytes that means fresh memory (page faults) for every
      response, which halved the throughput measured on 4 MiB bodies. Once a response is read
      and closed its stream has nothing left to give, so it is swapped for an empty one.
    - URL strings are parsed once: httpx's pure-Python URL parser costs about a tenth of a
      millisecond per call, and a client calls the same few endpoints again and again.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._parsed_urls: dict[str, httpx.URL] = {}
        # URL strings merged with base_url for the lean path, valid while base_url is the same object.
        self._merged_urls: dict[str, httpx.URL] = {}
        self._merged_for: httpx.URL | None = None
        self._timeout_dict: tuple[httpx.Timeout, dict[str, float | None]] | None = None

    def _parse(self, url: str) -> httpx.URL:
        parsed = self._parsed_urls.get(url)
        if parsed is None:
            if len(self._parsed_urls) >= _URL_CACHE_SIZE:
                self._parsed_urls.clear()
            parsed = self._parsed_urls[url] = httpx.URL(url)
        return parsed

    def build_request(self, method: str, url: httpx.URL | str, **kwargs: Any) -> httpx.Request:
        """Build a request as ``httpx.AsyncClient.build_request`` does, with ``url`` parsed once.

        Returns:
            the request.

        Raises:
            whatever ``httpx.AsyncClient.build_request`` raises.
        """
        if isinstance(url, str):
            url = self._parse(url)
        return super().build_request(method, url, **kwargs)

    def _lean_url(self, url: httpx.URL | str) -> httpx.URL:
        if not isinstance(url, str):
            return self._merge_url(url)
        if self._merged_for is not self.base_url:
            self._merged_urls.clear()
            self._merged_for = self.base_url
        merged = self._merged_urls.get(url)
        if merged is None:
            if len(self._merged_urls) >= _URL_CACHE_SIZE:
                self._merged_urls.clear()
            merged = self._merged_urls[url] = self._merge_url(self._parse(url))
        return merged

    def _lean_timeout(self, timeout: Any) -> dict[str, float | None]:
        if timeout is not httpx.USE_CLIENT_DEFAULT:
            return httpx.Timeout(timeout).as_dict()
        cached = self._timeout_dict
        if cached is None or cached[0] is not self.timeout:
            cached = self._timeout_dict = (self.timeout, self.timeout.as_dict())
        return dict(cached[1])

    def _lean_applies(self) -> bool:
        """The client holds nothing that httpx's full path would act on per request."""
        return (
            self.auth is None
            and not self.follow_redirects
            and not self.params
            and not self.cookies
            and not self._mounts
            and not self.event_hooks["request"]
            and not self.event_hooks["response"]
        )

    async def request(  # type: ignore[override]
        self,
        method: str,
        url: httpx.URL | str,
        *,
        content: Any = None,
        data: Any = None,
        files: Any = None,
        json: Any = None,
        params: Any = None,
        headers: Any = None,
        cookies: Any = None,
        auth: Any = httpx.USE_CLIENT_DEFAULT,
        follow_redirects: Any = httpx.USE_CLIENT_DEFAULT,
        timeout: Any = httpx.USE_CLIENT_DEFAULT,
        extensions: dict[str, Any] | None = None,
    ) -> httpx.Response:
        """Build and send a request, as ``httpx.AsyncClient.request`` does; the lean path when
        nothing in the call or the client needs httpx's full one (see the class).

        Returns:
            the response, read and closed.

        Raises:
            RuntimeError: the client is closed; the transport's httpx exceptions, as
            ``httpx.AsyncClient.request`` raises them.
        """
        if (
            data is not None
            or files is not None
            or params is not None
            or cookies is not None
            or auth is not httpx.USE_CLIENT_DEFAULT
            or follow_redirects is not httpx.USE_CLIENT_DEFAULT
            or not self._lean_applies()
        ):
            return await super().request(
                method,
                url,
                content=content,
                data=data,
                files=files,
                json=json,
                params=params,
                headers=headers,
                cookies=cookies,
                auth=auth,
                follow_redirects=follow_redirects,
                timeout=timeout,
                extensions=extensions,
            )
        if self.is_closed:
            raise RuntimeError("Cannot send a request, as the client has been closed.")
        merged = httpx.Headers(self.headers)
        if headers is not None:
            merged.update(headers)
        extensions = {} if extensions is None else dict(extensions)
        if "timeout" not in extensions:
            extensions["timeout"] = self._lean_timeout(timeout)
        request = httpx.Request(
            method, self._lean_url(url), content=content, json=json, headers=merged, extensions=extensions
        )
        start = time.perf_counter()
        with request_context(request=request):  # errors carry the request, as httpx's path gives them
            response = await self._transport.handle_async_request(request)
        try:
            response.request = request
            response.default_encoding = self._default_encoding
            await response.aread()
        finally:
            await response.aclose()
        response.elapsed = datetime.timedelta(seconds=time.perf_counter() - start)
        response.stream = httpx.ByteStream(b"")
        if "set-cookie" in response.headers:
            self.cookies.extract_cookies(response)
        if response.has_redirect_location:
            response.next_request = self._build_redirect_request(request, response)
        if _httpx_logger.isEnabledFor(logging.INFO):
            _httpx_logger.info(
                'HTTP Request: %s %s "%s %d %s"',
                request.method,
                request.url,
                response.http_version,
                response.status_code,
                response.reason_phrase,
            )
        return response

    async def send(self, request: httpx.Request, *, stream: bool = False, **kwargs: Any) -> httpx.Response:
        """Send ``request`` as ``httpx.AsyncClient.send`` does.

        Returns:
            the response; unless ``stream`` is true it is read, closed and free of the loop.

        Raises:
            whatever ``httpx.AsyncClient.send`` raises.
        """
        response = await super().send(request, stream=stream, **kwargs)
        if not stream and response.is_closed:
            response.stream = httpx.ByteStream(b"")
        return response


def make_transport(kind: TransportKind = "fast", *, limits: httpx.Limits = DEFAULT_LIMITS) -> httpx.AsyncBaseTransport:
    """A bare transport of ``kind`` (``"fast"`` means :data:`FAST_KIND`).

    Returns:
        the transport, without a total deadline.

    Raises:
        ValueError: unknown ``kind``.
    """
    makers: dict[str, Callable[[], httpx.AsyncBaseTransport]] = {
        "asyncio": lambda: AsyncioHTTPTransport(limits=limits),
        "aiohttp": lambda: AiohttpTransport(limits=limits),
        "httpx": lambda: httpx.AsyncHTTPTransport(limits=limits),
    }
    name = FAST_KIND if kind == "fast" else kind
    if name not in makers:
        raise ValueError(f"kind: {kind!r} is not one of 'fast', 'asyncio', 'aiohttp', 'httpx'")
    return makers[name]()


def make_async_client(
    kind: TransportKind = "fast",
    *,
    timeout: httpx.Timeout | float | None = DEFAULT_TIMEOUT,
    total_timeout: float | None = None,
    limits: httpx.Limits = DEFAULT_LIMITS,
    **client_kwargs: Any,
) -> VecsimAsyncClient:
    """An ``httpx.AsyncClient`` (:class:`VecsimAsyncClient`) on the transport ``kind``, with a
    whole-request deadline.

    ``timeout`` is httpx's (connect, read, write, pool); ``total_timeout`` bounds a whole
    request, body included, and can be set per request with
    ``extensions={"total_timeout": seconds}``. Environment proxies are ignored
    (``trust_env=False``) unless ``client_kwargs`` says otherwise: pods are reached directly.

    Returns:
        the client; close it with ``await client.aclose()``.

    Raises:
        ValueError: unknown ``kind``.
    """
    transport = DeadlineTransport(make_transport(kind, limits=limits), total_timeout)
    client_kwargs.setdefault("trust_env", False)
    return VecsimAsyncClient(transport=transport, timeout=timeout, **client_kwargs)
