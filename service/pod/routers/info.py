"""What the pod is and what it runs."""

from __future__ import annotations

from fastapi import APIRouter, Depends

from vecsim.engine.base import engine_kind
from vecsim.spaces import space_to_json

from ..deps import get_state
from ..models import InfoResponse, TaskInfo
from ..state import PodState

router = APIRouter(tags=["info"])


@router.get("/v1/info", response_model=InfoResponse, summary="The pod's assignment, tasks and spaces")
async def info(state: PodState = Depends(get_state)) -> InfoResponse:
    """The pod's name, stage, generation, readiness, its task blocks with their instructions and,
    once the envs are built, the observation and action space of one env."""
    assignment = state.assignment
    env = state.env
    tasks = []
    for block in [] if assignment is None else assignment.tasks:
        # The engine's own account: an mjwarp pod reads its exported scenes, not LIBERO.
        instruction, num_states = engine_kind(assignment.engine).task_info(assignment, block.task_id)
        tasks.append(
            TaskInfo(
                task_id=block.task_id,
                instruction=instruction,
                num_states=num_states,
                env_start=block.env_start,
                num_envs=block.num_envs,
                stage_id=block.stage_id,
                reset="seed" if block.task_id.startswith("gym/") and not assignment.camera.names else "state_id",
            )
        )
    return InfoResponse(
        pod=state.settings.name,
        stage_id=None if assignment is None else assignment.stage_id,
        generation=state.generation,
        ready=state.ready,
        num_envs=0 if assignment is None else assignment.num_envs,
        tasks=tasks,
        observation_space=None if env is None else space_to_json(env.single_observation_space),
        # The envs' own action space (a Dict or Tuple one travels flattened as single_action_space).
        action_space=None
        if env is None
        else space_to_json(getattr(env, "served_action_space", env.single_action_space)),
        max_chunk=state.settings.max_chunk,
        instance=state.instance,
    )
