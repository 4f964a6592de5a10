"""The controller's FastAPI app: routers over one :class:`ControllerState`, and the reconcile
loop running for the app's lifetime, wired as both servers are (:func:`service.app.server_app`)."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import AsyncIterator, Callable

from fastapi import FastAPI

from service.app import server_app
from service.routers import probe_router
from vecsim.auth import TOKEN_ENV, bearer_headers
from vecsim.transport import make_async_client

from .deps import get_state
from .jobs import check_job
from .reconciler import Reconciler
from .routers import job, pods, routing
from .settings import ControllerSettings
from .state import ControllerState

log = logging.getLogger(__name__)


async def _ticker(state: ControllerState, stop: asyncio.Event) -> None:
    """Ticks the state often enough that a gap between ticks means the loop itself stalled."""
    period = state.settings.stall_after_s / 4
    while not stop.is_set():
        state.tick()
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(stop.wait(), timeout=period)


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
        if settings.token is None:
            log.warning(
                "no %s set: anyone who can reach the controller may register pods and change the job "
                "(fine for local development only)",
                TOKEN_ENV,
            )
        if not reconcile:
            yield
            return
        stop = asyncio.Event()
        # vecsim's default transport (vecsim.transport): a new generation pushes an assignment to
        # every pod at once.
        async with make_async_client(headers=bearer_headers(settings.token)) as client:
            tasks = [
                asyncio.create_task(Reconciler(state, client).run(stop)),
                asyncio.create_task(_ticker(state, stop)),
            ]
            try:
                yield
            finally:
                stop.set()
                await asyncio.gather(*tasks)

    app = server_app(
        title="vecsim controller",
        description="Pod registry, job plan and routing table of a vecsim job (docs/api.md).",
        lifespan=lifespan,
        server="the controller",
        refused=state.metrics.refused,
        max_body_bytes=settings.max_body_bytes,
        token=settings.token,
        routers=[pods.router, job.router, routing.router, probe_router(get_state)],
    )
    app.state.controller = state
    return app
