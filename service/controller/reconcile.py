"""Reconcile: what the pods should run vs what they report, and the pushes that close the gap.

:func:`reconcile` is pure and level-triggered: it looks only at the desired assignments and what
is observed now, so it can run at any time, any number of times, and says the same thing until
something changes. The I/O around it, which pushes what it asks for, is
:class:`service.controller.reconciler.Reconciler`.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from vecsim.config import Assignment
from vecsim.plan import Plan


@dataclass(frozen=True)
class PushAssignment:
    """Send ``assignment`` to the pod ``pod`` at ``url`` (``PUT {url}/v1/assignment``)."""

    pod: str
    url: str
    assignment: Assignment


Action = PushAssignment


@dataclass(frozen=True)
class ObservedPod:
    """What the controller knows of one live pod right now.

    ``reported`` is the assignment its last heartbeat carried; ``acked`` the last assignment it
    accepted from a push (at ``acked_at``); no push is tried before ``retry_at`` (after failures).
    """

    url: str
    reported: Assignment | None = None
    acked: Assignment | None = None
    acked_at: float | None = None
    retry_at: float = 0.0


@dataclass(frozen=True)
class Observed:
    now: float
    pods: Mapping[str, ObservedPod]


@dataclass(frozen=True)
class Desired:
    """The assignment every live pod should run (spares get one with no tasks)."""

    assignments: Mapping[str, Assignment]
    repush_after_s: float = 5.0


def desired_assignments(plan: Plan, pods: Iterable[str]) -> dict[str, Assignment]:
    """Returns, for each of ``pods``, its slot's assignment, or an empty one if it holds no slot."""
    held = plan.assignments
    return {name: held.get(name) or plan.spare_assignment(name) for name in pods}


def satisfied(want: Assignment, reported: Assignment | None) -> bool:
    """True when a pod reporting ``reported`` already runs ``want``.

    A spare (``want`` has no tasks) is satisfied by any assignment without tasks, whatever its
    generation: it serves nothing, so a newer generation changes nothing for it.
    """
    if reported is None:
        return False
    if not want.tasks:
        return not reported.tasks
    return reported == want


def reconcile(desired: Desired, observed: Observed) -> list[Action]:
    """Returns the pushes that bring every observed pod to its desired assignment.

    A pod is left alone when it already reports its assignment, when it accepted that exact
    assignment less than ``repush_after_s`` ago (its next heartbeat will say so), or while it is
    backing off after a failed push. Pods with no desired assignment, or not observed, are left
    alone. Idempotent: the same inputs give the same actions, in pod-name order.
    """
    actions: list[Action] = []
    for name in sorted(desired.assignments):
        want = desired.assignments[name]
        pod = observed.pods.get(name)
        if pod is None or satisfied(want, pod.reported):
            continue
        if observed.now < pod.retry_at:
            continue
        recently_acked = pod.acked == want and pod.acked_at is not None
        if recently_acked and observed.now - pod.acked_at < desired.repush_after_s:
            continue
        actions.append(PushAssignment(pod=name, url=pod.url, assignment=want))
    return actions


def safe_generation(plan: Plan, reports: Mapping[str, Assignment | None]) -> int:
    """Returns a generation for ``plan`` that no pod would refuse or mistake for one it has.

    Pods refuse older generations and treat a generation they already run as a repeat; so when a
    pod reports a newer generation than the plan, or the plan's generation with other content,
    the plan must move past every reported generation.
    """
    want = desired_assignments(plan, reports)
    newest = plan.generation
    clash = False
    for name, reported in reports.items():
        if reported is None:
            continue
        newest = max(newest, reported.generation)
        if reported.generation > plan.generation:
            clash = True
        elif reported.generation == plan.generation and not satisfied(want[name], reported):
            clash = True
    return newest + 1 if clash else plan.generation
