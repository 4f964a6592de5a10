"""Reading request bodies and writing answers in the two formats the pod speaks.

A request body is wire (``Content-Type: application/x-vecsim``) or JSON
(``Content-Type: application/json``); an answer is wire unless the caller's ``Accept`` asks for
JSON and not for wire. Bodies are size-limited twice: by the announced ``Content-Length`` and by
the bytes actually read.
"""

from __future__ import annotations

import json
from typing import Any, TypeVar

from fastapi import Request, Response
from pydantic import BaseModel, ValidationError

from service.http import describe_validation_error
from vecsim import wire
from vecsim.engine import InvalidRequestError

from .errors import MalformedBodyError, UnsupportedMediaTypeError

JSON_TYPE = "application/json"
M = TypeVar("M", bound=BaseModel)


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
