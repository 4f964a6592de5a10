"""HTTP plumbing both servers (pod and controller) use: the request body limit and the one-line
description of a validation error."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from fastapi.responses import JSONResponse
from pydantic import ValidationError
from starlette.datastructures import Headers
from starlette.types import ASGIApp, Message, Receive, Scope, Send


def describe_validation_error(exc: ValidationError | Any) -> str:
    """One line naming each field at fault and what is wrong with it.

    Accepts a pydantic ``ValidationError`` or anything with an ``errors()`` list of the same
    shape (FastAPI's ``RequestValidationError``).
    """
    parts = []
    for err in exc.errors():
        loc = [str(p) for p in err.get("loc", ()) if p != "body"]
        msg = err.get("msg", "invalid").removeprefix("Value error, ")
        parts.append(f"{'.'.join(loc) or 'body'}: {msg}")
    return "; ".join(parts)


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
