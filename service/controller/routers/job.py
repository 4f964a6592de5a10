"""``/v1/job``: the desired job."""

from __future__ import annotations

from fastapi import APIRouter, Depends

from vecsim.config import JobSpec

from ..deps import get_state
from ..errors import JobRejectedError, NoJobError
from ..jobs import check_job
from ...models import Problem
from ..models import JobProblems
from ..state import ControllerState

router = APIRouter(prefix="/v1/job", tags=["job"])


@router.put(
    "",
    response_model=JobSpec,
    responses={422: {"model": JobProblems, "description": "the job cannot run; each problem says what to change"}},
    summary="Set the desired job",
)
async def put_job(job: JobSpec, state: ControllerState = Depends(get_state)) -> JobSpec:
    """Validates the job against the task catalogue and the registered pods, then plans it.

    The same job again changes nothing; another job keeps the pods in their slots and moves the
    generation on.
    """
    tasks, problems = check_job(job, state.records())
    if problems:
        raise JobRejectedError(job.job_id, problems)
    state.set_job(job, tasks)
    return job


@router.get("", response_model=JobSpec, responses={404: {"model": Problem}}, summary="The desired job")
async def get_job(state: ControllerState = Depends(get_state)) -> JobSpec:
    """The job last accepted by ``PUT /v1/job`` (or given at start-up)."""
    if state.job is None:
        raise NoJobError("no job: PUT /v1/job first")
    return state.job
