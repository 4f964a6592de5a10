"""Reconcile: what the pods should run vs what they report, and the pushes that close the gap.

:func:`reconcile` is pure and level-triggered: it looks only at the desired assignments and what
is observed now, so it can run at any time, any number of times, and says the same thing until
something changes. :class:`Reconciler` is the I/O around it: one pass expires silent pods,
re-plans, asks :func:`reconcile` what to do, and pushes every assignment concurrently
(``PUT /v1/assignment`` on each pod, bounded by a timeout).
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

import httpx

from vecsim.config import Assignment
from vecsim.plan import Plan
from vecsim.transport import send_capped

if TYPE_CHECKING:
    from .state import ControllerState

log = logging.getLogger(__name__)

# A pod answers a push with a line of JSON; anything much larger is not a pod's answer.
_MAX_PUSH_ANSWER_BYTES = 1 << 20


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


class Reconciler:
    """The I/O shell around :func:`reconcile` for one controller's state."""

    def __init__(self, state: ControllerState, client: httpx.AsyncClient) -> None:
        self._state = state
        self._client = client

    async def run_once(self) -> list[Action]:
        """One pass: expire, re-plan, push (re-planning is skipped while the state is settled).
        Returns the pushes it tried."""
        state = self._state
        started = time.perf_counter()
        state.expire()
        if state.settled:
            # Planning and comparing every pod's assignment blocks the event loop for tens of
            # milliseconds with a thousand pods; when nothing changed it would find nothing to do.
            state.metrics.reconcile_seconds.observe(time.perf_counter() - started)
            return []
        state.replan()
        desired, observed = state.desired(), state.observed()
        actions = reconcile(desired, observed)
        state.note_pass(desired, observed, actions)
        if actions:
            targets = {a.pod: state.pods.get(a.pod) for a in actions}
            outcomes = await asyncio.gather(*(self._push(a) for a in actions))
            for action, (ok, detail) in zip(actions, outcomes):
                # A pod that registered again meanwhile is a new process: the outcome is not its.
                if state.pods.get(action.pod) is targets[action.pod]:
                    state.record_push(action, ok=ok, detail=detail)
        state.metrics.reconcile_seconds.observe(time.perf_counter() - started)
        return actions

    async def run(self, stop: asyncio.Event) -> None:
        """Reconciles every ``reconcile_interval_s``, or sooner when the state asks, until ``stop``."""
        state = self._state
        while not stop.is_set():
            # Cleared before the pass, so a wake-up during it starts the next pass at once.
            state.wake.clear()
            try:
                await self.run_once()
            except Exception:
                log.exception("reconcile pass failed; retrying next interval")
            waiters = [asyncio.ensure_future(stop.wait()), asyncio.ensure_future(state.wake.wait())]
            await asyncio.wait(
                waiters, timeout=state.settings.reconcile_interval_s, return_when=asyncio.FIRST_COMPLETED
            )
            for waiter in waiters:
                waiter.cancel()

    async def _push(self, action: Action) -> tuple[bool, str]:
        url = f"{action.url}/v1/assignment"
        try:
            async with asyncio.timeout(self._state.settings.push_timeout_s):
                request = self._client.build_request("PUT", url, json=action.assignment.model_dump(mode="json"))
                response = await send_capped(self._client, request, _MAX_PUSH_ANSWER_BYTES)
        except TimeoutError:
            return False, f"no answer within {self._state.settings.push_timeout_s} s"
        except Exception as exc:  # noqa: BLE001 - whatever the pod's side did, the push failed and backs off
            return False, f"{type(exc).__name__}: {exc}"
        if response.status_code == 200:
            return True, ""
        return False, f"HTTP {response.status_code}: {response.content[:500].decode('utf-8', 'replace')}"
