"""``/v1/routing``: which pod runs which envs of which stage, for clients."""

from __future__ import annotations

from fastapi import APIRouter, Depends
from fastapi.responses import JSONResponse

from service.metrics import refusal
from vecsim.config import RoutingTable

from ..deps import get_state
from ...models import Problem
from ..state import ControllerState, NoJobError, NoPlanError

router = APIRouter(prefix="/v1/routing", tags=["routing"])


@router.get(
    "",
    response_model=RoutingTable,
    responses={
        404: {"model": Problem, "description": "no job"},
        503: {"model": Problem, "description": "not planned yet"},
    },
    summary="The routing table",
)
async def routing(state: ControllerState = Depends(get_state)) -> RoutingTable | JSONResponse:
    """The current plan's stages and pods; ``ready`` is true once every slot's pod runs it."""
    try:
        return state.routing()
    except NoJobError as exc:
        return refusal(state.metrics.refused, 404, "no_job", str(exc))
    except NoPlanError as exc:
        return refusal(state.metrics.refused, 503, "no_plan", str(exc))
