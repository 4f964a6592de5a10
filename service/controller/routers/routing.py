"""``/v1/routing``: which pod runs which envs of which stage, for clients."""

from __future__ import annotations

from fastapi import APIRouter, Depends
from vecsim.config import RoutingTable

from ..deps import get_state
from ...models import Problem
from ..state import ControllerState

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
async def routing(state: ControllerState = Depends(get_state)) -> RoutingTable:
    """The current plan's stages and pods; ``ready`` is true once every slot's pod runs it."""
    return state.routing()
