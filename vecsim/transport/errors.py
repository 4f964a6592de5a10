"""The transport's failures, each named once, and the one map from them, and from what the
wrapped libraries raise (the socket's ``OSError``, llhttp's parser errors, zlib's), to httpx's
exceptions, as httpx keeps its map of httpcore's in ``httpx/_transports/default.py``.

Inside the transport a failure is one of the kinds below (each a subclass of the httpx exception
it leaves as, so transport code may catch either). :func:`mapped` is the transport's edge: what
leaves it is httpx's own type (``BrokenAnswer`` leaves as ``httpx.RemoteProtocolError``, ...),
or :class:`AnswerTooLargeError`, carrying the request it belongs to and naming it.

    with mapped(f"GET {url}", request):
        ...  # an OSError raised here leaves as httpx.ConnectError("GET <url>: ...")
"""

from __future__ import annotations

import contextlib
import zlib
from collections.abc import Iterator

import httptools
import httpx

__all__ = [
    "AnswerTooLargeError",
    "BrokenAnswer",
    "ConnectFailed",
    "ConnectTimedOut",
    "ReadTimedOut",
    "UndecodableAnswer",
    "UnsendableRequest",
    "UnsupportedURL",
    "failure_of",
    "mapped",
]


class ConnectFailed(httpx.ConnectError):
    """No connection could be made (refused, unreachable, the TLS handshake failed)."""


class ConnectTimedOut(httpx.ConnectTimeout):
    """No connection within the connect timeout."""


class ReadTimedOut(httpx.ReadTimeout):
    """No byte of the answer within the read timeout."""


class BrokenAnswer(httpx.RemoteProtocolError):
    """The answer is not HTTP/1.1, passes one of the caps on its head, framing or chunks, or the
    connection ended inside it."""


class UnsendableRequest(httpx.LocalProtocolError):
    """The request cannot be written (a header that would split it)."""


class UnsupportedURL(httpx.UnsupportedProtocol):
    """The URL is not http or https, or names no host."""


class UndecodableAnswer(httpx.DecodingError):
    """The answer's body cannot be read: its Content-Length or Content-Encoding is unusable."""


class AnswerTooLargeError(UndecodableAnswer):
    """An answer (announced or received, encoded or decoded) is larger than the cap."""


# What each failure leaves the transport as.
_PUBLIC: dict[type[httpx.TransportError], type[httpx.TransportError]] = {
    ConnectFailed: httpx.ConnectError,
    ConnectTimedOut: httpx.ConnectTimeout,
    ReadTimedOut: httpx.ReadTimeout,
    BrokenAnswer: httpx.RemoteProtocolError,
    UnsendableRequest: httpx.LocalProtocolError,
    UnsupportedURL: httpx.UnsupportedProtocol,
    UndecodableAnswer: httpx.DecodingError,
    AnswerTooLargeError: AnswerTooLargeError,
}
# What the wrapped libraries raise, and the failure each is; the first match wins.
_WRAPPED: tuple[tuple[type[BaseException], type[httpx.TransportError]], ...] = (
    (httptools.HttpParserError, BrokenAnswer),
    (zlib.error, UndecodableAnswer),
    (TimeoutError, ReadTimedOut),  # an OSError too; a connect's own is named where it happens
    (OSError, ConnectFailed),
)


def failure_of(exc: BaseException) -> httpx.TransportError | None:
    """``exc`` as the transport's failure: itself if it is one, its type in the table if a wrapped
    library raised it, else None (not the transport's to name)."""
    if isinstance(exc, httpx.TransportError):
        return exc
    if isinstance(exc, httptools.HttpParserCallbackError) and isinstance(exc.__context__, httpx.TransportError):
        return exc.__context__  # a cap raised inside one of the parser's callbacks
    for wrapped, failure in _WRAPPED:
        if isinstance(exc, wrapped):
            return failure(str(exc) or type(exc).__name__)
    return None


@contextlib.contextmanager
def mapped(where: str = "", request: httpx.Request | None = None) -> Iterator[None]:
    """Let the block's failures (see :func:`failure_of`) leave as httpx's exceptions, their
    message prefixed with ``where`` (the request, or the host, they belong to) and carrying
    ``request`` when there is one. Anything else passes unchanged."""
    try:
        yield
    except Exception as exc:
        failure = failure_of(exc)
        if failure is None:
            raise
        message = f"{where}: {failure}" if where and not str(failure).startswith(where) else str(failure)
        raise _PUBLIC.get(type(failure), type(failure))(message, request=request) from None
