"""Each pipeline stage's call state, in the manner of gymnasium's ``AsyncState``. Pure: no I/O.

A stage is ``IDLE`` or waits on exactly one call: ``WAITING_RESET`` (its trajectories only
reset in it), ``WAITING_STEP`` (only step) or ``WAITING_CALL`` (some reset, some step: one round
of :meth:`StageClient.call`). The only transitions:

- ``IDLE -> WAITING_*``: :meth:`StageStates.begin`, for every stage of a call at once, or for none
  (``AlreadyPendingCallError`` naming the busy stages);
- ``WAITING_* -> IDLE``: :meth:`StageStates.end` by the call that began it. The client ends a call
  on its loop before the call's answer is handed over, and again when the call is cancelled, so a
  caller whose ``result()`` returned finds its stages idle; a late end of an older call leaves
  the stage's newer call alone.

A call may hold one pod of a stage rather than the whole stage (``StageClient.pod_call``): calls
on different pods of one stage then wait side by side, and the stage waits while any of them does.
"""

from __future__ import annotations

import enum
import threading
from collections.abc import Callable, Iterable
from typing import Any, TypeVar

from gymnasium.error import AlreadyPendingCallError

__all__ = ["StageState", "StageStates"]

T = TypeVar("T")


class StageState(enum.Enum):
    """What one stage is doing."""

    IDLE = "idle"
    WAITING_RESET = "reset"
    WAITING_STEP = "step"
    WAITING_CALL = "call"

    @classmethod
    def waiting_for(cls, resets: bool, steps: bool) -> StageState:
        """The waiting state of a stage whose trajectories reset (``resets``) and/or step in a call."""
        if resets and steps:
            return cls.WAITING_CALL
        return cls.WAITING_RESET if resets else cls.WAITING_STEP


class StageStates:
    """The state of every stage and the calls each waiting one waits on (thread-safe).

    A call holds whole stages, or one pod of its stages (``pod``); two calls conflict on a stage
    when either holds the whole stage or both hold the same pod.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        # stage -> its holders: (state, call, pod held or None for the whole stage)
        self._waiting: dict[int, list[tuple[StageState, object, str | None]]] = {}

    def state(self, stage_id: int) -> StageState:
        """The stage's state now (``IDLE`` for any stage no call holds; ``WAITING_CALL`` for pod
        calls of different kinds side by side)."""
        with self._lock:
            held = {state for state, _, _ in self._waiting.get(stage_id, ())}
        if not held:
            return StageState.IDLE
        return held.pop() if len(held) == 1 else StageState.WAITING_CALL

    def busy(self, stages: Iterable[int] | None = None) -> list[int]:
        """The sorted ids of ``stages`` (all, if None) that wait on a call."""
        with self._lock:
            return self._busy(stages)

    def pod_busy(self, stage_id: int, pod: str) -> bool:
        """Whether a call holds ``pod`` of stage ``stage_id`` (or the whole stage)."""
        with self._lock:
            return self._conflicts(stage_id, pod)

    def check_idle(self, lanes: Iterable[tuple[int, str]], what: str) -> None:
        """Raises ``AlreadyPendingCallError`` (naming the pods) when a call holds any of ``lanes``
        ``(stage, pod)`` (the pod, or its whole stage), before ``what``."""
        with self._lock:
            busy = sorted({pod for stage, pod in lanes if self._conflicts(stage, pod)})
        if busy:
            raise AlreadyPendingCallError(f"pods {busy} wait on a call; take its result before {what}", "step")

    def _busy(self, stages: Iterable[int] | None) -> list[int]:
        if stages is None:
            return sorted(self._waiting)
        return sorted(s for s in set(stages) if s in self._waiting)

    def _conflicts(self, stage_id: int, pod: str | None) -> bool:
        return any(pod is None or held is None or held == pod for _, _, held in self._waiting.get(stage_id, ()))

    def begin(
        self,
        states: dict[int, StageState],
        call: object,
        start: Callable[[], T] | None = None,
        pod: str | None = None,
    ) -> T | None:
        """Move each stage of ``states`` from ``IDLE`` to its waiting state, held by ``call`` (the
        whole stage, or only ``pod`` of it), and run ``start`` (what sends the call) while no other
        call can begin; return what it returns.

        Raises:
            AlreadyPendingCallError: one of the stages (or the pod) waits on a call (no stage changes).
            ValueError: a target state that is not a waiting one.
        """
        if any(state is StageState.IDLE for state in states.values()):
            raise ValueError(f"a call cannot move a stage to IDLE: {states}")
        with self._lock:
            busy = sorted(stage for stage in states if self._conflicts(stage, pod))
            if busy:
                what = f"stage(s) {busy}" if pod is None else f"pod {pod} of stage(s) {busy}"
                raise AlreadyPendingCallError(f"{what} already wait on a call; take its result first", "step")
            result = start() if start is not None else None
            for stage, state in states.items():
                self._waiting.setdefault(stage, []).append((state, call, pod))
        return result

    def end(self, stages: Iterable[int], call: object) -> None:
        """Let go of those of ``stages`` that ``call`` holds (idempotent)."""
        with self._lock:
            for stage in stages:
                holders = [held for held in self._waiting.get(stage, ()) if held[1] is not call]
                if holders:
                    self._waiting[stage] = holders
                else:
                    self._waiting.pop(stage, None)

    def while_idle(self, what: str, fn: Callable[[], T]) -> T:
        """Run ``fn`` while every stage is idle and none can begin a call; return what it returns.

        Raises:
            AlreadyPendingCallError: some stage waits on a call (``fn`` is not run).
        """
        with self._lock:
            busy = self._busy(None)
            if busy:
                raise AlreadyPendingCallError(
                    f"stages {busy} have calls in flight; wait for them before {what}", "reset"
                )
            return fn()

    def end_all(self) -> list[Any]:
        """Move every stage to ``IDLE``; return the calls that held any (each once)."""
        with self._lock:
            calls = list({id(call): call for holders in self._waiting.values() for _, call, _ in holders}.values())
            self._waiting.clear()
        return calls
