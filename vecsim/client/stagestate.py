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
    """The state of every stage and the call each waiting one waits on (thread-safe)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._waiting: dict[int, tuple[StageState, object]] = {}

    def state(self, stage_id: int) -> StageState:
        """The stage's state now (``IDLE`` for any stage no call holds)."""
        with self._lock:
            held = self._waiting.get(stage_id)
        return StageState.IDLE if held is None else held[0]

    def busy(self, stages: Iterable[int] | None = None) -> list[int]:
        """The sorted ids of ``stages`` (all, if None) that wait on a call."""
        with self._lock:
            return self._busy(stages)

    def _busy(self, stages: Iterable[int] | None) -> list[int]:
        if stages is None:
            return sorted(self._waiting)
        return sorted(s for s in set(stages) if s in self._waiting)

    def begin(self, states: dict[int, StageState], call: object, start: Callable[[], T] | None = None) -> T | None:
        """Move each stage of ``states`` from ``IDLE`` to its waiting state, held by ``call``, and
        run ``start`` (what sends the call) while no other call can begin; return what it returns.

        Raises:
            AlreadyPendingCallError: one of the stages waits on a call (no stage changes).
            ValueError: a target state that is not a waiting one.
        """
        if any(state is StageState.IDLE for state in states.values()):
            raise ValueError(f"a call cannot move a stage to IDLE: {states}")
        with self._lock:
            busy = self._busy(states)
            if busy:
                raise AlreadyPendingCallError(f"stage(s) {busy} already wait on a call; take its result first", "step")
            result = start() if start is not None else None
            for stage, state in states.items():
                self._waiting[stage] = (state, call)
        return result

    def end(self, stages: Iterable[int], call: object) -> None:
        """Move those of ``stages`` that ``call`` holds back to ``IDLE`` (idempotent)."""
        with self._lock:
            for stage in stages:
                held = self._waiting.get(stage)
                if held is not None and held[1] is call:
                    del self._waiting[stage]

    def while_idle(self, what: str, fn: Callable[[], T]) -> T:
        """Run ``fn`` while every stage is idle and none can begin a call; return what it returns.

        Raises:
            AlreadyPendingCallError: some stage waits on a call (``fn`` is not run).
        """
        with self._lock:
            busy = self._busy(None)
            if busy:
                raise AlreadyPendingCallError(f"stages {busy} have calls in flight; wait for them before {what}", "reset")
            return fn()

    def end_all(self) -> list[Any]:
        """Move every stage to ``IDLE``; return the calls that held any (each once)."""
        with self._lock:
            calls = list({id(call): call for _, call in self._waiting.values()}.values())
            self._waiting.clear()
        return calls
