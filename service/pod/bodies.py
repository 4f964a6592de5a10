"""Reading request bodies and writing answers in the two formats the pod speaks.

A request body is wire (``Content-Type: application/x-vecsim``) or JSON
(``Content-Type: application/json``); an answer is wire unless the caller's ``Accept`` asks for
JSON and not for wire. Bodies are size-limited twice: by the announced ``Content-Length`` and by
the bytes actually read.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any, TypeVar

from fastapi import Request, Response
from fastapi.responses import JSONResponse
from pydantic import BaseModel, ValidationError
from starlette.datastructures import Headers
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from vecsim import wire

from .errors import InvalidRequestError, MalformedBodyError, UnsupportedMediaTypeError
from .models import describe_validation_error

JSON_TYPE = "application/json"
M = TypeVar("M", bound=BaseModel)


def _media_type(header: str | None) -> str:
    return (header or "").split(";", 1)[0].strip().lower()


def wants_json(request: Request) -> bool:
    """Whether the answer should be JSON: ``Accept`` names JSON and does not name the wire."""
    accepted = {_media_type(part) for part in request.headers.get("accept", "").split(",")}
    return JSON_TYPE in accepted and wire.CONTENT_TYPE not in accepted


class BodyLimitMiddleware:
    """Refuses every request whose body exceeds ``limit`` bytes with 413, before any route sees
    it: at once when ``Content-Length`` says so, else as soon as the bytes read pass the limit.

    The body is read whole here and replayed to the app, so routes read it with
    ``await request.body()``. ``server`` names whose limit it is in the 413's detail.
    """

    def __init__(
        self, app: ASGIApp, limit: int, on_refused: Callable[[], None], server: str = "this pod"
    ) -> None:
        self.app = app
        self.limit = limit
        self.on_refused = on_refused
        self.server = server

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = Headers(scope=scope).get("content-length")
        if declared is not None and declared.isdigit() and int(declared) > self.limit:
            await self._refuse(
                scope, receive, send, f"body of {declared} bytes exceeds {self.server}'s limit of {self.limit} bytes"
            )
            return
        chunks: list[bytes] = []
        size = 0
        while True:
            message = await receive()
            if message["type"] != "http.request":
                break
            chunk = message.get("body", b"")
            size += len(chunk)
            if size > self.limit:
                await self._refuse(scope, receive, send, f"body exceeds {self.server}'s limit of {self.limit} bytes")
                return
            chunks.append(chunk)
            if not message.get("more_body", False):
                break
        replayed = False

        async def replay() -> Message:
            nonlocal replayed
            if replayed:
                return await receive()
            replayed = True
            return {"type": "http.request", "body": b"".join(chunks), "more_body": False}

        await self.app(scope, replay, send)

    async def _refuse(self, scope: Scope, receive: Receive, send: Send, detail: str) -> None:
        self.on_refused()
        response = JSONResponse({"detail": detail}, status_code=413)
        await response(scope, receive, send)


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


def encode_answer(obj: dict[str, Any], as_json: bool) -> Response:
    """``obj`` as a JSON or wire response; called on the worker thread, which keeps the copy of
    every array (or the JSON rendering) off the event loop.

    Returns:
        The response, ready to send.
    """
    if as_json:
        content = json.dumps(wire.to_jsonable(obj), separators=(",", ":"), allow_nan=False).encode()
        return Response(content=content, media_type=JSON_TYPE)
    return Response(content=wire.encode(obj), media_type=wire.CONTENT_TYPE)
