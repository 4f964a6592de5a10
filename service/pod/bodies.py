"""Reading request bodies and writing answers in the two formats the pod speaks.

A request body is wire (``Content-Type: application/x-vecsim``) or JSON
(``Content-Type: application/json``); an answer is wire unless the caller's ``Accept`` asks for
JSON and not for wire. Bodies are size-limited twice: by the announced ``Content-Length`` and by
the bytes actually read.

A wire answer is never joined into one body when it is large: :class:`Answer` keeps the encoded
parts (views of the answer's own arrays) and sends them in slices of at most
:data:`SLICE_BYTES`, each once the connection has taken the last (uvicorn's flow control).
"""

from __future__ import annotations

import json
from collections.abc import Iterator, Sequence
from typing import Any, TypeVar

from fastapi import Request, Response
from pydantic import BaseModel, ValidationError

from service.http import describe_validation_error
from vecsim import wire
from vecsim.engine import InvalidRequestError

from .errors import MalformedBodyError, UnsupportedMediaTypeError

JSON_TYPE = "application/json"
M = TypeVar("M", bound=BaseModel)
# An answer up to this size is joined into one body and written at once; a larger one is sent in
# slices of about this size, straight from its arrays: a slice fits the socket's send buffer, so
# it mostly goes out without a copy into the event loop's write buffer.
SLICE_BYTES = 1 << 20


def _media_type(header: str | None) -> str:
    return (header or "").split(";", 1)[0].strip().lower()


def wants_json(request: Request) -> bool:
    """Whether the answer should be JSON: ``Accept`` names JSON and does not name the wire."""
    accepted = {_media_type(part) for part in request.headers.get("accept", "").split(",")}
    return JSON_TYPE in accepted and wire.CONTENT_TYPE not in accepted


def parse_body(request: Request, body: bytes, model: type[M]) -> M:
    """Decode ``body`` by the request's ``Content-Type`` and validate it as ``model``.

    Returns:
        The validated request.

    Raises:
        UnsupportedMediaTypeError: neither JSON nor the wire (415).
        MalformedBodyError: the body is not valid JSON or wire (400).
        InvalidRequestError: a field is missing or has the wrong type (422, field named).
    """
    media_type = _media_type(request.headers.get("content-type"))
    if media_type == wire.CONTENT_TYPE:
        try:
            obj: Any = wire.decode(body)
        except (wire.WireError, ValueError, RecursionError) as exc:
            raise MalformedBodyError(f"body is not valid {wire.CONTENT_TYPE}: {_reason(exc)}") from None
    elif media_type == JSON_TYPE:
        try:
            obj = json.loads(body)
        # ValueError: not JSON, not UTF-8, or an integer past Python's digit limit; RecursionError:
        # nesting deeper than the parser's stack.
        except (ValueError, RecursionError) as exc:
            raise MalformedBodyError(f"body is not valid JSON: {_reason(exc)}") from None
    else:
        raise UnsupportedMediaTypeError(
            f"Content-Type {media_type or '(none)'!r} is not supported; send {JSON_TYPE} or {wire.CONTENT_TYPE}"
        )
    if not isinstance(obj, dict):
        raise InvalidRequestError(f"body: expected an object with fields, got {type(obj).__name__}")
    try:
        return model.model_validate(obj)
    except ValidationError as exc:
        raise InvalidRequestError(describe_validation_error(exc)) from None
    except (ValueError, RecursionError) as exc:
        # Arrays nested past numpy's or the interpreter's depth, numbers past the digit limit.
        raise MalformedBodyError(f"body cannot be read as a request: {_reason(exc)}") from None


def _reason(exc: BaseException) -> str:
    if isinstance(exc, RecursionError):
        return "nested too deeply"
    return str(exc)[:300]


class Answer(Response):
    """A pod's answer to a reset or step, kept as the parts of its body (bytes or byte views) so
    that it can be sent, and sent again to a repeated request, without joining them.

    The parts must not change after it is made: they are views of arrays that belong to the answer
    (an engine's results are the caller's, :class:`~vecsim.engine.base.PodEngine`), and the pod
    may send them while the next call runs.
    """

    def __init__(self, parts: Sequence[bytes | memoryview], media_type: str) -> None:
        self.parts = tuple(parts)
        self.nbytes = sum(len(part) for part in self.parts)
        self.status_code = 200
        self.media_type = media_type
        self.background = None
        self.init_headers({"content-length": str(self.nbytes)})

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        await send({"type": "http.response.start", "status": self.status_code, "headers": self.raw_headers})
        if self.nbytes <= SLICE_BYTES:
            await send({"type": "http.response.body", "body": b"".join(self.parts)})
            return
        for piece in slices(self.parts, SLICE_BYTES):
            # Each send waits until the connection took the last slice (flow control), and is a
            # no-op once the client has gone.
            await send({"type": "http.response.body", "body": piece, "more_body": True})
        await send({"type": "http.response.body", "body": b""})

    def again(self) -> Answer:
        """The same answer, to send to a repeated request."""
        return Answer(self.parts, self.media_type)


def slices(parts: Sequence[bytes | memoryview], size: int) -> Iterator[bytes | memoryview]:
    """The concatenation of ``parts`` as pieces of about ``size`` bytes: parts of ``size`` or more
    cut into views, runs of smaller ones joined (at most ``2 * size`` bytes a piece)."""
    pending: list[bytes | memoryview] = []
    pending_bytes = 0
    for part in parts:
        n = len(part)
        if n < size:
            pending.append(part)
            pending_bytes += n
            if pending_bytes >= size:
                yield b"".join(pending)
                pending, pending_bytes = [], 0
            continue
        if pending:
            yield b"".join(pending)
            pending, pending_bytes = [], 0
        view = memoryview(part)
        for start in range(0, n, size):
            yield view[start : start + size]
    if pending:
        yield b"".join(pending)


def encode_answer(obj: dict[str, Any], as_json: bool) -> Answer:
    """``obj`` as a JSON or wire answer; called on the worker thread, which keeps the JSON
    rendering, the wire header and the joining of small answers off the event loop.

    Returns:
        The answer, ready to send.
    """
    if as_json:
        content = json.dumps(wire.to_jsonable(obj), separators=(",", ":"), allow_nan=False).encode()
        return Answer((content,), JSON_TYPE)
    parts = wire.encode_parts(obj)
    if sum(len(part) for part in parts) <= SLICE_BYTES:
        parts = [b"".join(parts)]  # a snapshot: nothing of it refers to the engine's arrays
    return Answer(parts, wire.CONTENT_TYPE)
