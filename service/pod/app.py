"""The pod's FastAPI app: ``create_app(settings)`` builds its state and lifespan, wired as both
servers are (:func:`service.app.server_app`)."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
from collections.abc import AsyncIterator

from fastapi import FastAPI

from service.app import server_app
from service.contract import Heartbeat
from service.routers import probe_router
from vecsim.auth import TOKEN_ENV

from .agent import ControllerAgent
from .deps import get_state
from .errors import LIBRARY_ERRORS
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
                "(fine for local development only)",
                settings.name,
                TOKEN_ENV,
            )
        agent_task = None
        if settings.controller_url:
            agent = ControllerAgent(settings, lambda: heartbeat_of(state))
            agent_task = asyncio.create_task(agent.run(), name=f"{settings.name}-agent")
        log.info(
            "pod %s (namespace %s) serving at %s, on CPUs %s",
            settings.name,
            settings.namespace,
            settings.url,
            sorted(os.sched_getaffinity(0)),
        )
        try:
            yield
        finally:
            if agent_task is not None:
                agent_task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await agent_task
            await state.close()
            log.info("pod %s stopped", settings.name)

    app = server_app(
        title=f"vecsim pod {settings.name}",
        description="One sim pod: task-grouped MuJoCo envs served over HTTP (see docs/api.md).",
        lifespan=lifespan,
        server=f"pod {settings.name}",
        refused=state.metrics.refused,
        max_body_bytes=settings.max_body_bytes,
        token=settings.token,
        routers=[probe_router(get_state), info.router, assignment.router, envs.router],
        library_errors=LIBRARY_ERRORS,
    )
    app.state.pod = state
    return app
