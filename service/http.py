"""HTTP plumbing both servers (pod and controller) use: the request body limit, the one-line
description of a validation error, and the job's bearer token: the middleware that checks it
(:mod:`vecsim.auth` holds the check itself, which the client shares) and its OpenAPI description."""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

from fastapi.responses import JSONResponse
from pydantic import ValidationError
from starlette.datastructures import Headers
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from vecsim.auth import OPEN_METHODS, TOKEN_ENV, authorization_problem, check_token

# The OpenAPI security scheme that names the job's token.
SECURITY_SCHEME = "vecsimToken"


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

    def __init__(self, app: ASGIApp, limit: int, on_refused: Callable[[], None], server: str = "this pod") -> None:
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


class BearerTokenMiddleware:
    """ASGI middleware: a request with a method outside :data:`OPEN_METHODS` gets 401 unless it
    carries ``token``; nothing of the request (not even its body) is read before the check.

    ``server`` names the server in the 401's ``detail`` (``"pod sim-0"``, ``"the controller"``);
    ``on_refused`` is called once per refused request (a metric). With ``token`` None every
    request passes.
    """

    def __init__(
        self, app: ASGIApp, token: str | None, server: str, on_refused: Callable[[], None] | None = None
    ) -> None:
        self.app = app
        self.token = check_token(token)
        self.server = server
        self.on_refused = on_refused

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or self.token is None or scope["method"] in OPEN_METHODS:
            await self.app(scope, receive, send)
            return
        header = None
        for name, value in scope.get("headers", ()):
            if name == b"authorization":
                header = value.decode("latin-1")
                break
        problem = authorization_problem(header, self.token, self.server)
        if problem is None:
            await self.app(scope, receive, send)
            return
        if self.on_refused is not None:
            self.on_refused()
        body = json.dumps({"detail": problem}).encode()
        await send(
            {
                "type": "http.response.start",
                "status": 401,
                "headers": [
                    (b"content-type", b"application/json"),
                    (b"content-length", str(len(body)).encode()),
                    (b"www-authenticate", b'Bearer realm="vecsim"'),
                ],
            }
        )
        await send({"type": "http.response.body", "body": body})


def document_bearer_security(schema: dict[str, Any]) -> dict[str, Any]:
    """Mark every operation of an OpenAPI ``schema`` whose method changes state as needing the
    bearer token, with its 401 answer. Changes ``schema`` in place.

    Returns:
        ``schema``.
    """
    components = schema.setdefault("components", {})
    components.setdefault("securitySchemes", {})[SECURITY_SCHEME] = {
        "type": "http",
        "scheme": "bearer",
        "description": f"the job's shared token ({TOKEN_ENV}); required on every request that changes state",
    }
    components.setdefault("schemas", {}).setdefault(
        "Unauthorized",
        {"type": "object", "properties": {"detail": {"type": "string"}}, "required": ["detail"]},
    )
    for operations in schema.get("paths", {}).values():
        for method, operation in operations.items():
            if method.upper() in OPEN_METHODS or not isinstance(operation, dict):
                continue
            operation["security"] = [{SECURITY_SCHEME: []}]
            operation.setdefault("responses", {})["401"] = {
                "description": "no bearer token, or not the job's",
                "content": {"application/json": {"schema": {"$ref": "#/components/schemas/Unauthorized"}}},
            }
    return schema
