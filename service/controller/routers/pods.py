"""``/v1/pods``: registration, heartbeats, and the registry."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Path

from service.contract import Heartbeat, HeartbeatAnswer
from service.errors import InvalidFieldError
from vecsim.config import POD_NAME_PATTERN, PodRecord, PodRegistration

from ..deps import get_state
from ...models import Problem
from ..state import ControllerState

router = APIRouter(prefix="/v1/pods", tags=["pods"])

POD_NAME = Path(min_length=1, max_length=63, pattern=POD_NAME_PATTERN, description="stable pod name, e.g. sim-0")


@router.post("", response_model=PodRecord, summary="Register a pod (again, after a restart)")
async def register(registration: PodRegistration, state: ControllerState = Depends(get_state)) -> PodRecord:
    """Adds the pod to the registry; a pod of the same name is replaced (a new process)."""
    return state.register(registration)


@router.get("", response_model=list[PodRecord], summary="Every registered pod")
async def list_pods(state: ControllerState = Depends(get_state)) -> list[PodRecord]:
    """Pods heard from within the heartbeat TTL, by name, with their stage from the plan."""
    return state.records()


@router.post(
    "/{pod}/heartbeat",
    response_model=HeartbeatAnswer,
    responses={
        404: {"model": Problem, "description": "unknown pod: register first"},
        409: {"model": Problem, "description": "the heartbeat's URL is not the pod's registered one"},
        422: {"model": Problem},
    },
    summary="Report what a pod runs",
)
async def heartbeat(
    body: Heartbeat, pod: str = POD_NAME, state: ControllerState = Depends(get_state)
) -> HeartbeatAnswer:
    """Keeps the pod registered and records its assignment and readiness. A heartbeat cannot move
    a pod to another URL (409): a pod that moved registers again."""
    if body.assignment is not None and body.generation is not None and body.generation != body.assignment.generation:
        detail = f"generation: {body.generation} differs from assignment.generation {body.assignment.generation}"
        raise InvalidFieldError(detail)
    return HeartbeatAnswer(generation=state.heartbeat(pod, body.url, body.assignment, body.ready))
