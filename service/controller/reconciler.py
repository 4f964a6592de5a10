"""The controller's reconcile loop: the I/O shell around the pure
:func:`service.controller.reconcile.reconcile`. One pass expires silent pods, re-plans, asks
``reconcile`` what to do, and pushes every assignment concurrently (``PUT /v1/assignment`` on
each pod, bounded by a timeout)."""

from __future__ import annotations

import asyncio
import logging
import time

import httpx

from vecsim.transport import send_capped

from .reconcile import Action, reconcile
from .state import ControllerState

log = logging.getLogger(__name__)

# A pod answers a push with a line of JSON; anything much larger is not a pod's answer.
_MAX_PUSH_ANSWER_BYTES = 1 << 20


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
