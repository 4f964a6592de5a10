"""The controller's state: the pod registry (kept by heartbeats), the job, and its plan.

Everything here is synchronous and runs on the app's event loop, so a request handler and the
reconcile loop never see each other's half-made changes.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from prometheus_client import CollectorRegistry

from vecsim.config import Assignment, JobSpec, PodCapacity, PodRecord, PodRegistration, RoutingTable
from vecsim.plan import Plan, Slot, adopt, plan

from ..models import Problem, Readiness
from .errors import NoJobError, NoPlanError, PodUrlConflictError, UnknownPodError
from .metrics import ControllerMetrics, Gauges
from .reconcile import Action, Desired, Observed, ObservedPod, desired_assignments, safe_generation, satisfied
from .settings import ControllerSettings

log = logging.getLogger(__name__)


@dataclass
class PodEntry:
    """One registered pod: what it said about itself and what the controller did to it."""

    name: str
    url: str
    capacity: PodCapacity
    last_seen: float  # wall clock, for people
    seen_at: float  # the controller's clock, for the TTL
    heard: bool = False  # a heartbeat arrived since it registered
    ready: bool = False
    reported: Assignment | None = None
    acked: Assignment | None = None
    acked_at: float | None = None
    push_failures: int = 0
    push_error: str = ""  # why the last push failed ("" after one that succeeded)
    retry_at: float = 0.0

    @property
    def generation(self) -> int | None:
        return self.reported.generation if self.reported is not None else None


class ControllerState:
    """Registry, job and plan of one controller."""

    def __init__(
        self,
        settings: ControllerSettings,
        *,
        clock: Callable[[], float] = time.monotonic,
        wall: Callable[[], float] = time.time,
    ) -> None:
        self.settings = settings
        self.clock = clock
        self.wall = wall
        self.started_at = clock()
        self.pods: dict[str, PodEntry] = {}
        self.job: JobSpec | None = None
        self.tasks: tuple[str, ...] = ()
        self.plan: Plan | None = None
        # Slot holders that registered again while still registered: new processes, new envs.
        self.restarted: set[str] = set()
        self.wake = asyncio.Event()
        # Counts every change that can alter the plan or the pushes; a reconcile pass that left
        # every pod running its assignment records the count, and passes skip until it moves.
        self.changes = 0
        self._settled_at: int | None = None
        # Counts changes of what a plan is made of (the job, the live pods, restarts): while it
        # stands still, re-planning would give the same plan, and heartbeats alone do not move it.
        self._members = 0
        self._planned_at: int | None = None
        # When the controller's loop last ran (see tick); None until the loop starts ticking.
        self._ticked_at: float | None = None
        self.metrics = ControllerMetrics()
        self.metrics.watch(self.gauges)

    # Registry

    def register(self, registration: PodRegistration) -> PodRecord:
        """Adds a pod, or replaces a pod of the same name (a restarted process). Returns its record."""
        now = self.clock()
        name = registration.pod
        if name in self.pods and self.plan is not None and self.plan.slot_of(name):
            log.info("pod %s registered again while holding a slot: treating it as restarted", name)
            self.restarted.add(name)
        self.pods[name] = PodEntry(
            name=name,
            url=registration.url.rstrip("/"),
            capacity=registration.capacity,
            last_seen=self.wall(),
            seen_at=now,
        )
        self.metrics.registrations.inc()
        log.info("pod %s registered at %s (max_envs %d)", name, registration.url, registration.capacity.max_envs)
        self.changes += 1
        self._members += 1
        self.wake.set()
        return self.record(name)

    def heartbeat(self, name: str, url: str, assignment: Assignment | None, ready: bool) -> int | None:
        """Records what a pod reports. Returns the plan's generation (``None`` without a plan).

        Raises:
            UnknownPodError: ``name`` is not registered.
            PodUrlConflictError: ``url`` is not the one ``name`` registered at (nothing changes).
        """
        entry = self.pods.get(name)
        if entry is None:
            ttl = self.settings.heartbeat_ttl_s
            raise UnknownPodError(
                f"pod {name!r} is not registered (or was silent for over {ttl} s): POST /v1/pods first"
            )
        if url.rstrip("/") != entry.url:
            self.metrics.url_conflicts.inc()
            raise PodUrlConflictError(
                f"pod {name!r} is registered at {entry.url}, the heartbeat says {url.rstrip('/')}: a live pod's "
                "URL changes only by registering again (POST /v1/pods)"
            )
        changed = entry.reported != assignment or entry.ready != ready or not entry.heard
        entry.reported = assignment
        entry.ready = ready
        entry.heard = True
        entry.seen_at = self.clock()
        entry.last_seen = self.wall()
        self.metrics.heartbeats.inc()
        if changed:
            self.changes += 1
            self.wake.set()
        return self.plan.generation if self.plan is not None else None

    def tick(self) -> float:
        """Notes that the controller's event loop runs now; returns the stall it ended (0.0: none).

        A gap since the last tick longer than ``settings.stall_after_s`` is a stall of the
        controller itself (GC, a long pass, an overloaded machine): no heartbeat could be taken in
        meanwhile, so that time is not counted against the pods, whose heartbeat deadlines move on
        by the whole gap. The first tick starts the watch; a state that is never ticked (no loop,
        as in tests driving it pass by pass) counts every second against the pods.
        """
        now = self.clock()
        last, self._ticked_at = self._ticked_at, now
        gap = 0.0 if last is None else now - last
        if gap <= self.settings.stall_after_s:
            return 0.0
        for entry in self.pods.values():
            entry.seen_at += gap
        self.metrics.stalls.inc()
        self.metrics.stalled_seconds.inc(gap)
        log.warning(
            "the controller did not run for %.1f s; %d pods' heartbeat deadlines move on by as much",
            gap,
            len(self.pods),
        )
        return gap

    def expire(self) -> list[str]:
        """Drops pods not heard from within the TTL, not counting the controller's own stalls
        (see :meth:`tick`). Returns their names."""
        if self._ticked_at is not None:
            # A pass may run before the loop's ticker after a stall: measure the stall first.
            self.tick()
        now = self.clock()
        gone = [n for n, e in self.pods.items() if now - e.seen_at > self.settings.heartbeat_ttl_s]
        for name in gone:
            del self.pods[name]
            self.restarted.discard(name)
            self.metrics.expired.inc()
            log.warning("pod %s dropped: no heartbeat for over %s s", name, self.settings.heartbeat_ttl_s)
        if gone:
            self.changes += 1
            self._members += 1
        return gone

    def record(self, name: str) -> PodRecord:
        """Returns the public record of one registered pod (stage from the plan)."""
        entry = self.pods[name]
        slot = self.plan.slot_of(name) if self.plan is not None else None
        return PodRecord(
            pod=entry.name,
            url=entry.url,
            capacity=entry.capacity,
            stage_id=slot.stage_id if slot is not None else None,
            ready=entry.ready,
            generation=entry.generation,
            last_seen=entry.last_seen,
        )

    def records(self) -> list[PodRecord]:
        """Returns every registered pod's record, by name."""
        return [self.record(name) for name in sorted(self.pods)]

    # Job and plan

    def set_job(self, job: JobSpec, tasks: Sequence[str]) -> None:
        """Makes ``job`` (with its resolved ``tasks``) the desired job; the next pass plans it."""
        if job != self.job or tuple(tasks) != self.tasks:
            log.info(
                "job %s: %d tasks, %d stages, stage_layout %s, pods_per_stage %d (%d pods)",
                job.job_id,
                len(tasks),
                job.num_stages,
                job.stage_layout,
                job.pods_per_stage,
                job.pods_needed,
            )
        self.job = job
        self.tasks = tuple(tasks)
        self.changes += 1
        self._members += 1
        self.wake.set()

    def _may_plan_first(self, job: JobSpec, adopted: Plan | None) -> bool:
        # A fresh controller waits for pods to say what they run, so that it adopts their layout
        # instead of reshuffling it. It plans at once when every slot was adopted, or when every
        # registered pod has reported, enough of them for the job, and each slot left unfilled
        # can go to a pod that reports no assignment at all: a restarted process, whose envs are
        # gone (a live spare reports its empty assignment, and does not count). Else it waits
        # for the grace period, for a slot holder that has not reported yet.
        if adopted is not None and not adopted.unfilled:
            return True
        if self.clock() - self.started_at >= self.settings.adopt_grace_s:
            return True
        heard = [e for e in self.pods.values() if e.heard]
        if len(heard) < len(self.pods) or len(heard) < job.pods_needed:
            return False
        fresh = [e for e in heard if e.reported is None]
        return adopted is None or len(fresh) >= len(adopted.unfilled)

    def replan(self) -> Plan | None:
        """Brings the plan up to date with the job and the live pods. Returns it (``None``: not yet)."""
        if self.job is None:
            return None
        previous = self.plan
        if previous is None:
            reports = {n: e.reported for n, e in self.pods.items() if e.heard}
            previous = adopt(self.job, self.tasks, reports)
            if not self._may_plan_first(self.job, previous):
                return None
            if previous is not None:
                log.info("adopted %d slots at generation %d from pod reports", len(previous.pods), previous.generation)
        if self.plan is not None and self._planned_at == self._members:
            new = self.plan
        else:
            live = [PodRecord(pod=e.name, url=e.url, capacity=e.capacity) for e in self.pods.values()]
            new = plan(self.job, live, previous, self.tasks, restarted=self.restarted)
            self._planned_at = self._members
        generation = safe_generation(new, {n: e.reported for n, e in self.pods.items()})
        if generation != new.generation:
            new = new.with_generation(generation)
        if previous is None or new.generation != previous.generation:
            log.info(
                "plan generation %d: %s; unfilled %s",
                new.generation,
                ", ".join(f"{s.pod}={s.name}" for s in new.slots if s.pod) or "no pods",
                [s.key for s in new.unfilled] or "none",
            )
        self.plan = new
        self.restarted.clear()
        return new

    # Reconcile inputs and outcomes

    def desired(self) -> Desired:
        """Returns every live pod's desired assignment (empty when there is no plan)."""
        if self.plan is None:
            return Desired(assignments={}, repush_after_s=self.settings.repush_after_s)
        return Desired(
            assignments=desired_assignments(self.plan, self.pods), repush_after_s=self.settings.repush_after_s
        )

    def observed(self) -> Observed:
        """Returns what is known of the live pods now."""
        pods = {
            n: ObservedPod(url=e.url, reported=e.reported, acked=e.acked, acked_at=e.acked_at, retry_at=e.retry_at)
            for n, e in self.pods.items()
        }
        return Observed(now=self.clock(), pods=pods)

    @property
    def settled(self) -> bool:
        """True when nothing changed since a pass found every live pod running its assignment:
        another pass would find the same plan and push nothing (no retry or re-push is pending,
        as those only concern pods that do not run their assignment)."""
        return self._settled_at == self.changes

    def note_pass(self, desired: Desired, observed: Observed, actions: Sequence[Action]) -> None:
        """Records whether a pass left the state settled (see :attr:`settled`)."""
        done = (
            self.plan is not None
            and not actions
            and all(satisfied(want, observed.pods[name].reported) for name, want in desired.assignments.items())
        )
        self._settled_at = self.changes if done else None

    def record_push(self, action: Action, *, ok: bool, detail: str = "") -> None:
        """Notes how a push went: an accepted one is remembered, a failed one backs off."""
        entry = self.pods.get(action.pod)
        self.metrics.pushes.labels(result="ok" if ok else "failed").inc()
        self.changes += 1
        if entry is None:
            return
        if ok:
            entry.acked, entry.acked_at = action.assignment, self.clock()
            entry.push_failures, entry.push_error, entry.retry_at = 0, "", 0.0
            log.info("pod %s accepted generation %d", action.pod, action.assignment.generation)
            return
        entry.push_failures += 1
        entry.push_error = detail
        delay = min(self.settings.push_backoff_max_s, 0.25 * 2 ** (entry.push_failures - 1))
        entry.retry_at = self.clock() + delay
        log.warning(
            "push of generation %d to pod %s failed (%s); retrying in %.2f s",
            action.assignment.generation,
            action.pod,
            detail,
            delay,
        )

    # Readiness and routing

    def problems(self) -> list[str]:
        """Returns why the job is not ready (empty: every slot's pod runs the plan and is ready)."""
        if self.job is None:
            return ["no job: PUT /v1/job"]
        if self.plan is None:
            return ["no plan yet: waiting for pods to register and report what they run"]
        # Spares are found once, not once per unfilled slot: with a thousand pods the readiness
        # check runs on every GET /v1/routing and /readyz, on the event loop.
        spares = sorted((n, e.capacity.max_envs) for n, e in self.pods.items() if self.plan.slot_of(n) is None)
        problems = [self._unfilled_problem(slot, spares) for slot in self.plan.unfilled]
        assignments = self.plan.assignments
        for slot in self.plan.slots:
            if slot.pod is None:
                continue
            entry = self.pods[slot.pod]
            want = assignments[slot.pod]
            if entry.reported != want:
                have = "nothing" if entry.reported is None else f"generation {entry.reported.generation}"
                # A pod's refusal (an assignment it cannot build) is how a job's task that no pod
                # can serve shows: the controller makes no env to find out before.
                refused = f" (its last push failed: {entry.push_error})" if entry.push_error else ""
                problems.append(f"pod {slot.pod} runs {have}, the plan is generation {want.generation}{refused}")
            elif not entry.ready:
                problems.append(f"pod {slot.pod} is not ready (building its envs)")
        return problems

    def _unfilled_problem(self, slot: Slot, spares: list[tuple[str, int]]) -> str:
        small = [name for name, max_envs in spares if max_envs < slot.num_envs]
        why = f" (pods {', '.join(small)} have max_envs below the {slot.num_envs} envs it needs)" if small else ""
        return f"{slot.name} has no pod{why}"

    @property
    def ready(self) -> bool:
        return not self.problems()

    def readiness(self) -> Readiness | Problem:
        """``/readyz``'s answer: ready once every slot's pod runs the plan and is ready, else
        what is missing."""
        problems = self.problems()
        if problems or self.plan is None:
            return Problem(detail="not ready: " + "; ".join(problems))
        return Readiness(status="ready", generation=self.plan.generation)

    @property
    def registry(self) -> CollectorRegistry:
        """The controller's metrics registry, which ``/metrics`` serves."""
        return self.metrics.registry

    def routing(self) -> RoutingTable:
        """Returns the routing table of the current plan.

        Raises:
            NoJobError: no job was set.
            NoPlanError: the job is not planned yet.
        """
        if self.job is None:
            raise NoJobError("no job: PUT /v1/job first")
        if self.plan is None:
            raise NoPlanError("no plan yet: waiting for pods to register and report what they run")
        return self.plan.routing_table({n: e.url for n, e in self.pods.items()}, ready=self.ready)

    def gauges(self) -> Gauges:
        """Returns the values the metrics report at a scrape."""
        return Gauges(
            pods=len(self.pods),
            ready_pods=sum(e.ready for e in self.pods.values()),
            generation=self.plan.generation if self.plan is not None else 0,
            unfilled_slots=len(self.plan.unfilled) if self.plan is not None else 0,
            job_ready=self.ready,
            stage_ready_pods=self._stage_ready_pods(),
        )

    def _stage_ready_pods(self) -> dict[int, int]:
        if self.plan is None:
            return {}
        counts = dict.fromkeys(range(self.plan.job.num_stages), 0)
        for slot in self.plan.slots:
            entry = self.pods.get(slot.pod) if slot.pod is not None else None
            if entry is not None and entry.ready:
                for stage in counts if slot.stage_id is None else (slot.stage_id,):
                    counts[stage] += 1
        return counts
