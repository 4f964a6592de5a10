"""The controller's (or a person's) way to tell the pod what to run."""

from __future__ import annotations

from fastapi import APIRouter, Depends

from vecsim.config import Assignment

from ..deps import get_state
from ...models import Problem
from ..models import AssignmentResponse
from ..state import PodState

router = APIRouter(tags=["assignment"])


@router.put(
    "/v1/assignment",
    response_model=AssignmentResponse,
    responses={
        409: {"model": Problem, "description": "older generation, or same generation with other content"},
        422: {"model": Problem, "description": "another pod's assignment, too many envs, unknown task"},
    },
    summary="Take on an assignment; build its envs in the background",
)
async def put_assignment(assignment: Assignment, state: PodState = Depends(get_state)) -> AssignmentResponse:
    """Adopt ``assignment``. New content starts a build in the background (``/readyz`` says when
    it is done); a new generation with the same content is adopted at once with no rebuild; the
    same assignment twice is a no-op."""
    rebuilt = await state.assign(assignment)
    return AssignmentResponse(generation=assignment.generation, rebuilt=rebuilt)
