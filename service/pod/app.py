"""The pod's FastAPI app: ``create_app(settings)`` wires state, routers, errors and lifespan."""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncIterator

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse

import vecsim
from service.contract import Heartbeat
from service.http import BearerTokenMiddleware, BodyLimitMiddleware, describe_validation_error, document_bearer_security
from service.metrics import refusal
from service.routers import probe_router
from vecsim.auth import TOKEN_ENV
from vecsim.engine import InvalidRequestError

from .agent import ControllerAgent
from .deps import get_state
from .errors import LIBRARY_ERRORS, PodError
from .metrics import PodMetrics
from .routers import assignment, envs, info
from .settings import PodSettings
from .state import PodState

log = logging.getLogger(__name__)


def heartbeat_of(state: PodState) -> Heartbeat:
    """What the pod tells the controller about itself now."""
    return Heartbeat(
        url=state.settings.url,
        generation=state.generation,
        assignment=state.assignment,
        ready=state.ready,
    )


def create_app(settings: PodSettings) -> FastAPI:
    """A pod app for ``settings``; serve it once (its lifespan closes its envs and worker).

    At start-up it builds ``settings.assignment`` if one is given (standalone mode) and starts
    the controller agent if ``settings.controller_url`` is set.

    Returns:
        The FastAPI app, with the pod's state in ``app.state.pod``.
    """
    state = PodState(settings, PodMetrics())

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        if settings.assignment is not None:
            await state.assign(settings.assignment)
        if settings.token is None:
            log.warning(
                "pod %s: no %s set: anyone who can reach it may assign, reset and step it "
                "(fine for local development only)", settings.name, TOKEN_ENV,
            )
        agent_task = None
        if settings.controller_url:
            agent = ControllerAgent(settings, lambda: heartbeat_of(state))
            agent_task = asyncio.create_task(agent.run(), name=f"{settings.name}-agent")
        log.info("pod %s (namespace %s) serving at %s", settings.name, settings.namespace, settings.url)
        try:
            yield
        finally:
            if agent_task is not None:
                agent_task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await agent_task
            await state.close()
            log.info("pod %s stopped", settings.name)

    app = FastAPI(
        title=f"vecsim pod {settings.name}",
        version=vecsim.__version__,
        description="One sim pod: task-grouped MuJoCo envs served over HTTP (see docs/api.md).",
        lifespan=lifespan,
    )
    app.state.pod = state

    @app.exception_handler(PodError)
    async def _pod_error(request: Request, exc: PodError) -> JSONResponse:
        log.debug("%s %s -> %d: %s", request.method, request.url.path, exc.status_code, exc.detail)
        return refusal(state.metrics.refused, exc.status_code, exc.reason, exc.detail)

    async def _library_error(request: Request, exc: Exception) -> JSONResponse:
        status, reason = next(answer for cls, answer in LIBRARY_ERRORS.items() if isinstance(exc, cls))
        log.debug("%s %s -> %d: %s", request.method, request.url.path, status, exc)
        return refusal(state.metrics.refused, status, reason, str(exc))

    for library_error in LIBRARY_ERRORS:
        app.add_exception_handler(library_error, _library_error)

    @app.exception_handler(RequestValidationError)
    async def _validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
        return await _library_error(request, InvalidRequestError(describe_validation_error(exc)))

    app.add_middleware(
        BodyLimitMiddleware,
        limit=settings.max_body_bytes,
        on_refused=state.metrics.refused.labels(reason="body_too_large").inc,
        server=f"pod {settings.name}",
    )
    # Added last, so it runs first: a request without the token is refused before its body is read.
    app.add_middleware(
        BearerTokenMiddleware,
        token=settings.token,
        server=f"pod {settings.name}",
        on_refused=state.metrics.refused.labels(reason="unauthorized").inc,
    )
    for router in (probe_router(get_state), info.router, assignment.router, envs.router):
        app.include_router(router)
    default_openapi = app.openapi
    app.openapi = lambda: document_bearer_security(default_openapi())  # type: ignore[method-assign]
    return app
