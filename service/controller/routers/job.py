"""``/v1/job``: the desired job."""

from __future__ import annotations


from fastapi import APIRouter, Depends
from fastapi.responses import JSONResponse

from service.metrics import refusal
from vecsim.config import JobSpec

from ..deps import get_state
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
async def put_job(job: JobSpec, state: ControllerState = Depends(get_state)) -> JobSpec | JSONResponse:
    """Validates the job against the task catalogue and the registered pods, then plans it.

    The same job again changes nothing; another job keeps the pods in their slots and moves the
    generation on.
    """
    tasks, problems = check_job(job, state.records())
    if problems:
        detail = f"job {job.job_id!r} rejected: " + "; ".join(problems)
        return refusal(state.metrics.refused, 422, "job_rejected", detail, problems=problems)
    state.set_job(job, tasks)
    return job


@router.get("", response_model=JobSpec, responses={404: {"model": Problem}}, summary="The desired job")
async def get_job(state: ControllerState = Depends(get_state)) -> JobSpec | JSONResponse:
    """The job last accepted by ``PUT /v1/job`` (or given at start-up)."""
    if state.job is None:
        return refusal(state.metrics.refused, 404, "no_job", "no job: PUT /v1/job first")
    return state.job
