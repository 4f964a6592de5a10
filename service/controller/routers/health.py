"""Liveness, readiness of the job, and Prometheus metrics."""

from __future__ import annotations

from fastapi import APIRouter, Depends
from fastapi.responses import JSONResponse, Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from ..deps import get_state
from ...models import Health, Problem, Readiness
from ..state import ControllerState

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=Health, summary="Liveness: the controller answers")
async def healthz() -> Health:
    """Always 200 while the server runs."""
    return Health(status="alive")


@router.get(
    "/readyz",
    response_model=Readiness,
    response_model_exclude_none=True,  # a pod's num_envs: the controller runs no envs
    responses={503: {"model": Problem, "description": "why the job is not ready"}},
    summary="Readiness of the job",
)
async def readyz(state: ControllerState = Depends(get_state)) -> Readiness | JSONResponse:
    """200 when the job's plan is pushed and every slot's pod runs it and is ready; else 503
    naming what is missing."""
    problems = state.problems()
    if problems or state.plan is None:
        return JSONResponse({"detail": "not ready: " + "; ".join(problems)}, status_code=503)
    return Readiness(status="ready", generation=state.plan.generation)


@router.get("/metrics", response_class=Response, summary="Prometheus metrics")
async def metrics(state: ControllerState = Depends(get_state)) -> Response:
    """Pods, ready pods, generation, unfilled slots, heartbeats, pushes, reconcile duration."""
    return Response(generate_latest(state.metrics.registry), media_type=CONTENT_TYPE_LATEST)
