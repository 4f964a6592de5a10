"""Liveness and readiness: what Kubernetes probes and the controller watches."""

from __future__ import annotations

from fastapi import APIRouter, Depends
from fastapi.responses import JSONResponse

from ..deps import get_state
from ...models import Health, Problem, Readiness
from ..state import PodState

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=Health, summary="Liveness: the process answers")
async def healthz() -> Health:
    """Always 200 while the server runs, also while envs are being built or stepped."""
    return Health(status="alive")


@router.get(
    "/readyz",
    response_model=Readiness,
    responses={503: {"model": Problem, "description": "no assignment, building, or failed"}},
    summary="Readiness: envs built and a render works",
)
async def readyz(state: PodState = Depends(get_state)) -> Readiness | JSONResponse:
    """200 once the envs of the current assignment are built and rendered a frame; 503 with the
    reason before the first assignment, while building or rebuilding, and after a failure."""
    if not state.ready or state.env is None:
        return JSONResponse({"detail": f"pod {state.settings.name} is not ready: {state.detail}"}, status_code=503)
    return Readiness(status="ready", generation=state.generation, num_envs=state.env.num_envs)
