"""The ``cpu`` engine: :class:`~vecsim.engine.vector_env.TaskGroupedVectorEnv`, the pod's envs in
worker processes on its cores, as the pod's engine seam (:mod:`vecsim.engine.base`) builds it."""

from __future__ import annotations

from vecsim.config import Assignment
from vecsim.engine.base import EngineKind
from vecsim.engine.checks import assignment_spaces
from vecsim.engine.tasks import get_task
from vecsim.engine.vector_env import TaskGroupedVectorEnv
from vecsim.engine.base import DEFAULT_MAX_CHUNK


def build(
    assignment: Assignment,
    *,
    timeout_s: float | None = None,
    build_timeout_s: float | None = None,
    max_chunk: int = DEFAULT_MAX_CHUNK,
) -> TaskGroupedVectorEnv:
    """The assignment's envs in worker processes, every env in state 0 (raises what
    :class:`TaskGroupedVectorEnv` raises)."""
    return TaskGroupedVectorEnv(assignment, timeout_s=timeout_s, build_timeout_s=build_timeout_s, max_chunk=max_chunk)


def steps_on_event_loop(assignment: Assignment) -> bool:
    """Whether the pod resets and steps ``assignment``'s envs on its event loop rather than on
    its worker thread: when every scene is cheap (a ``gym/*`` task, no camera), as
    ``vecsim.engine.resolve_envs_per_worker`` calls them.

    A call of cheap scenes takes the workers a millisecond or two, and the hand-over to the worker
    thread and back about 0.2 ms of it; blocking the loop for that long delays a health check no
    more than a busy loop would. Robot scenes and cameras take tens to hundreds of milliseconds a
    call, so they stay on the worker thread. A worker that hangs holds the loop with it, up to the
    pod's step timeout: health checks and heartbeats wait too, and the controller may give the
    slot to a spare. Raises nothing (tasks were checked when the assignment was taken).
    """
    return not assignment.camera.names and all(get_task(b.task_id).suite == "gym" for b in assignment.tasks)


def task_info(assignment: Assignment, task_id: str) -> tuple[str, int]:
    """The task's instruction and number of fixed initial states, from the task registry."""
    spec = get_task(task_id)
    return spec.instruction, spec.num_states


KIND = EngineKind(
    name="cpu", spaces=assignment_spaces, build=build, steps_on_event_loop=steps_on_event_loop, task_info=task_info
)
