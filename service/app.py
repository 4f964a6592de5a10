"""The one wiring of both servers' FastAPI apps (pod and controller): refusal handlers, the body
cap, the bearer token, the shared probe routes and the OpenAPI security scheme.

Each server's ``create_app`` builds its state and lifespan, then calls :func:`server_app`::

    app = server_app(title=..., description=..., lifespan=lifespan, server="the controller",
                     refused=state.metrics.refused, max_body_bytes=..., token=...,
                     routers=[pods.router, probe_router(get_state)])
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from contextlib import AbstractAsyncContextManager
from typing import Any

from fastapi import APIRouter, FastAPI
from fastapi.exceptions import RequestValidationError
from prometheus_client import Counter

from vecsim import __version__

from .errors import RefusedError, answer_library_error, answer_refusal, answer_validation_error
from .http import BearerTokenMiddleware, BodyLimitMiddleware, document_bearer_security


def server_app(
    *,
    title: str,
    description: str,
    lifespan: Callable[[FastAPI], AbstractAsyncContextManager[Any]],
    server: str,
    refused: Counter,
    max_body_bytes: int,
    token: str | None,
    routers: Iterable[APIRouter],
    library_errors: Mapping[type[Exception], tuple[int, str]] | None = None,
) -> FastAPI:
    """Returns a server's app, wired as every vecsim server is.

    Args:
        server: names the server in refusals' details (``"pod sim-0"``, ``"the controller"``).
        refused: the server's ``vecsim_<server>_refused_requests`` counter (labelled ``reason``).
        max_body_bytes: larger bodies are answered 413 before any route reads them.
        token: the job's bearer token; None lets every request in.
        library_errors: library exception classes the server answers as they are, each with its
            (status, reason); a :class:`RefusedError` needs no entry.
    """
    app = FastAPI(title=title, version=__version__, description=description, lifespan=lifespan)
    app.state.refused_requests = refused
    app.state.library_errors = dict(library_errors or {})
    app.add_exception_handler(RefusedError, answer_refusal)  # type: ignore[arg-type]
    app.add_exception_handler(RequestValidationError, answer_validation_error)  # type: ignore[arg-type]
    for library_error in app.state.library_errors:
        app.add_exception_handler(library_error, answer_library_error)
    app.add_middleware(
        BodyLimitMiddleware,
        limit=max_body_bytes,
        on_refused=refused.labels(reason="body_too_large").inc,
        server=server,
    )
    # Added last, so it runs first: a request without the token is refused before its body is read.
    app.add_middleware(
        BearerTokenMiddleware,
        token=token,
        server=server,
        on_refused=refused.labels(reason="unauthorized").inc,
    )
    for router in routers:
        app.include_router(router)
    default_openapi = app.openapi
    app.openapi = lambda: document_bearer_security(default_openapi())  # type: ignore[method-assign]
    return app
