"""Reading an answer's body under a size cap, whatever carried it: the checks of its headers,
its pieces counted as they arrive, a gzip or deflate Content-Encoding decoded once, a bounded
piece at a time (:class:`AnswerReader`, sans I/O: the callers feed it the pieces they receive),
and the readers of a streamed httpx response (:func:`read_answer`, :func:`send_capped`: the
controller's pushes to pods).
"""

from __future__ import annotations

import asyncio
import zlib
from collections.abc import Iterator
from typing import Any

import httpx

from .errors import AnswerTooLargeError, UndecodableAnswer, mapped

__all__ = [
    "DEFAULT_MAX_ANSWER_BYTES",
    "MAX_CONTROL_ANSWER_BYTES",
    "AnswerReader",
    "AnswerTooLargeError",
    "read_answer",
    "send_capped",
]

# The cap on one answer when nothing better is known (before a job's spaces are read).
DEFAULT_MAX_ANSWER_BYTES = 64 << 20
# The cap on a JSON answer of the control plane (a routing table, a pod's /v1/info): a job of
# thousands of pods and tasks stays far below it.
MAX_CONTROL_ANSWER_BYTES = 16 << 20

# Decoded output per step of a Content-Encoding: a piece the event loop can afford between yields.
_DECODE_STEP = 1 << 20


def _decoder(encoding: str, url: str, request: httpx.Request | None) -> Any:
    """A zlib decompressor for a Content-Encoding, or None for identity."""
    if encoding in ("", "identity"):
        return None
    if encoding in ("gzip", "x-gzip"):
        return zlib.decompressobj(zlib.MAX_WBITS | 16)
    if encoding == "deflate":
        return zlib.decompressobj(zlib.MAX_WBITS)
    raise UndecodableAnswer(f"{url}: unsupported Content-Encoding {encoding!r}", request=request)


def _values(headers: list[tuple[str, str]], name: str) -> list[str]:
    """The values of header ``name`` (any case), each split at its commas."""
    return [part for key, value in headers if key.lower() == name for part in value.split(",")]


class AnswerReader:
    """The sans-I/O part of reading an answer under a cap: checks the headers, then takes the raw
    body a piece at a time (:meth:`feed`) and gives the decoded body (:meth:`finish`).

    ``url`` names the answer in errors; ``headers`` are its (name, value) pairs; ``request``, when
    there is one, goes with the errors raised.

    Raises (from any method):
        AnswerTooLargeError: Content-Length, the bytes received or the decoded bytes exceed
            ``max_bytes``.
        httpx.DecodingError: an unreadable Content-Length, an unsupported or corrupt encoding.
    """

    def __init__(
        self, url: str, headers: list[tuple[str, str]], max_bytes: int, request: httpx.Request | None = None
    ) -> None:
        self._url = url
        self._request = request
        self._max = max_bytes
        declared = [value.strip() for value in _values(headers, "content-length")]
        if declared:
            if len(set(declared)) != 1 or not declared[0].isdigit():
                raise UndecodableAnswer(f"{url}: bad Content-Length {declared[:4]!r:.100}", request=request)
            if int(declared[0]) > max_bytes:
                raise AnswerTooLargeError(
                    f"{url}: Content-Length {declared[0][:40]} exceeds the cap of {max_bytes} bytes", request=request
                )
        encodings = [e.strip().lower() for e in _values(headers, "content-encoding")]
        encodings = [e for e in encodings if e not in ("", "identity")]
        if len(encodings) > 1:
            raise UndecodableAnswer(f"{url}: stacked Content-Encodings {encodings!r:.100}", request=request)
        self._encoding = encodings[0] if encodings else ""
        self._decoder = _decoder(self._encoding, url, request)
        self._pieces: list[bytes] = []
        self._received = self._size = 0

    @classmethod
    def of(cls, response: httpx.Response, max_bytes: int) -> AnswerReader:
        """The reader of a streamed httpx response."""
        return cls(str(response.request.url), response.headers.multi_items(), max_bytes, response.request)

    def _too_large(self, what: str) -> AnswerTooLargeError:
        return AnswerTooLargeError(f"{self._url}: {what} exceeds the cap of {self._max} bytes", request=self._request)

    def feed(self, piece: bytes) -> Iterator[None]:
        """Take one raw piece of the body; yields between bounded steps of decoding it."""
        self._received += len(piece)
        if self._received > self._max:
            raise self._too_large("answer")
        if self._decoder is None:
            self._pieces.append(piece)
            return
        while piece:
            with mapped(f"{self._url}: corrupt {self._encoding} body", self._request):
                out = self._decoder.decompress(piece, min(_DECODE_STEP, self._max - self._size + 1))
            self._size += len(out)
            if self._size > self._max:
                raise self._too_large("decoded answer")
            self._pieces.append(out)
            piece = self._decoder.unconsumed_tail
            if piece:
                yield

    def finish(self) -> bytes:
        """The whole decoded body, once the raw body has ended."""
        if self._decoder is not None:
            if not self._decoder.eof:
                raise UndecodableAnswer(f"{self._url}: truncated {self._encoding} body", request=self._request)
            rest = self._decoder.flush()
            if self._size + len(rest) > self._max:
                raise self._too_large("decoded answer")
            self._pieces.append(rest)
        return b"".join(self._pieces)


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
        with mapped(request=response.request):
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
    """Send ``request`` through ``http`` (an ``httpx.AsyncClient`` on a transport) and read the
    answer whole under the cap ``max_bytes``, as :func:`read_answer` does: how the controller reads
    a pod's answer to a push. Callers bound the whole exchange with ``asyncio.timeout``.

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
