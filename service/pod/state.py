"""The state of one pod: its assignment, its envs, and the single worker thread that owns them.

All simulation work (building, stepping, rendering, closing) runs on one worker thread, in the
order it was submitted, so env access is serialised and the event loop stays free for health
checks; except that cheap scenes are reset and stepped on the event loop itself
(:func:`steps_on_event_loop`). The assignment, the phase and the current env are changed only on
the event loop.
"""

from __future__ import annotations

import asyncio
import logging
import uuid
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Literal, TypeVar

from prometheus_client import CollectorRegistry

from vecsim.config import Assignment
from vecsim.engine import InvalidRequestError
from vecsim.engine.base import PodEngine, engine_kind
from vecsim.engine.tasks import TaskSetupError, UnknownTaskError

from ..models import Problem, Readiness
from .errors import NotReadyError, StaleGenerationError
from .idempotency import AnswerMemory
from .metrics import PodMetrics
from .settings import PodSettings

log = logging.getLogger(__name__)

T = TypeVar("T")
Phase = Literal["unassigned", "building", "ready", "failed"]


def check_assignment(settings: PodSettings, assignment: Assignment) -> None:
    """Check that this pod can run ``assignment``: it is for this pod, fits ``max_envs``, its
    engine is installed here, and its tasks exist for that engine and share their spaces. Cheap:
    builds no env (a gym task's env is made to read its spaces).

    Raises:
        InvalidRequestError: the message names the field at fault (422).
    """
    if assignment.pod != settings.name:
        raise InvalidRequestError(f"pod: assignment is for pod {assignment.pod!r}, this is pod {settings.name!r}")
    if assignment.num_envs > settings.max_envs:
        raise InvalidRequestError(
            f"tasks: assignment asks for {assignment.num_envs} envs, pod {settings.name} hosts at most "
            f"{settings.max_envs} (VECSIM_MAX_ENVS)"
        )
    try:
        kind = engine_kind(assignment.engine)
    except ImportError as exc:
        raise InvalidRequestError(
            f"engine: pod {settings.name} cannot run engine {assignment.engine!r}: {exc}"
        ) from None
    try:
        kind.spaces(assignment)
    except InvalidRequestError:
        raise
    except (UnknownTaskError, TaskSetupError, ValueError) as exc:
        message = str(exc)
        raise InvalidRequestError(message if message.startswith("tasks:") else f"tasks: {message}") from None


def steps_on_event_loop(assignment: Assignment) -> bool:
    """Whether the pod resets and steps ``assignment``'s envs on its event loop rather than on
    its worker thread, as its engine decides (``EngineKind.steps_on_event_loop``: the CPU engine's
    cheap scenes). Raises nothing (the assignment was checked when it was taken)."""
    return engine_kind(assignment.engine).steps_on_event_loop(assignment)


class PodState:
    """One pod's assignment and envs; the app keeps one in ``app.state.pod``."""

    def __init__(self, settings: PodSettings, metrics: PodMetrics) -> None:
        self.settings = settings
        self.metrics = metrics
        self.assignment: Assignment | None = None
        self.env: PodEngine | None = None
        self.phase: Phase = "unassigned"
        self.detail = "no assignment yet"
        # Names one build of the envs: new whenever they are built anew, kept when only the
        # generation moves on, so a client can tell whether its trajectories survived.
        self.instance: str | None = None
        # Whether data-plane calls run on the event loop (cheap scenes); set with each build.
        self.inline = False
        # The answers of keyed resets and steps (exactly once); one per build of the envs.
        self.answers = AnswerMemory(0)
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"{settings.name}-sim")
        self._build_task: asyncio.Task[None] | None = None
        self._building_for: Assignment | None = None
        # Every env the worker has built and not yet closed, touched only on the worker thread,
        # so that shutdown closes an env whose build outlived the coroutine that waited for it.
        self._live_envs: list[PodEngine] = []

    @property
    def generation(self) -> int | None:
        return None if self.assignment is None else self.assignment.generation

    @property
    def ready(self) -> bool:
        return self.phase == "ready"

    def readiness(self) -> Readiness | Problem:
        """``/readyz``'s answer: ready once the envs of the current assignment are built and
        rendered a frame; else why not (no assignment, building or rebuilding, failed)."""
        if not self.ready or self.env is None:
            return Problem(detail=f"pod {self.settings.name} is not ready: {self.detail}")
        return Readiness(status="ready", generation=self.generation, num_envs=self.env.num_envs)

    @property
    def registry(self) -> CollectorRegistry:
        """The pod's metrics registry, which ``/metrics`` serves."""
        return self.metrics.registry

    async def run(self, fn: Callable[..., T], *args: object) -> T:
        """Run ``fn(*args)`` on the worker thread, after everything submitted before it.

        Returns:
            What ``fn`` returns.

        Raises:
            Whatever ``fn`` raises.
        """
        call = self.metrics.queued()

        def started() -> T:
            call.started()
            return fn(*args)

        try:
            return await asyncio.get_running_loop().run_in_executor(self._executor, started)
        finally:
            call.started()  # a call cancelled before it ran

    def serving_env(self, generation: int) -> PodEngine:
        """The env that serves a data-plane request made for ``generation``.

        Returns:
            The current env.

        Raises:
            StaleGenerationError: ``generation`` is not the pod's (409, both named).
            NotReadyError: no assignment yet, or the envs are being built or failed (503).
        """
        if self.assignment is None:
            raise NotReadyError(f"pod {self.settings.name} has no assignment yet")
        if generation != self.assignment.generation:
            raise StaleGenerationError(
                f"request is for generation {generation} but pod {self.settings.name} is at "
                f"generation {self.assignment.generation}; re-read the routing table"
            )
        return self.current_env()

    def current_env(self) -> PodEngine:
        """The env now serving, whatever the generation.

        Returns:
            The current env.

        Raises:
            NotReadyError: no assignment yet, or the envs are being built or failed (503).
        """
        if self.env is None or not self.ready:
            raise NotReadyError(f"pod {self.settings.name} is not ready: {self.detail}")
        return self.env

    async def assign(self, assignment: Assignment) -> bool:
        """Take ``assignment`` on; build its envs in the background if their content changed.

        Returns:
            Whether the envs are rebuilt (False when only the generation moved on, or when the
            same assignment arrives again).

        Raises:
            InvalidRequestError: the assignment names another pod, exceeds ``max_envs`` or names
                an unknown task (422); nothing changes.
            StaleGenerationError: the generation is older than the pod's, or equal to it with
                different content (409); nothing changes.
        """
        self._check_generation(assignment)
        if not assignment.same_envs(self.assignment):
            # Off the worker thread, which may be busy building; this touches no env of ours.
            await asyncio.to_thread(check_assignment, self.settings, assignment)
            # Another assignment may have arrived while the spaces were being checked.
            self._check_generation(assignment)
        current, self.assignment = self.assignment, assignment
        if self._build_task is not None and not self._build_task.done():
            # The running build notices a change of content when it finishes and builds again.
            return not assignment.same_envs(self._building_for)
        if self.phase == "ready" and assignment.same_envs(current):
            if assignment.generation != current.generation:
                log.info("pod %s: generation %d adopted, no rebuild", self.settings.name, assignment.generation)
            return False
        self._start_build()
        return True

    def rebuild_after_crash(self, env: PodEngine, reason: str) -> None:
        """Mark the pod not ready and rebuild its envs, unless ``env`` was already replaced."""
        if env is not self.env:
            return
        log.error("pod %s: simulation crashed (%s); rebuilding its envs", self.settings.name, reason)
        self._start_build()

    async def close(self) -> None:
        """Stop building, close every env the worker holds, and stop the worker thread."""
        if self._build_task is not None:
            self._build_task.cancel()
        self.env = None
        self.phase = "unassigned"
        self.detail = "shutting down"
        self.metrics.ready.set(0)
        await self.run(self._close_all)
        self._executor.shutdown(wait=True)

    def _check_generation(self, assignment: Assignment) -> None:
        current = self.assignment
        if current is None:
            return
        if assignment.generation < current.generation:
            raise StaleGenerationError(
                f"assignment generation {assignment.generation} is older than pod "
                f"{self.settings.name}'s generation {current.generation}"
            )
        if assignment.generation == current.generation and assignment != current:
            raise StaleGenerationError(
                f"pod {self.settings.name} already holds a different assignment for "
                f"generation {current.generation}; send a new generation to change it"
            )

    def _start_build(self) -> None:
        self.env = None
        self.inline = False
        self.instance = None
        self.phase = "building"
        self.detail = "building envs"
        self.metrics.ready.set(0)
        self._build_task = asyncio.get_running_loop().create_task(self._build())

    async def _build(self) -> None:
        while True:
            target = self.assignment
            assert target is not None
            self._building_for = target
            log.info(
                "pod %s: building %d envs for generation %d (%s)",
                self.settings.name,
                target.num_envs,
                target.generation,
                ", ".join(f"{b.task_id} x{b.num_envs}" for b in target.tasks) or "spare",
            )
            self.detail = f"building {target.num_envs} envs for generation {target.generation}"
            try:
                env = await self.run(self._build_env, target)
            except Exception as exc:
                log.exception("pod %s: building envs for generation %d failed", self.settings.name, target.generation)
                if target.same_envs(self.assignment):
                    self.phase = "failed"
                    self.detail = f"building envs for generation {target.generation} failed: {exc}"
                    return
                continue
            if target.same_envs(self.assignment):
                self.env = env
                self.inline = steps_on_event_loop(target)
                self.instance = uuid.uuid4().hex
                self.answers = AnswerMemory(env.num_envs)
                self.phase = "ready"
                self.detail = f"serving generation {self.generation}"
                self.metrics.serving(env.num_envs)
                log.info("pod %s: ready, %d envs, generation %s", self.settings.name, env.num_envs, self.generation)
                return
            # The assignment changed while building: this env is already out of date.
            await self.run(self._close_env, env)

    def _build_env(self, assignment: Assignment) -> PodEngine:
        """Worker thread: close what the worker holds, then build the envs on the assignment's
        engine. Building resets every env to state 0, which renders each camera, so a built env
        has proven that a render works."""
        self._close_all()
        env = engine_kind(assignment.engine).build(
            assignment,
            timeout_s=self.settings.step_timeout_s,
            build_timeout_s=self.settings.build_timeout_s,
            max_chunk=self.settings.max_chunk,
        )
        self._live_envs.append(env)
        return env

    def _close_env(self, env: PodEngine) -> None:
        """Worker thread: close one env, logging (not raising) a failure to close."""
        if env in self._live_envs:
            self._live_envs.remove(env)
        try:
            env.close()
        except Exception:
            log.exception("pod %s: closing envs failed", self.settings.name)

    def _close_all(self) -> None:
        for env in list(self._live_envs):
            self._close_env(env)
