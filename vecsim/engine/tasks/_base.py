"""What every task env shares: the task record, seeds, the cache folder and the adapter base."""

from __future__ import annotations

import contextlib
import hashlib
import io
import logging
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np

log = logging.getLogger("vecsim.engine.tasks")


@dataclass(frozen=True)
class TaskSpec:
    """One named, reproducible scene with a natural-language instruction.

    ``num_states`` fixed initial states are named by state ids ``0..num_states-1``;
    ``max_episode_steps`` is the task's default episode length.
    """

    task_id: str
    suite: str
    instruction: str
    scene: str
    num_states: int
    max_episode_steps: int


class UnknownTaskError(KeyError):
    """A task id or suite name that no provider knows. The message names it and lists the suites."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


class TaskSetupError(RuntimeError):
    """A provider cannot build envs on this machine (say, LIBERO's assets are missing)."""


def derive_seed(task_id: str, state_id: int, attempt: int = 0) -> int:
    """Return the 32-bit seed of ``(task_id, state_id, attempt)``: the same on every machine.

    A hash of the text, not Python's ``hash()``, which is salted per process.
    """
    return _hash_seed(f"vecsim:{task_id}:{state_id}:{attempt}")


def scene_seed(task_id: str) -> int:
    """Return the 32-bit seed under which ``task_id``'s scene is built, the same on every machine.

    robosuite draws parts of the model itself at random when an env is made (Lift's cube size,
    for one), so two processes agree on a scene only when they build it under the same seed.
    """
    return _hash_seed(f"vecsim-scene:{task_id}")


def _hash_seed(text: str) -> int:
    return int.from_bytes(hashlib.sha256(text.encode()).digest()[:4], "little")


def cache_dir() -> Path:
    """Return vecsim's cache folder: ``$VECSIM_CACHE_DIR`` or ``~/.cache/vecsim``."""
    return Path(os.environ.get("VECSIM_CACHE_DIR") or Path.home() / ".cache" / "vecsim")


def ensure_gl_backend() -> None:
    """Default MuJoCo's GL backend to EGL (headless) unless the caller chose one. Returns None."""
    os.environ.setdefault("MUJOCO_GL", "egl")


@contextlib.contextmanager
def stdout_to_log() -> Iterator[None]:
    """Send what third-party code prints to stdout to the debug log instead."""
    buffer = io.StringIO()
    try:
        with contextlib.redirect_stdout(buffer):
            yield
    finally:
        for line in buffer.getvalue().splitlines():
            if line.strip():
                log.debug("%s", line)


class TaskEnv(gymnasium.Env):
    """Base of vecsim's task envs: fixed initial states, step counting, the info every task gives.

    ``reset(options={"state_id": k})`` puts the env in fixed initial state ``k``; without a state
    id it draws one from the env's random generator (seeded by ``reset(seed=...)``). Truncation
    comes at ``max_episode_steps`` steps after the last reset. Nothing autoresets; stepping a
    terminated or truncated env is allowed. ``info`` holds ``success`` and ``task_id`` (and
    ``state_id`` after a reset).
    """

    metadata: dict[str, Any] = {"render_modes": []}

    def __init__(self, task: TaskSpec, max_episode_steps: int) -> None:
        if max_episode_steps < 1:
            raise ValueError(f"max_episode_steps must be >= 1, got {max_episode_steps}")
        self.task = task
        self.max_episode_steps = int(max_episode_steps)
        self._elapsed = 0

    @property
    def _max_episode_steps(self) -> int:
        """The episode limit by the name gymnasium's ``TimeLimit`` gives it (trainers read it)."""
        return self.max_episode_steps

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, Any], dict[str, Any]]:
        """Reset to a fixed initial state.

        Returns:
            ``(observation, {"success", "task_id", "state_id"})``.

        Raises:
            ValueError: ``options["state_id"]`` is not an int in ``0..num_states-1``.
        """
        super().reset(seed=seed)
        state_id = self._state_id(options)
        observation, success = self._reset_to(state_id)
        self._elapsed = 0
        return observation, {"success": success, "task_id": self.task.task_id, "state_id": state_id}

    def step(self, action: Any) -> tuple[dict[str, Any], float, bool, bool, dict[str, Any]]:
        """Advance one control step.

        Returns:
            ``(observation, reward, terminated, truncated, {"success", "task_id"})``.
        """
        observation, reward, terminated, truncated, success = self._step(action)
        self._elapsed += 1
        truncated = truncated or self._elapsed >= self.max_episode_steps
        return (
            observation,
            float(reward),
            bool(terminated),
            bool(truncated),
            {"success": success, "task_id": self.task.task_id},
        )

    def _state_id(self, options: dict[str, Any] | None) -> int:
        if not options or options.get("state_id") is None:
            return int(self.np_random.integers(self.task.num_states))
        state_id = options["state_id"]
        if isinstance(state_id, (bool, np.bool_)) or not isinstance(state_id, (int, np.integer)):
            raise ValueError(f"{self.task.task_id}: state_id must be an int, got {state_id!r}")
        if not 0 <= state_id < self.task.num_states:
            raise ValueError(f"{self.task.task_id}: state_id {state_id} out of range 0..{self.task.num_states - 1}")
        return int(state_id)

    def _reset_to(self, state_id: int) -> tuple[dict[str, Any], bool]:
        raise NotImplementedError

    def _step(self, action: Any) -> tuple[dict[str, Any], float, bool, bool, bool]:
        raise NotImplementedError
