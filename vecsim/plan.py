"""Planning: which pod runs which tasks for which pipeline stage (pure, no I/O).

Every stage runs all the job's tasks, ``group_size`` envs per task. The job's ``stage_layout``
says how stages sit on *slots* (one pod each). ``pods``: ``num_stages`` stages of
``pods_per_stage`` slots, a stage's tasks split over its slots. ``slices``: ``pods_per_stage``
slots in all, each holding every stage's share of its tasks; a task's envs alternate stage by
stage (env 0 stage 0, env 1 stage 1, ...), so that each worker process of the pod, which hosts
consecutive envs, holds envs of every stage and stays busy whichever stage the pod steps. Tasks
split over slots in contiguous ranges, remainders spread over the first slots (10 tasks over 3
slots -> 4, 3, 3). A slot with no tasks is a spare with zero envs.

Slot holders are stable: :func:`plan` keeps a slot's pod while that pod is alive. A slot whose
pod is gone stays unfilled until a pod of the same name comes back (the StatefulSet
replacement), or goes to a spare pod if one is free. The generation moves on only when the
slot -> pod mapping or a slot's content changes, or when a slot's pod was restarted.
"""

from __future__ import annotations

import functools
import math
import re
from collections.abc import Collection, Container, Iterable, Mapping, Sequence
from dataclasses import dataclass, replace

from vecsim.config import Assignment, EnvSettings, JobSpec, PodRecord, RoutedPod, RoutedStage, RoutingTable, TaskBlock


def stage_of(i: int, num_stages: int) -> int:
    """Return the pipeline stage of request ``i`` of a batch: ``i % num_stages``.

    This is the one definition the sampler, the client and the rollout share.

    Raises:
        ValueError: ``num_stages < 1`` or ``i < 0``.
    """
    if num_stages < 1:
        raise ValueError(f"num_stages must be >= 1, got {num_stages}")
    if i < 0:
        raise ValueError(f"request index must be >= 0, got {i}")
    return i % num_stages


SlotKey = tuple[int | None, int]
"""``(stage_id, index of the slot within its stage)``; stage ``None``: a ``slices`` slot (every stage)."""


@dataclass(frozen=True)
class Slot:
    """One pod's worth of a stage: a contiguous range of the job's tasks and who runs it.

    ``stage_id`` ``None``: a slot of the ``slices`` layout, whose blocks serve every stage (each
    block names its own). ``pod`` is the holder (``None``: unfilled); ``last_pod`` remembers who
    held it last, so that the slot goes back to a pod of that name when it returns.
    """

    stage_id: int | None
    index: int
    tasks: tuple[TaskBlock, ...]
    pod: str | None = None
    last_pod: str | None = None

    @property
    def key(self) -> SlotKey:
        return (self.stage_id, self.index)

    @property
    def name(self) -> str:
        """``stage 1 slot 0``, or ``slot 0 (every stage)`` for a ``slices`` slot: for messages."""
        return (
            f"slot {self.index} (every stage)" if self.stage_id is None else f"stage {self.stage_id} slot {self.index}"
        )

    @property
    def num_envs(self) -> int:
        return sum(block.num_envs for block in self.tasks)

    @property
    def task_ids(self) -> tuple[str, ...]:
        return tuple(dict.fromkeys(block.task_id for block in self.tasks))

    def blocks_of(self, stage_id: int) -> tuple[TaskBlock, ...]:
        """The slot's blocks whose envs serve ``stage_id``."""
        if self.stage_id is not None:
            return self.tasks if self.stage_id == stage_id else ()
        return tuple(block for block in self.tasks if block.stage_id == stage_id)


@dataclass(frozen=True)
class Plan:
    """The controller's desired state for one job at one generation."""

    generation: int
    job: JobSpec
    slots: tuple[Slot, ...]

    @property
    def job_id(self) -> str:
        return self.job.job_id

    @property
    def unfilled(self) -> tuple[Slot, ...]:
        """Slots that have no pod right now."""
        return tuple(slot for slot in self.slots if slot.pod is None)

    @property
    def pods(self) -> dict[str, SlotKey]:
        """Slot holders: pod name -> the key of the slot it holds."""
        return {slot.pod: slot.key for slot in self.slots if slot.pod is not None}

    def slot_of(self, pod: str) -> Slot | None:
        """Returns the slot ``pod`` holds, or ``None`` when it holds none (a spare pod)."""
        return self._slot_by_pod.get(pod)

    @functools.cached_property
    def _slot_by_pod(self) -> dict[str, Slot]:
        # Looked up once per pod by the registry and the readiness check: a scan per lookup
        # made those quadratic in the number of pods.
        held: dict[str, Slot] = {}
        for slot in self.slots:
            if slot.pod is not None:
                held.setdefault(slot.pod, slot)
        return held

    def assignment_for(self, slot: Slot, pod: str | None = None) -> Assignment:
        """Returns the assignment that the holder of ``slot`` (or ``pod``) runs at this generation."""
        name = pod if pod is not None else slot.pod
        if name is None:
            raise ValueError(f"slot {slot.key} has no pod; name the pod to build its assignment for")
        return _assignment(self.job, self.generation, name, slot.stage_id, slot.tasks)

    @functools.cached_property
    def assignments(self) -> dict[str, Assignment]:
        """Returns the assignment of every slot holder, by pod name (built once per plan: the
        controller reads it on every reconcile pass). Treat it as read-only."""
        return {slot.pod: self.assignment_for(slot) for slot in self.slots if slot.pod is not None}

    def spare_assignment(self, pod: str) -> Assignment:
        """Returns the empty assignment for a pod that holds no slot (zero envs; its stage is 0)."""
        return _assignment(self.job, self.generation, pod, 0, ())

    def with_generation(self, generation: int) -> Plan:
        """Returns the same plan at another generation."""
        return replace(self, generation=generation)

    def routing_table(self, urls: Mapping[str, str], *, ready: bool = False) -> RoutingTable:
        """Returns the routing table of this plan: each stage's filled slots with their pods' urls
        and, per pod, the blocks (env ids) that serve the stage. In the ``slices`` layout every
        pod is in every stage, each time with that stage's blocks only.

        Raises:
            KeyError: a slot holder has no entry in ``urls`` (the message names the pod).
        """
        stages = []
        for stage_id in range(self.job.num_stages):
            routed = []
            for slot in self.slots:
                if slot.stage_id not in (stage_id, None) or slot.pod is None:
                    continue
                if slot.pod not in urls:
                    raise KeyError(f"no url for pod {slot.pod!r} (holds slot {slot.key})")
                blocks = slot.blocks_of(stage_id)
                num_envs = sum(block.num_envs for block in blocks)
                routed.append(RoutedPod(pod=slot.pod, url=urls[slot.pod], num_envs=num_envs, tasks=blocks))
            stages.append(RoutedStage(stage_id=stage_id, pods=tuple(routed)))
        return RoutingTable(generation=self.generation, job_id=self.job_id, ready=ready, stages=tuple(stages))


def _assignment(
    job: JobSpec, generation: int, pod: str, stage_id: int | None, tasks: tuple[TaskBlock, ...]
) -> Assignment:
    settings = {name: getattr(job, name) for name in EnvSettings.model_fields}
    settings["make_kwargs"] = {
        task: kwargs for task, kwargs in job.make_kwargs.items() if task in {b.task_id for b in tasks}
    }
    return Assignment(generation=generation, job_id=job.job_id, pod=pod, stage_id=stage_id, tasks=tasks, **settings)


def split_tasks(tasks: Sequence[str], parts: int) -> list[tuple[str, ...]]:
    """Returns ``tasks`` cut into ``parts`` contiguous ranges, the first ``len % parts`` one longer.

    Raises:
        ValueError: ``parts`` is not positive.
    """
    if parts < 1:
        raise ValueError(f"pods_per_stage must be at least 1, got {parts}")
    base, extra = divmod(len(tasks), parts)
    ranges, start = [], 0
    for i in range(parts):
        size = base + (1 if i < extra else 0)
        ranges.append(tuple(tasks[start : start + size]))
        start += size
    return ranges


def slice_blocks(task_range: Sequence[str], group_size: int, num_stages: int) -> tuple[TaskBlock, ...]:
    """Returns a ``slices`` slot's blocks: per task, ``group_size x num_stages`` consecutive envs
    whose stages alternate (env ``k`` of the task serves stage ``k % num_stages``), one block per
    env (one per task and stage for ``group_size`` 0: empty blocks, as the ``pods`` layout has).
    With one stage, one block per task."""
    blocks: list[TaskBlock] = []
    start = 0
    for task_id in task_range:
        if group_size == 0:
            blocks += [TaskBlock(task_id=task_id, env_start=start, num_envs=0, stage_id=s) for s in range(num_stages)]
            continue
        for k in range(group_size * num_stages):
            stage_id = k % num_stages
            last = blocks[-1] if blocks else None
            if last is not None and last.task_id == task_id and last.stage_id == stage_id:
                blocks[-1] = last.model_copy(update={"num_envs": last.num_envs + 1})
            else:
                blocks.append(TaskBlock(task_id=task_id, env_start=start, num_envs=1, stage_id=stage_id))
            start += 1
    return tuple(blocks)


def slot_contents(job: JobSpec, tasks: Sequence[str]) -> list[Slot]:
    """Returns the job's unfilled slots, each with its task blocks: stage-major for the ``pods``
    layout, ``pods_per_stage`` slots of stage ``None`` (every stage) for ``slices``."""
    if job.stage_layout == "slices":
        return [
            Slot(stage_id=None, index=index, tasks=slice_blocks(task_range, job.group_size, job.num_stages))
            for index, task_range in enumerate(split_tasks(tasks, job.pods_per_stage))
        ]
    slots = []
    for stage_id in range(job.num_stages):
        for index, task_range in enumerate(split_tasks(tasks, job.pods_per_stage)):
            blocks = tuple(
                TaskBlock(task_id=task_id, env_start=i * job.group_size, num_envs=job.group_size)
                for i, task_id in enumerate(task_range)
            )
            slots.append(Slot(stage_id=stage_id, index=index, tasks=blocks))
    return slots


def pod_sort_key(name: str) -> tuple[str, int, str]:
    """Orders pod names by their stable ordinal, so that ``sim-2`` comes before ``sim-10``."""
    match = re.fullmatch(r"(.*?)(\d+)", name)
    if match is None:
        return (name, -1, name)
    return (match.group(1), int(match.group(2)), name)


def plan(
    job: JobSpec,
    pods: Sequence[PodRecord],
    previous: Plan | None,
    tasks: Sequence[str],
    *,
    restarted: Collection[str] = (),
) -> Plan:
    """Returns the plan for ``job`` over the live ``pods``, keeping ``previous``'s holders.

    ``tasks`` are the job's resolved task ids, in order. ``restarted`` names pods that came back
    as new processes since ``previous`` (they keep their slots, but their envs are new, so the
    generation moves on). A pod can hold a slot only when its ``max_envs`` fits the slot.

    Returns a plan whose generation equals ``previous``'s when nothing changed, and is one more
    otherwise (1 for the first plan).
    """
    alive = {record.pod: record for record in pods}
    old = {slot.key: slot for slot in previous.slots} if previous is not None else {}

    def fits(name: str, slot: Slot) -> bool:
        return alive[name].capacity.max_envs >= slot.num_envs

    slots: list[Slot] = []
    taken: set[str] = set()
    for slot in slot_contents(job, tasks):
        before = old.get(slot.key)
        holder = before.pod if before is not None else None
        if holder is not None and holder in alive and holder not in taken and fits(holder, slot):
            slot = replace(slot, pod=holder, last_pod=holder)
            taken.add(holder)
        else:
            slot = replace(slot, last_pod=before.last_pod if before is not None else None)
        slots.append(slot)

    # A returning pod takes back the slot it held last before any spare is used.
    for i, slot in enumerate(slots):
        name = slot.last_pod
        if slot.pod is None and name is not None and name in alive and name not in taken and fits(name, slot):
            slots[i] = replace(slot, pod=name)
            taken.add(name)

    spares = sorted((name for name in alive if name not in taken), key=pod_sort_key)
    for i, slot in enumerate(slots):
        if slot.pod is not None:
            continue
        for name in spares:
            if fits(name, slot):
                slots[i] = replace(slot, pod=name, last_pod=name)
                spares.remove(name)
                taken.add(name)
                break

    candidate = Plan(generation=previous.generation if previous is not None else 0, job=job, slots=tuple(slots))
    if previous is not None and not _changed(previous, candidate, restarted):
        return candidate
    return candidate.with_generation(candidate.generation + 1)


def _changed(previous: Plan, new: Plan, restarted: Collection[str]) -> bool:
    if any(slot.pod in restarted for slot in new.slots if slot.pod is not None):
        return True
    if [(s.key, s.pod) for s in previous.slots] != [(s.key, s.pod) for s in new.slots]:
        return True
    if previous.job == new.job:
        # Same job, same holders in the same slots: assignments differ only where tasks do (and
        # comparing task blocks is far cheaper than building two assignments per slot).
        return any(old.tasks != slot.tasks for old, slot in zip(previous.slots, new.slots))
    before = {slot.key: previous.assignment_for(slot, slot.pod or "") for slot in previous.slots}
    after = {slot.key: new.assignment_for(slot, slot.pod or "") for slot in new.slots}
    return any(not after[key].same_envs(before[key]) for key in after)


def adopt(job: JobSpec, tasks: Sequence[str], reports: Mapping[str, Assignment | None]) -> Plan | None:
    """Rebuilds a plan from what pods report they run (a restarted controller's first plan).

    A pod keeps the slot whose assignment it already runs exactly (same job, stage, tasks and
    settings); when two pods claim one slot, the one with the newer generation (then the lower
    ordinal) keeps it. The plan's generation is the newest generation any pod reports, so that
    nothing the controller pushes next is older than what a pod has seen.

    Returns ``None`` when no pod reports any assignment (there is nothing to adopt).
    """
    reported = {name: a for name, a in reports.items() if a is not None}
    if not reported:
        return None
    generation = max(a.generation for a in reported.values())
    base = Plan(generation=generation, job=job, slots=tuple(slot_contents(job, tasks)))
    claims = sorted(reported.items(), key=lambda item: (-item[1].generation, pod_sort_key(item[0])))
    slots = list(base.slots)
    for name, assignment in claims:
        for i, slot in enumerate(slots):
            if slot.pod is None and assignment.same_envs(base.assignment_for(slot, name)):
                slots[i] = replace(slot, pod=name, last_pod=name)
                break
    return replace(base, slots=tuple(slots))


def validate_job(
    job: JobSpec,
    tasks: Sequence[str],
    pods: Iterable[PodRecord],
    *,
    known_tasks: Container[str] | None = None,
) -> list[str]:
    """Checks a job against its resolved ``tasks`` and the registered ``pods``.

    ``known_tasks``, when given, is every task id the pods can run; a task outside it is a
    problem. More slots than tasks is fine (the extra slots are spares with zero envs).

    Returns a list of problems, each saying what to change; empty when the job can run.
    """
    problems: list[str] = []
    if not tasks:
        what = f"suite {job.suite!r} has no tasks" if job.suite is not None else "the job lists no tasks"
        problems.append(f"tasks: {what}; name a suite with tasks or list task ids in 'tasks'")
    seen: set[str] = set()
    for task_id in tasks:
        if task_id in seen:
            problems.append(f"tasks: {task_id!r} appears more than once; list each task once")
        seen.add(task_id)
        if known_tasks is not None and task_id not in known_tasks:
            problems.append(f"tasks: unknown task {task_id!r}; use a task id of a known suite (e.g. 'tiny/lift')")
    per_slot_tasks = math.ceil(len(tasks) / job.pods_per_stage) if tasks else 0
    stages_per_slot = job.num_stages if job.stage_layout == "slices" else 1
    slot_envs = per_slot_tasks * job.group_size * stages_per_slot
    times_stages = f" x {job.num_stages} stages (stage_layout 'slices')" if stages_per_slot > 1 else ""
    for record in sorted(pods, key=lambda r: pod_sort_key(r.pod)):
        if record.capacity.max_envs < slot_envs:
            problems.append(
                f"capacity: pod {record.pod!r} holds at most {record.capacity.max_envs} envs but a slot needs "
                f"{slot_envs} ({per_slot_tasks} tasks x group_size {job.group_size}{times_stages}); raise pods_per_stage "
                f"(now {job.pods_per_stage}), lower group_size, or raise the pods' max_envs (VECSIM_MAX_ENVS)"
            )
    return problems
