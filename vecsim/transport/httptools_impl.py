"""The default :class:`~vecsim.transport.Transport`: HTTP/1.1 on httptools (llhttp, the parser
under uvicorn). Its :meth:`HttptoolsTransport.fetch` sends a request given as plain values and
gives back the status and the decoded body under a size cap, with no httpx objects made on the
way; it also serves httpx's interface (``handle_async_request``) for the control plane's
``httpx.AsyncClient``. Why it is the default, measured: docs/api.md ("Transport").

What is vecsim's here and what is not: llhttp parses every byte that arrives (status line,
headers, Content-Length, chunked framing) and raises on anything malformed; this module writes
the request (a request line, the caller's headers, a Content-Length, its body, in one write),
keeps idle connections per origin for reuse, and decides when an answer has ended where llhttp
cannot say so itself (a body that runs until the connection closes; the answer to a HEAD).
Header names and values that could split the request (CR, LF, NUL) are refused before a byte
is sent. Every part of an answer is capped: the head (:data:`MAX_HEAD_BYTES`), chunk extensions
and trailers (:data:`MAX_FRAMING_BYTES`), the chunks (:data:`MAX_CHUNKS`) and the body (the
caller's ``max_bytes``); reading stops at a cap, so a hostile answer costs what was read up to it.
Failures leave as httpx's exceptions (``vecsim.transport.errors`` maps them): ``ConnectError``/
``ConnectTimeout``, ``RemoteProtocolError`` (a malformed answer, a cap passed, a connection that
ends inside one), ``ReadTimeout``, ``LocalProtocolError`` (a request that cannot be written),
``UnsupportedProtocol``.

Connections belong to the event loop that made them; one transport serves one loop, as the
client uses it.
"""

from __future__ import annotations

import asyncio
import mmap
import ssl
import time
from collections.abc import AsyncIterator, Iterable, Sequence

import httptools
import httpx

from vecsim import wire

from .answers import AnswerReader
from .base import KEEPALIVE_S, Transport
from .errors import BrokenAnswer, ConnectTimedOut, ReadTimedOut, UnsendableRequest, UnsupportedURL, failure_of, mapped

__all__ = [
    "IDEMPOTENCY_KEY",
    "MAX_CHUNKS",
    "MAX_FRAMING_BYTES",
    "MAX_HEAD_BYTES",
    "HttptoolsTransport",
    "MayHaveBeenAppliedError",
]

# An answer's head (status line and headers) larger than this is refused: llhttp sets no bound,
# and httptools gathers a header's pieces in memory until it ends. A pod's head is ~200 bytes.
MAX_HEAD_BYTES = 64 << 10
# After the head, what is not body (chunk extensions, trailers) may take this much beside the
# size lines' own bytes: httptools rebuilds a trailer's value on every read, so a trailer or an
# extension left unbounded costs memory and loop time without end. Pods send neither.
MAX_FRAMING_BYTES = 64 << 10
# What one chunk's size line and CRLFs may take of the framing: 16 hex digits and two CRLFs.
_CHUNK_LINE_BYTES = 20
# Chunks of one answer: each costs a few parser callbacks and a piece kept, whatever its size,
# so a body sent a byte per chunk would cost tens of times its size. Pods send no chunks; a proxy
# that re-chunks sends buffers of KiBs, which this allows up to a 64 MiB answer in 4 KiB chunks.
MAX_CHUNKS = 1 << 14
# Idle connections kept per origin; more are closed as they come back. The client bounds its
# requests in flight itself, so this only trims what a burst leaves behind.
MAX_IDLE_PER_ORIGIN = 64
# Reading stops while this much of an answer's body waits to be taken (a reader slower than
# the socket); it goes on once the reader has taken it.
_HIGH_WATER = 4 << 20
# A 200 wire answer to fetch of at least this many bytes (its length declared, not encoded) is
# read past the parser, straight into one buffer of its length: the socket's bytes land where the
# caller decodes them, no piece kept or joined. The buffer is an anonymous mapping, whose pages
# are taken as they are written (so such an answer too costs what was read) and are not asked to
# be huge ones (numpy's large arrays are: on a busy machine the kernel then stalls compacting).
DIRECT_BYTES = 1 << 20
# What the socket is read into while an answer is parsed.
_READ_BYTES = 256 << 10
# Request heads kept encoded, by method, URL and headers: a client sends a few kinds to a few pods.
_CACHED_HEADS = 1024
# The header that makes a request safe to send again (the IETF httpapi draft's name): the server
# answers a repeated key from memory. Idempotent methods (RFC 9110, 9.2.2) are safe without it.
IDEMPOTENCY_KEY = "Idempotency-Key"
_KEY_LOWER = IDEMPOTENCY_KEY.lower()
_IDEMPOTENT_METHODS = frozenset({"GET", "HEAD", "OPTIONS", "PUT", "DELETE"})
# Statuses whose answer has no body whatever its headers say (RFC 9110).
_NO_BODY = frozenset({204, 304})


def _bad_header_text(text: bytes) -> bool:
    return b"\r" in text or b"\n" in text or b"\0" in text


def _header_value(value: str) -> bytes:
    raw = value.encode("latin-1")
    if _bad_header_text(raw):
        raise httpx.LocalProtocolError(f"header value {raw[:40]!r} cannot be sent")
    return raw


class MayHaveBeenAppliedError(httpx.RemoteProtocolError):
    """A reused connection ended before any byte of the answer to a request that is not safe to
    send again (see :meth:`HttptoolsTransport._send`): the server may have applied it."""


class _Connection(asyncio.BufferedProtocol):
    """One keep-alive connection: one request at a time, its answer parsed as it arrives (a big
    wire answer's body read past the parser, see :data:`DIRECT_BYTES`)."""

    def __init__(self, origin: tuple[str, str, int]) -> None:
        self.origin = origin
        self.transport: asyncio.Transport | None = None
        self.closed = False
        self.idle_since = 0.0
        self._waiter: asyncio.Future[None] | None = None
        self._parser: httptools.HttpResponseParser | None = None
        self._active = False
        self._head_only = False
        self._paused = False
        self.status = 0
        self.reason = b""
        self.headers: list[tuple[bytes, bytes]] = []
        self.headers_done = False
        self.done = False
        self.keep_alive = False
        self.error: Exception | None = None
        self._pieces: list[bytes] = []
        self._buffered = 0
        self._informational = False
        self.received = 0  # bytes of the current exchange's answer, head included
        self._head_bytes = 0
        self.body_received = 0  # of them, bytes of body
        self.chunks = 0  # chunks of the current answer begun
        self.exchanges = 0  # requests sent on this connection
        self.written = False  # whether the current exchange's request was handed to the socket
        self._scratch = memoryview(bytearray(_READ_BYTES))
        self._direct_cap: int | None = None  # fetch's cap: a big wire answer may be read direct
        self.body: memoryview | None = None  # the body of an answer read direct
        self._room: memoryview | None = None  # its buffer, one byte longer: bytes after it show
        self._filled = 0  # bytes of it in place
        self._direct = False  # reading past the parser, into self.body

    # asyncio.BufferedProtocol

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]

    def get_buffer(self, sizehint: int) -> memoryview:
        return self._room[self._filled :] if self._direct else self._scratch  # type: ignore[index]

    def buffer_updated(self, nbytes: int) -> None:
        if not self._direct:
            self.data_received(self._scratch[:nbytes])
            return
        assert self.body is not None
        self._filled += nbytes
        self.received += nbytes
        if self._filled > len(self.body):
            # Bytes after the body in the same read, as the parser would have seen them: the
            # answer stands, the connection goes.
            self._filled = len(self.body)
            self.keep_alive = False
        self.body_received = self._filled
        if self._filled == len(self.body):
            self._direct = False
            self.done = True
            self._wake()

    def data_received(self, data: bytes | memoryview) -> None:
        if self.done and self.body is not None:
            # Bytes after an answer read direct: the parser, which saw only part of its body,
            # cannot judge them; the answer stands, the connection goes.
            self.keep_alive = False
            self.close()
            return
        if not self._active or self._parser is None or self.error is not None:
            # Bytes nobody asked for (after an answer ended, or after it failed): the connection
            # cannot be trusted.
            self.close()
            return
        self.received += len(data)
        try:
            self._parser.feed_data(data)
        except httptools.HttpParserError as exc:
            if self.done:
                self.keep_alive = False  # junk after a whole answer: the answer stands, the connection goes
            elif isinstance(exc.__context__, BrokenAnswer):
                self._fail(exc.__context__)  # a cap of a callback's own
            else:
                self._fail(BrokenAnswer(f"malformed answer: {failure_of(exc.__context__ or exc)}"))
            self.close()
            return
        # Reading stops at a cap: what one read brings past it is all that is parsed beyond it.
        framing = self.received - self.body_received
        if not self.headers_done and framing > MAX_HEAD_BYTES:  # a head still growing
            self._fail(BrokenAnswer(f"the answer's head is larger than {MAX_HEAD_BYTES} bytes"))
            self.close()
        elif framing > MAX_HEAD_BYTES + MAX_FRAMING_BYTES + _CHUNK_LINE_BYTES * self.chunks and not self.done:
            self._fail(
                BrokenAnswer(
                    f"the answer's chunk extensions and trailers are larger than {MAX_FRAMING_BYTES} bytes "
                    f"({framing} bytes of head and framing read)"
                )
            )
            self.close()
        elif self.body is not None and not self.done and not self.closed:
            self._direct = True  # the rest of the body goes straight into its buffer

    def eof_received(self) -> bool | None:
        return None  # close the transport; connection_lost says the rest

    def connection_lost(self, exc: Exception | None) -> None:
        self.closed = True
        if self._active and not self.done and self.error is None:
            if self.headers_done and self._ends_at_close():
                self.keep_alive = False
                self.done = True
            else:
                where = "before the answer's head" if not self.headers_done else "inside the answer's body"
                self.error = BrokenAnswer(f"the server closed the connection {where}")
        self._wake()

    def pause_writing(self) -> None:  # a request body larger than the socket's buffer: written all the same
        pass

    # httptools callbacks

    def on_message_begin(self) -> None:
        if self.done:
            # A second answer to one request: nothing of it is taken, and the connection, out of
            # step with its requests, is not used again.
            self.keep_alive = False

    def on_status(self, status: bytes) -> None:
        if not self.done:
            self.reason += status

    def on_header(self, name: bytes, value: bytes) -> None:
        if not self.headers_done:
            self.headers.append((name, value))
            self._head_bytes += len(name) + len(value) + 4
            if self._head_bytes > MAX_HEAD_BYTES:  # a head that arrived whole in one read
                raise BrokenAnswer(f"the answer's head is larger than {MAX_HEAD_BYTES} bytes")

    def on_headers_complete(self) -> None:
        assert self._parser is not None
        if self.done:
            return
        status = self._parser.get_status_code()
        if 100 <= status < 200:
            if status == 101:
                raise BrokenAnswer("the server switched protocols (101), which this client does not speak")
            self._informational = True  # a 100 Continue or 103: the real answer follows
            return
        self.status = status
        self.headers_done = True
        if self._head_only:
            # llhttp cannot be told an answer to HEAD has no body: the answer ends here, and the
            # connection with it (bytes after the head would be read as the next answer's).
            self.done = True
            self.keep_alive = False
        elif self._direct_cap is not None:
            length = _direct_length(status, self.headers, self._direct_cap)
            if length is not None:
                self.keep_alive = self._parser.should_keep_alive()
                self._room = memoryview(mmap.mmap(-1, length + 1))
                self.body = self._room[:length]
        self._wake()

    def on_chunk_header(self) -> None:
        self.chunks += 1

    def on_body(self, body: bytes) -> None:
        if self.done:
            return
        if self.chunks > MAX_CHUNKS:  # counted at its body: the last chunk, of none, ends the answer
            raise BrokenAnswer(
                f"the answer has more than {MAX_CHUNKS} chunks ({self.body_received} bytes of body in them)"
            )
        self.body_received += len(body)
        if self.body is not None:
            self.body[self._filled : self._filled + len(body)] = body
            self._filled += len(body)
            return
        self._pieces.append(body)
        self._buffered += len(body)
        if self._buffered > _HIGH_WATER and not self._paused and self.transport is not None:
            self._paused = True
            self.transport.pause_reading()
        self._wake()

    def on_message_complete(self) -> None:
        if self._informational:
            self._informational = False
            self.headers, self.reason = [], b""
            return
        if self.done:  # the answer to a HEAD, ended at its head, or a second answer
            return
        assert self._parser is not None
        self.keep_alive = self._parser.should_keep_alive()
        self.done = True
        self._wake()

    # the request

    def _ends_at_close(self) -> bool:
        """Whether the answer's body runs until the connection closes (no length, not chunked)."""
        if self.status in _NO_BODY or self._head_only:
            return True
        names = {name.lower() for name, _ in self.headers}
        return b"content-length" not in names and b"transfer-encoding" not in names

    async def send(self, data: bytes, head_only: bool, read_s: float | None, direct_cap: int | None = None) -> None:
        """Send one request (head and body in ``data``) and wait for its answer's head; with
        ``direct_cap``, a big wire answer up to that size is read into :attr:`body`.

        Raises:
            ReadTimedOut, BrokenAnswer: as :meth:`wait`.
        """
        self._parser = httptools.HttpResponseParser(self)
        self._active = True
        self._head_only = head_only
        self.status, self.reason, self.headers = 0, b"", []
        self.headers_done = self.done = self.keep_alive = self._informational = False
        self.error = None
        self._pieces, self._buffered = [], 0
        self._direct_cap, self.body, self._room, self._filled, self._direct = direct_cap, None, None, 0, False
        self.received = self._head_bytes = self.body_received = self.chunks = 0
        self.written = False
        self.exchanges += 1
        assert self.transport is not None
        if self.closed:  # closed under us before a byte went out: provably not sent
            raise BrokenAnswer("the connection closed before the request was written")
        self.written = True
        self.transport.write(data)
        while not self.headers_done:
            await self.wait(read_s)
            if self.done and not self.headers_done:
                raise BrokenAnswer("the answer ended without a head")

    def take(self) -> list[bytes]:
        """The body's pieces that arrived since the last take (reading resumes if it paused)."""
        pieces, self._pieces, self._buffered = self._pieces, [], 0
        if self._paused and self.transport is not None and not self.closed:
            self._paused = False
            self.transport.resume_reading()
        return pieces

    async def wait(self, timeout_s: float | None) -> None:
        """Wait for the answer to move on (its head, a piece of body, its end, a failure).

        Raises:
            ReadTimedOut: nothing arrived within ``timeout_s``.
            BrokenAnswer: the answer is malformed, past a cap, or the connection ended inside it.
        """
        if self.error is None and not self._pieces and not self.done:
            if self.closed:
                raise BrokenAnswer("the connection is closed")
            self._waiter = asyncio.get_running_loop().create_future()
            try:
                if timeout_s is None:
                    await self._waiter
                else:
                    try:
                        async with asyncio.timeout(timeout_s):
                            await self._waiter
                    except TimeoutError:
                        raise ReadTimedOut(f"no byte of the answer for {timeout_s} s") from None
            finally:
                self._waiter = None
        if self.error is not None:
            raise self.error

    def finish(self) -> bool:
        """End the exchange; return whether the connection can carry another request."""
        self._active = False
        self._parser = None
        return self.done and self.keep_alive and self.error is None and not self.closed

    def _wake(self) -> None:
        if self._waiter is not None and not self._waiter.done():
            self._waiter.set_result(None)

    def _fail(self, error: Exception) -> None:
        if self.error is None:
            self.error = error
        self._wake()

    def close(self) -> None:
        self.closed = True
        if self.transport is not None:
            self.transport.close()
        self._wake()


class _Body(httpx.AsyncByteStream):
    """An answer's body for httpx's interface: its pieces as they arrive; the connection goes
    back to its transport once the body ended, and is closed if the reader stops before."""

    def __init__(
        self, owner: HttptoolsTransport, connection: _Connection, request: httpx.Request, read_s: float | None
    ) -> None:
        self._owner = owner
        self._connection = connection
        self._request = request
        self._read_s = read_s
        self._released = False

    async def __aiter__(self) -> AsyncIterator[bytes]:
        connection = self._connection
        while True:
            try:
                with mapped(f"{self._request.method} {self._request.url}", self._request):
                    await connection.wait(self._read_s)
            except httpx.TransportError:
                self._release()
                raise
            for piece in connection.take():
                yield piece
            if connection.done:
                self._release()
                return

    def _release(self) -> None:
        if not self._released:
            self._released = True
            self._owner.release(self._connection)

    async def aclose(self) -> None:
        self._release()


class HttptoolsTransport(Transport):
    """HTTP/1.1 over asyncio connections, answers parsed by httptools; see the module's text.

    uvicorn speaks HTTP/1.1 only, so each request in flight holds a connection of its own;
    finished ones are kept per origin (scheme, host, port) for :data:`KEEPALIVE_S` and reused,
    newest first, at most ``max_idle_per_origin`` of them. An answer's head is read up to
    :data:`MAX_HEAD_BYTES`. ``https`` URLs get TLS with ``ssl_context`` (default: the system's trust store,
    the server's certificate and host name checked).
    """

    def __init__(
        self, *, ssl_context: ssl.SSLContext | None = None, max_idle_per_origin: int = MAX_IDLE_PER_ORIGIN
    ) -> None:
        if max_idle_per_origin < 0:
            raise ValueError(f"max_idle_per_origin must be >= 0, got {max_idle_per_origin}")
        self._max_idle = max_idle_per_origin
        self._idle: dict[tuple[str, str, int], list[_Connection]] = {}
        self._busy: set[_Connection] = set()
        self._heads: dict[tuple[str, str, tuple[tuple[str, str], ...]], tuple[tuple[str, str, int], bytes]] = {}
        self._ssl = ssl_context
        self._closed = False

    # connections

    async def _connection(
        self, origin: tuple[str, str, int], connect_s: float | None, fresh: bool = False
    ) -> _Connection:
        if self._closed:
            raise RuntimeError("the transport is closed")
        idle = None if fresh else self._idle.get(origin)
        now = time.monotonic()
        while idle:
            connection = idle.pop()
            if not connection.closed and now - connection.idle_since < KEEPALIVE_S:
                self._busy.add(connection)
                return connection
            connection.close()
        scheme, host, port = origin
        if scheme == "https" and self._ssl is None:
            self._ssl = ssl.create_default_context()
        tls = self._ssl if scheme == "https" else None
        loop = asyncio.get_running_loop()
        with mapped(f"cannot connect to {host}:{port}"):
            try:
                async with asyncio.timeout(connect_s):
                    _, connection = await loop.create_connection(
                        lambda: _Connection(origin), host, port, ssl=tls, server_hostname=host if tls else None
                    )
            except TimeoutError:  # before the table's OSError: a TimeoutError is one
                raise ConnectTimedOut(f"no connection within {connect_s} s") from None
        self._busy.add(connection)
        return connection

    def release(self, connection: _Connection) -> None:
        """Take a connection back after its exchange: kept if it can carry another, else closed."""
        self._busy.discard(connection)
        idle = self._idle.setdefault(connection.origin, [])
        if connection.finish() and not self._closed and len(idle) < self._max_idle:
            connection.idle_since = time.monotonic()
            idle.append(connection)
        else:
            connection.close()

    async def _send(
        self,
        origin: tuple[str, str, int],
        data: bytes,
        head_only: bool,
        connect_s: float | None,
        read_s: float | None,
        resendable: bool,
        direct_cap: int | None = None,
    ) -> _Connection:
        """Send one request on a connection to ``origin`` and wait for its answer's head; return
        the connection, which the caller releases once the answer is read.

        A reused connection that ends before the first byte of its answer is most often the race
        of a server closing it idle as the request went out (a pod whose keep-alive is below
        :data:`KEEPALIVE_S`); but the server may also have read the request, applied it and then
        lost the connection. So the request is sent once more, on a new connection, only when
        that is safe: it was provably not written (the connection had closed before), or it is
        ``resendable`` (an idempotent method, or a request carrying an ``Idempotency-Key``: the
        server answers its repeat from memory). Else :class:`MayHaveBeenAppliedError`. A new
        connection that ends so is an error at once.

        Raises:
            MayHaveBeenAppliedError: as said.
            as :meth:`_connection` and :meth:`_Connection.send`.
        """
        connection = await self._connection(origin, connect_s)
        try:
            await connection.send(data, head_only, read_s, direct_cap)
            return connection
        except httpx.RemoteProtocolError as exc:
            closed_idle = connection.exchanges > 1 and connection.received == 0 and connection.closed
            written = connection.written
            self.release(connection)
            if not closed_idle:
                raise
            if written and not resendable:
                raise MayHaveBeenAppliedError(
                    f"{exc}, and the request may have been applied: it is not sent again "
                    f"(not an idempotent method, no {IDEMPOTENCY_KEY} header)"
                ) from None
        except BaseException:
            self.release(connection)
            raise
        connection = await self._connection(origin, connect_s, fresh=True)
        try:
            await connection.send(data, head_only, read_s, direct_cap)
        except BaseException:
            self.release(connection)
            raise
        return connection

    # requests

    @staticmethod
    def _origin(url: httpx.URL) -> tuple[str, str, int]:
        if url.scheme not in ("http", "https"):
            raise UnsupportedURL(f"{url}: only http and https URLs are supported")
        if not url.host:
            raise UnsupportedURL(f"{url}: no host")
        return url.scheme, url.host, url.port or (443 if url.scheme == "https" else 80)

    @staticmethod
    def _head(method: str, url: httpx.URL, headers: Iterable[tuple[bytes, bytes]], length: int | None) -> bytes:
        """The request's head: its line, ``headers`` (a Host added if missing), a Content-Length."""
        lines = [b"%s %s HTTP/1.1" % (method.encode("ascii"), url.raw_path)]
        has_host = False
        for name, value in headers:
            if _bad_header_text(name) or _bad_header_text(value) or b":" in name or not name:
                raise UnsendableRequest(f"header {name[:40]!r}: {value[:40]!r} cannot be sent")
            lower = name.lower()
            if lower in (b"content-length", b"transfer-encoding"):
                continue  # the body is sent whole, with its own length
            has_host = has_host or lower == b"host"
            lines.append(name + b": " + value)
        if not has_host:
            lines.insert(1, b"Host: " + url.netloc)
        if length is not None:
            lines.append(b"Content-Length: %d" % length)
        return b"\r\n".join(lines) + b"\r\n\r\n"

    async def handle_async_request(self, request: httpx.Request) -> httpx.Response:
        """Send ``request``; return its answer's status and headers, the body streaming on reading.

        httpx's ``connect`` timeout bounds making a connection and ``read`` each wait for the
        answer's next bytes; a whole request is bounded by the caller (``asyncio.timeout``).

        Raises:
            httpx.ConnectError, httpx.ConnectTimeout, httpx.ReadTimeout, httpx.RemoteProtocolError,
            httpx.LocalProtocolError, httpx.UnsupportedProtocol: as the module's text says.
        """
        timeouts = request.extensions.get("timeout", {})
        body = await request.aread()
        with mapped(f"{request.method} {request.url}", request):
            origin = self._origin(request.url)
            send_length = bool(body) or request.method in ("POST", "PUT", "PATCH")
            head = self._head(request.method, request.url, request.headers.raw, len(body) if send_length else None)
            resendable = request.method in _IDEMPOTENT_METHODS or IDEMPOTENCY_KEY in request.headers
            connection = await self._send(
                origin, head + body, request.method == "HEAD", timeouts.get("connect"), timeouts.get("read"), resendable
            )
        return httpx.Response(
            connection.status,
            headers=connection.headers,
            stream=_Body(self, connection, request, timeouts.get("read")),
            extensions={"http_version": b"HTTP/1.1", "reason_phrase": connection.reason},
        )

    def _cached_head(
        self, method: str, url: str, headers: tuple[tuple[str, str], ...]
    ) -> tuple[tuple[str, str, int], bytes]:
        """The origin and the head (without its Content-Length) of a request, made once per kind."""
        key = (method, url, headers)
        cached = self._heads.get(key)
        if cached is None:
            parsed = httpx.URL(url)
            encoded = [(k.encode("latin-1"), v.encode("latin-1")) for k, v in headers]
            head = self._head(method, parsed, encoded, None)[:-2]  # open: the Content-Length follows
            if len(self._heads) >= _CACHED_HEADS:
                self._heads.clear()
            cached = self._heads[key] = (self._origin(parsed), head)
        return cached

    async def fetch(
        self, method: str, url: str, headers: tuple[tuple[str, str], ...], body: bytes, max_bytes: int
    ) -> tuple[int, bytes | memoryview]:
        """Send one request and read its answer whole under the cap ``max_bytes``, decoding a
        gzip or deflate Content-Encoding, as ``vecsim.transport.read_answer`` does; no httpx
        objects on the way. The caller bounds it in time (``asyncio.timeout``).

        Returns:
            the answer's status code and its decoded body: for a 200 wire answer of
            :data:`DIRECT_BYTES` or more, a ``memoryview`` of the buffer it was read into; else
            ``bytes``.

        Raises:
            vecsim.transport.AnswerTooLargeError, httpx.DecodingError: as ``read_answer``.
            httpx.ConnectError, httpx.RemoteProtocolError, httpx.LocalProtocolError,
            httpx.UnsupportedProtocol: as the module's text says.
        """
        with mapped():
            # A key is new on every call: it goes after the head made once per kind of request.
            key = [value for name, value in headers if name.lower() == _KEY_LOWER]
            if key:
                headers = tuple((name, value) for name, value in headers if name.lower() != _KEY_LOWER)
            origin, head = self._cached_head(method, url, headers)
            keyed = b"".join(b"%s: %s\r\n" % (IDEMPOTENCY_KEY.encode(), _header_value(v)) for v in key)
            data = b"%s%sContent-Length: %d\r\n\r\n%s" % (head, keyed, len(body), body)
            connection = await self._send(
                origin, data, method == "HEAD", None, None, bool(key) or method in _IDEMPOTENT_METHODS, max_bytes
            )
            try:
                if connection.body is not None:
                    while not connection.done:
                        await connection.wait(None)
                    return connection.status, connection.body
                reader = AnswerReader(url, _text_headers(connection.headers), max_bytes)
                while True:
                    for piece in connection.take():
                        for _ in reader.feed(piece):
                            await asyncio.sleep(0)
                    if connection.done:
                        break
                    await connection.wait(None)
                return connection.status, reader.finish()
            finally:
                self.release(connection)

    async def aclose(self) -> None:
        """Close every connection, idle or in use."""
        self._closed = True
        for connections in self._idle.values():
            for connection in connections:
                connection.close()
        self._idle.clear()
        for connection in list(self._busy):
            connection.close()
        self._busy.clear()
        await asyncio.sleep(0)  # one turn of the loop: the closed connections let go of their sockets


def _text_headers(headers: Sequence[tuple[bytes, bytes]]) -> list[tuple[str, str]]:
    return [(name.decode("latin-1"), value.decode("latin-1")) for name, value in headers]


_WIRE_TYPE = wire.CONTENT_TYPE.encode()


def _direct_length(status: int, headers: list[tuple[bytes, bytes]], cap: int) -> int | None:
    """The body's length, when an answer with this head is read past the parser
    (:data:`DIRECT_BYTES`); None when it is parsed (and its reader checks it)."""
    if status != 200:
        return None
    lengths, types = [], []
    for name, value in headers:
        lower = name.lower()
        if lower in (b"transfer-encoding", b"content-encoding"):
            return None
        if lower == b"content-length":
            lengths.append(value.strip())
        elif lower == b"content-type":
            types.append(value.split(b";", 1)[0].strip().lower())
    if types != [_WIRE_TYPE] or len(lengths) != 1 or not lengths[0].isdigit() or len(lengths[0]) > 18:
        return None
    length = int(lengths[0])
    return length if DIRECT_BYTES <= length <= cap else None
