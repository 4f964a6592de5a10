"""The pod's engine seam: what a pod asks of whatever simulates its envs, and how it picks one.

A pod talks to one :class:`PodEngine`: it builds it for an assignment, resets and chunk-steps its
envs by env index, reads one env's camera frame, and closes it; besides, it reads the engine's
spaces, env count and the last call's timing. Which engine a job runs is its ``engine`` setting
(:data:`vecsim.config.EngineName`), carried to the pod in the assignment. :func:`engine_kind`
maps that name to an :class:`EngineKind`, importing the engine's module only then, so a pod
imports the packages of the engine it runs and no other's (the CPU engine's robosuite and LIBERO,
MuJoCo Warp's warp).

A second engine is one module that defines ``KIND`` (an :class:`EngineKind`) plus its name in
:data:`ENGINES` and in :data:`vecsim.config.EngineName`.

- ``cpu`` (:mod:`vecsim.engine.cpu`): :class:`~vecsim.engine.vector_env.TaskGroupedVectorEnv`,
  worker processes on the pod's cores; LIBERO's bit-exact reference.
- ``mjwarp`` (:mod:`vecsim.engine.mjwarp.engine`): many worlds per task on one GPU (MuJoCo Warp),
  fed scenes exported from the CPU engine (:mod:`vecsim.engine.mjwarp.scene`).
"""

from __future__ import annotations

import dataclasses
import importlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol, get_args, runtime_checkable

import gymnasium
import numpy as np

from vecsim.config import Assignment, EngineName
from vecsim.engine.errors import EnvError, InvalidRequestError

# The longest chunk a pod takes by default (the CPU engine: the chunk axis of a worker's shared
# result rows).
DEFAULT_MAX_CHUNK = 64

# Engine name -> the module whose ``KIND`` builds it; imported on first use only.
ENGINES: dict[str, str] = {
    "cpu": "vecsim.engine.cpu",
    "mjwarp": "vecsim.engine.mjwarp.engine",
}
assert set(ENGINES) == set(get_args(EngineName)), "ENGINES and vecsim.config.EngineName must name the same engines"


@dataclass(frozen=True)
class CallTiming:
    """Seconds of one reset or step call: ``physics_s`` in the scenes' resets and steps,
    ``render_s`` rendering their cameras (summed over the CPU engine's workers); ``renders``,
    how many env renders (all of one env's cameras drawn once) the call made; and
    ``turn_wait_s``, waiting for its turn at a GPU that other pods share (``mjwarp``)."""

    physics_s: float = 0.0
    render_s: float = 0.0
    renders: int = 0
    turn_wait_s: float = 0.0


@dataclass(frozen=True)
class ChunkResult:
    """What one chunk step answers, over the named envs in the given order (n envs, chunk K).

    ``reward`` float64, ``terminated``, ``truncated``, ``success`` bool, all ``[n, K]``: entry
    ``[i, k]`` belongs to env i's action k, zero/false from the action after env i stopped on.
    ``num_steps`` int32 ``[n]``: actions applied (K unless the env terminated or truncated first).
    ``obs``: the observation after each env's last applied action, batched ``[n, ...]``.
    ``frames``: ``{camera: uint8[m, K, H, W, 3]}`` for the m recorded envs, in the order asked,
    the frame after each applied action (zeros after the env stopped); empty when none is recorded.
    ``env_info``: per row, the env's own info after its last applied action (``{}`` where it has
    none beyond vecsim's keys). ``errors``: the envs that raised (:class:`EnvError`), in row order.
    """

    obs: dict[str, Any]
    reward: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    success: np.ndarray
    num_steps: np.ndarray
    frames: dict[str, np.ndarray]
    env_info: list[dict[str, Any]] = dataclasses.field(default_factory=list)
    errors: list[EnvError] = dataclasses.field(default_factory=list)


@runtime_checkable
class PodEngine(Protocol):
    """The envs of one assignment, addressed by env index ``0..num_envs-1``, as a pod serves them.

    Every call checks all its arguments before any env moves (a refused call changes nothing and
    raises :class:`~vecsim.engine.errors.UnknownEnvError` or
    :class:`~vecsim.engine.errors.InvalidRequestError` naming the field); an empty call is a
    no-op; an env that fails is named in the answer's ``errors`` while every other env goes on;
    :class:`~vecsim.engine.errors.SimCrashedError` means the whole engine must be rebuilt. The
    arrays a call returns are the caller's: the engine never writes them again (the pod sends an
    answer's arrays while the next call runs, and keeps them for a repeated request).
    :class:`~vecsim.engine.vector_env.TaskGroupedVectorEnv` documents each call in full.
    """

    num_envs: int
    task_ids: list[str]
    max_chunk: int
    single_observation_space: gymnasium.Space
    single_action_space: gymnasium.Space
    last_timing: CallTiming

    def reset_envs(
        self, env_indices: Any, state_ids: Any = None, *, seeds: Any = None, options: dict[str, Any] | None = None
    ) -> tuple[Any, dict[str, Any]]: ...

    def step_envs(self, env_indices: Any, actions: Any) -> tuple[Any, Any, Any, Any, dict[str, Any]]: ...

    def chunk_step_envs(
        self, env_indices: Any, actions: Any, record_env_indices: Any = (), step_past_end: bool = False
    ) -> ChunkResult: ...

    def reset_and_step_envs(
        self,
        reset_env_indices: Any,
        state_ids: Any,
        env_indices: Any,
        actions: Any,
        *,
        chunked: bool = True,
        record_env_indices: Any = (),
        step_past_end: bool = False,
    ) -> tuple[tuple[Any, dict[str, Any]], ChunkResult]: ...

    def frame(self, env_index: int, camera: str) -> np.ndarray: ...

    def env_attr(
        self, env_indices: Any, op: str, name: Any, payload: Any = None
    ) -> tuple[list[Any], list[EnvError]]: ...

    def close(self) -> None: ...


@dataclass(frozen=True)
class EngineKind:
    """One engine as the pod builds it.

    ``spaces(assignment)``: checks that this engine can run ``assignment`` without building it
    and returns ``(observation_space, action_space)``; raises ``InvalidRequestError`` (or the task
    registry's errors) naming the field at fault. ``build(assignment, timeout_s=,
    build_timeout_s=, max_chunk=)``: the built :class:`PodEngine`, every env in state 0.
    ``steps_on_event_loop(assignment)``: whether calls are cheap enough to run on the pod's event
    loop rather than its worker thread. ``task_info(assignment, task_id)``: the task's instruction
    and its number of fixed initial states, as ``/v1/info`` answers them (raises what ``spaces``
    raises for a task it cannot serve).
    """

    name: str
    spaces: Callable[[Assignment], tuple[gymnasium.Space, gymnasium.Space]]
    build: Callable[..., PodEngine]
    steps_on_event_loop: Callable[[Assignment], bool]
    task_info: Callable[[Assignment, str], tuple[str, int]]


def engine_kind(name: str) -> EngineKind:
    """The engine ``name`` names, its module imported now.

    Raises:
        InvalidRequestError: no engine of that name (the message names the field ``engine`` and
            the engines there are).
        ImportError: the engine's packages are not installed here (e.g. ``mjwarp`` without the
            ``mjwarp`` extra); the message says which.
    """
    module = ENGINES.get(name)
    if module is None:
        raise InvalidRequestError(f"engine: no engine {name!r}; engines: {sorted(ENGINES)}")
    kind = importlib.import_module(module).KIND
    assert isinstance(kind, EngineKind) and kind.name == name
    return kind
