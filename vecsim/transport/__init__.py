"""How the client's bytes reach a pod: one interface, :class:`Transport`, and its implementations.

Laid out as uvicorn lays out its HTTP protocols: the interface in ``base``, one file per
implementation, named for what it wraps (``httptools_impl``: vecsim's HTTP/1.1 client on llhttp,
the one over sockets; ``httpx_impl``: an in-process httpx transport, ``httpx.ASGITransport(app)``
for a pod served in the test's process), and the choice in ``auto``. The client calls
:meth:`Transport.fetch` for every call to a pod, whatever the implementation, so tests over an
in-process pod take the same path as production; the control plane's blocking GETs take it too
(``control``). Every part of an answer is capped: head, chunk extensions and trailers, chunks
(``httptools_impl``) and body (``answers``: a Content-Length over the cap is refused before a byte
of body is read, a body that grows past it is dropped as soon as it does, and a gzip or deflate
Content-Encoding is decoded once, a bounded piece at a time). Failures are httpx's exceptions
(and :class:`AnswerTooLargeError`, an ``httpx.DecodingError``), mapped in one table (``errors``).

    transport = make_transport()                   # HttptoolsTransport
    status, body = await transport.fetch("GET", "http://127.0.0.1:8100/v1/info", (), b"", 1 << 20)
    await transport.aclose()
"""

from __future__ import annotations

from .answers import (
    DEFAULT_MAX_ANSWER_BYTES,
    MAX_CONTROL_ANSWER_BYTES,
    AnswerReader,
    read_answer,
    send_capped,
)
from .auto import DEFAULT_KIND, TransportKind, as_transport, make_async_client, make_transport
from .base import KEEPALIVE_S, Transport
from .control import get_answer
from .errors import AnswerTooLargeError
from .httptools_impl import MAX_CHUNKS, MAX_FRAMING_BYTES, MAX_HEAD_BYTES, HttptoolsTransport
from .httpx_impl import HttpxTransport

__all__ = [
    "DEFAULT_KIND",
    "DEFAULT_MAX_ANSWER_BYTES",
    "KEEPALIVE_S",
    "MAX_CHUNKS",
    "MAX_CONTROL_ANSWER_BYTES",
    "MAX_FRAMING_BYTES",
    "MAX_HEAD_BYTES",
    "AnswerReader",
    "AnswerTooLargeError",
    "HttptoolsTransport",
    "HttpxTransport",
    "Transport",
    "TransportKind",
    "as_transport",
    "get_answer",
    "make_async_client",
    "make_transport",
    "read_answer",
    "send_capped",
]
