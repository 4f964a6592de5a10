"""The one interface between the client and the bytes on the wire (see ``vecsim.transport``)."""

from __future__ import annotations

import abc

import httpx

__all__ = ["KEEPALIVE_S", "Transport"]

# Idle connections are dropped before uvicorn's keep-alive timeout would close them under us
# (the pod's default is 5 s); a pod set lower can still close one as a request goes out on it,
# which is why HttptoolsTransport tries a reused connection that ends before any byte of its
# answer once anew.
KEEPALIVE_S = 4.0


class Transport(httpx.AsyncBaseTransport, abc.ABC):
    """How the client reaches pods: :meth:`fetch` for every call to a pod, ``aclose`` at the end,
    and httpx's ``handle_async_request`` so that an ``httpx.AsyncClient`` can sit on the same
    connections (the controller's pushes to pods).

    Every implementation raises httpx's exceptions (those of ``vecsim.transport.errors``:
    ``ConnectFailed``, ``BrokenAnswer``, ...) and reads answers through
    :class:`~vecsim.transport.answers.AnswerReader`, so callers handle one set of failures.
    """

    @abc.abstractmethod
    async def fetch(
        self, method: str, url: str, headers: tuple[tuple[str, str], ...], body: bytes, max_bytes: int
    ) -> tuple[int, bytes | memoryview]:
        """Send one request and read its answer whole under the cap ``max_bytes``, decoding a gzip
        or deflate Content-Encoding. The caller bounds it in time (``asyncio.timeout``).

        Returns:
            the answer's status code and its decoded body (bytes-like: a big wire answer may
            come as a ``memoryview`` of the buffer it was read into).

        Raises:
            vecsim.transport.AnswerTooLargeError, httpx.DecodingError: the answer is over the cap
                or cannot be decoded.
            httpx.HTTPError: what the transport met (refused connection, malformed answer, ...).
        """
