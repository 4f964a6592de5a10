"""The routes both servers (pod and controller) mount alike: liveness, readiness and Prometheus
metrics, each with one implementation and one body model (:mod:`service.models`).

A server hands ``probe_router`` its own state dependency; the state says whether it is ready
and holds its metrics registry (:class:`Probed`)::

    app.include_router(probe_router(get_state))  # get_state: the server's own dependency
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from typing import Protocol

from fastapi import APIRouter, Depends, Request, Response
from fastapi.responses import JSONResponse
from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, generate_latest

from .models import Health, Problem, Readiness


class Probed(Protocol):
    """What the shared routes read from a server's state."""

    @property
    def registry(self) -> CollectorRegistry:
        """The server's Prometheus registry (one per app, so several apps share a process)."""
        ...

    def readiness(self) -> Readiness | Problem:
        """Readiness when the server serves, else the problem that keeps it from serving."""
        ...


def probe_router(get_server: Callable[[Request], Awaitable[Probed]]) -> APIRouter:
    """The ``/healthz``, ``/readyz`` and ``/metrics`` routes over the state ``get_server`` gives."""
    router = APIRouter()

    @router.get("/healthz", response_model=Health, tags=["health"], summary="Liveness: the process answers")
    async def healthz() -> Health:
        """Always 200 while the server runs, also while a pod builds or steps its envs."""
        return Health(status="alive")

    @router.get(
        "/readyz",
        response_model=Readiness,
        response_model_exclude_none=True,  # a pod's num_envs: the controller runs no envs
        responses={503: {"model": Problem, "description": "why the server is not ready"}},
        tags=["health"],
        summary="Readiness: a pod's envs built and rendering; the controller's job running",
    )
    async def readyz(server: Probed = Depends(get_server)) -> Readiness | JSONResponse:
        """200 when the server serves: a pod once the envs of its current assignment are built
        and rendered a frame, the controller once every slot's pod runs the plan and is ready.
        Else 503 naming the reason (a pod: no assignment, building, failed; the controller:
        what is missing)."""
        answer = server.readiness()
        if isinstance(answer, Problem):
            return JSONResponse(answer.model_dump(), status_code=503)
        return answer

    @router.get(
        "/metrics",
        response_class=Response,
        responses={200: {"content": {CONTENT_TYPE_LATEST: {}}, "description": "Prometheus text format"}},
        tags=["metrics"],
        summary="Prometheus metrics",
    )
    async def metrics(server: Probed = Depends(get_server)) -> Response:
        """The server's metrics (``vecsim_pod_*``, ``vecsim_controller_*``; docs/api.md)."""
        return Response(generate_latest(server.registry), media_type=CONTENT_TYPE_LATEST)

    return router
