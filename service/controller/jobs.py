"""Checking a job before it is accepted: its task ids, their spaces, and the pods' capacity."""

from __future__ import annotations

from collections.abc import Container, Iterable

from vecsim.engine import tasks as registry
from vecsim.config import CameraConfig, JobSpec, PodRecord
from vecsim.plan import validate_job


class _KnownTasks(Container[str]):
    """Every task id the task registry can build (gymnasium ids are open-ended, so no set)."""

    def __contains__(self, task_id: object) -> bool:
        try:
            registry.get_task(str(task_id))
        except registry.UnknownTaskError:
            return False
        return True


def resolve_tasks(job: JobSpec) -> tuple[list[str], list[str], Container[str]]:
    """Resolves the job's task ids: its ``tasks`` list (normalised) when given, else its suite's.

    Returns ``(task ids, problems, known)``: a problem (an unknown suite) says what to change;
    ``known`` answers whether a task id can be built (for :func:`vecsim.plan.validate_job`).
    """
    known = _KnownTasks()
    if job.tasks:
        return [registry.normalize_task_id(t) for t in job.tasks], [], known
    try:
        return [spec.task_id for spec in registry.suite_tasks(str(job.suite))], [], known
    except registry.UnknownTaskError:
        suites = registry.list_suites()
        return [], [f"suite: unknown suite {job.suite!r}; use one of {suites} or list task ids in 'tasks'"], known


def space_problems(task_ids: list[str], camera: CameraConfig) -> list[str]:
    """Returns a problem for each task whose spaces differ from the first task's, or that has
    spaces a pod cannot serve (every env of a job shares one observation and one action space)."""
    problems: list[str] = []
    first: tuple[str, object] | None = None
    for task_id in task_ids:
        try:
            spaces = registry.task_spaces(task_id, camera)
        except ValueError as exc:
            problems.append(f"tasks: {task_id!r} cannot be served: {exc}")
            continue
        if first is None:
            first = (task_id, spaces)
        elif spaces != first[1]:
            problems.append(
                f"tasks: {task_id!r} has other observation/action spaces than {first[0]!r} "
                f"({spaces[0]}, {spaces[1]} vs {first[1][0]}, {first[1][1]}); a job's tasks must share "
                "one observation and one action space: run them as separate jobs"
            )
    return problems


def check_job(job: JobSpec, pods: Iterable[PodRecord]) -> tuple[list[str], list[str]]:
    """Checks everything a job needs to run on ``pods``: known tasks with one shared pair of
    spaces, and pods big enough for a slot. May make (and close) a gym env to read its spaces.

    Returns ``(resolved task ids, problems)``; each problem says what to change.
    """
    tasks, problems, known = resolve_tasks(job)
    if problems:
        return tasks, problems
    problems = validate_job(job, tasks, pods, known_tasks=known)
    if problems:
        return tasks, problems
    return tasks, space_problems(tasks, job.camera)
