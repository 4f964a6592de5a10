"""Checking a job before it is accepted: its task ids, whether they share their spaces, and the
pods' capacity.

The controller makes no env: it knows the tasks from the job and the task catalogue
(:mod:`vecsim.suites`), so it installs and runs without the simulator. Whether a gymnasium id
can be made, and its spaces, is the pod's to say when it builds its assignment (the pod refuses
one whose tasks do not share their spaces); the spaces it serves are in its ``/v1/info``.
"""

from __future__ import annotations

from collections.abc import Container, Iterable

from vecsim import suites
from vecsim.config import JobSpec, PodRecord
from vecsim.plan import validate_job


class _KnownTasks(Container[str]):
    """Every task id of the catalogue (gymnasium ids are open-ended, so no set)."""

    def __contains__(self, task_id: object) -> bool:
        return isinstance(task_id, str) and suites.is_known(task_id)


def resolve_tasks(job: JobSpec) -> tuple[list[str], list[str], Container[str]]:
    """Resolves the job's task ids: its ``tasks`` list (normalised) when given, else its suite's.

    Returns ``(task ids, problems, known)``: a problem (an unknown suite) says what to change;
    ``known`` answers whether a task id names a task (for :func:`vecsim.plan.validate_job`).
    """
    known = _KnownTasks()
    if job.tasks:
        return [suites.normalize_task_id(t) for t in job.tasks], [], known
    try:
        return suites.suite_task_ids(str(job.suite)), [], known
    except KeyError:
        names = suites.suite_names()
        return [], [f"suite: unknown suite {job.suite!r}; use one of {names} or list task ids in 'tasks'"], known


def space_problems(task_ids: list[str]) -> list[str]:
    """Returns a problem for each task whose spaces differ from the first task's, as far as the
    catalogue tells (every env of a job shares one observation and one action space)."""
    problems: list[str] = []
    if not task_ids:
        return problems
    first = task_ids[0]
    family = suites.space_family(first)
    for task_id in dict.fromkeys(task_ids[1:]):
        theirs = suites.space_family(task_id)
        if theirs == family:
            continue
        gym = first.startswith("gym/") or task_id.startswith("gym/")
        why = (
            "another env: the controller makes none to compare their spaces"
            if gym
            else f"a {theirs} task, not {family}"
        )
        problems.append(
            f"tasks: {task_id!r} has other observation/action spaces than {first!r} ({why}); a job's tasks "
            "must share one observation and one action space: run them as separate jobs"
        )
    return problems


def check_job(job: JobSpec, pods: Iterable[PodRecord]) -> tuple[list[str], list[str]]:
    """Checks everything a job needs to run on ``pods``: known tasks with one shared pair of
    spaces, and pods big enough for a slot. Pure: makes no env.

    Returns ``(resolved task ids, problems)``; each problem says what to change.
    """
    tasks, problems, known = resolve_tasks(job)
    if problems:
        return tasks, problems
    problems = validate_job(job, tasks, pods, known_tasks=known)
    if problems:
        return tasks, problems
    return tasks, space_problems(tasks)
