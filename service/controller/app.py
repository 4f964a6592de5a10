"""The controller's FastAPI app: routers over one :class:`ControllerState`, and the reconcile
loop running for the app's lifetime."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import AsyncIterator, Callable

import httpx
from fastapi import FastAPI

from vecsim import __version__

from .jobs import check_job
from .reconcile import Reconciler
from .routers import health, job, pods, routing
from .settings import ControllerSettings
from .state import ControllerState

log = logging.getLogger(__name__)


def create_app(
    settings: ControllerSettings,
    *,
    clock: Callable[[], float] = time.monotonic,
    reconcile: bool = True,
) -> FastAPI:
    """Returns the controller app for ``settings``.

    ``clock`` is the controller's time source for heartbeat TTLs (tests pass their own);
    ``reconcile=False`` serves the API without the loop that pushes assignments to pods.

    Raises:
        ValueError: ``settings.job`` cannot run (the message lists what to change).
    """
    state = ControllerState(settings, clock=clock)
    if settings.job is not None:
        tasks, problems = check_job(settings.job, [])
        if problems:
            raise ValueError(f"job {settings.job.job_id!r} from the settings cannot run: " + "; ".join(problems))
        state.set_job(settings.job, tasks)

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        if not reconcile:
            yield
            return
        stop = asyncio.Event()
        async with httpx.AsyncClient() as client:
            task = asyncio.create_task(Reconciler(state, client).run(stop))
            try:
                yield
            finally:
                stop.set()
                await task

    app = FastAPI(
        title="vecsim controller",
        version=__version__,
        description="Pod registry, job plan and routing table of a vecsim job (docs/api.md).",
        lifespan=lifespan,
    )
    app.state.controller = state
    for module in (pods, job, routing, health):
        app.include_router(module.router)
    return app
