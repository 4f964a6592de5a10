"""The task registry: named, reproducible scenes with instructions, grouped into suites.

Task ids are ``<suite>/<name>``:

- LIBERO: ``libero_10/0`` … (suites ``libero_10``, ``libero_spatial``, ``libero_object``,
  ``libero_goal``, ``libero_90``; LIBERO's order, instructions and 50 init states per task);
- robosuite: ``robosuite/Lift``, ``robosuite/Stack``, ``robosuite/PickPlace[Milk|Bread|Cereal|Can]``,
  ``robosuite/NutAssembly[Square|Round]``, ``robosuite/Door`` (Panda, OSC_POSE; 50 fixed initial
  states generated from seeds and cached);
- ``tiny``: ``tiny/lift``, ``tiny/stack``, ``tiny/door``, robosuite scenes with 50-step episodes;
- any gymnasium id as ``gym/<id>`` (``gym:<id>`` is accepted and normalised), and a user's env as
  ``gym/<module>:<id>`` (the module is imported first, gymnasium's own ``"module:EnvId"`` form);
  served without cameras, a gym task is the env itself (its spaces, info and seeding).

The suites and their task ids are the task catalogue's (:mod:`vecsim.suites`, which needs no
simulator); this registry adds what building them takes. All tasks of a suite share one
observation space and one action space (docs/api.md); so do all robot tasks (LIBERO, robosuite,
tiny) under one camera config. Importing this module imports
neither robosuite nor LIBERO: they load when an env is made (or, for LIBERO, listed).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import gymnasium

from vecsim.config import CameraConfig, LiberoProtocol, RenderPreset
from vecsim.suites import ROBOSUITE_SUITES, normalize_task_id, suite_names
from vecsim.engine.tasks._base import (
    TaskEnv,
    TaskSetupError,
    TaskSpec,
    UnknownTaskError,
    cache_dir,
    derive_seed,
    stdout_to_log,
)
from vecsim.engine.tasks._fast_step import ArmStep, ExactStep, library_step, osc_kernel
from vecsim.engine.tasks._gym import GymTaskEnv, gym_spaces, gym_spec
from vecsim.engine.tasks._libero import (
    LIBERO_SUITES,
    ensure_config,
    episode_fixtures,
    fixtures_path,
    init_states,
    libero_benchmark,
    libero_observation_space,
    libero_specs,
    load_fixtures,
    make_libero_env,
)
from vecsim.engine.tasks._robot import (
    PROPRIO_KEYS,
    RobotTaskEnv,
    make_robosuite_env,
    robosuite_specs,
    robot_action_space,
    robot_observation_space,
    seeded_global_rngs,
    states_path,
)

__all__ = [
    "PROPRIO_KEYS",
    "ArmStep",
    "ExactStep",
    "GymTaskEnv",
    "RobotTaskEnv",
    "TaskEnv",
    "TaskSetupError",
    "TaskSpec",
    "UnknownTaskError",
    "cache_dir",
    "default_render",
    "derive_seed",
    "ensure_config",
    "episode_fixtures",
    "episode_limit",
    "fixtures_path",
    "get_task",
    "init_states",
    "libero_benchmark",
    "library_step",
    "list_suites",
    "load_fixtures",
    "make_env",
    "normalize_task_id",
    "osc_kernel",
    "robot_action_space",
    "robot_observation_space",
    "seeded_global_rngs",
    "states_path",
    "stdout_to_log",
    "suite_tasks",
    "task_spaces",
]

# Episode length of a pod's non-LIBERO tasks when the assignment sets none.
POD_MAX_EPISODE_STEPS = 300


def list_suites() -> list[str]:
    """Return the names of the suites, as the task catalogue (:mod:`vecsim.suites`) lists them
    (gymnasium ids are tasks of no suite listing)."""
    return suite_names()


def _unknown(what: str) -> UnknownTaskError:
    return UnknownTaskError(f"{what}; suites: {', '.join(list_suites())}, or gym/<gymnasium id>")


def suite_tasks(suite: str) -> list[TaskSpec]:
    """Return the tasks of ``suite`` in the suite's order.

    Raises:
        UnknownTaskError: no suite of that name.
        TaskSetupError: a LIBERO suite, and LIBERO is not installed or lacks its assets.
    """
    if suite in LIBERO_SUITES:
        return libero_specs(suite)
    if suite in ROBOSUITE_SUITES:
        return robosuite_specs()[suite]
    raise _unknown(f"unknown suite {suite!r}")


def get_task(task_id: str) -> TaskSpec:
    """Return the :class:`TaskSpec` of ``task_id`` (``gym:<id>`` accepted).

    Raises:
        UnknownTaskError: no provider knows ``task_id``; the message names it and lists the suites.
        TaskSetupError: a LIBERO task, and LIBERO is not installed or lacks its assets; a
            ``gym/<module>:<id>`` whose module cannot be imported (named).
    """
    normalized = normalize_task_id(task_id)
    suite, _, name = normalized.partition("/")
    if suite == "gym" and name:
        spec = gym_spec(normalized)
        if spec is not None:
            return spec
    elif suite in LIBERO_SUITES or suite in ROBOSUITE_SUITES:
        for spec in suite_tasks(suite):
            if spec.task_id == normalized:
                return spec
    raise _unknown(f"unknown task {task_id!r}")


def task_spaces(
    task_id: str, camera: CameraConfig, make_kwargs: Mapping[str, Any] | None = None
) -> tuple[gymnasium.Space, gymnasium.Space]:
    """Return ``(observation_space, action_space)`` of ``task_id``'s envs under ``camera``.

    Robot tasks need no env for this; a gym task's env is made (with ``make_kwargs``, without
    rendering) and closed.

    Raises:
        UnknownTaskError: unknown task id.
        TaskSetupError: a LIBERO task, and LIBERO is not installed or lacks its assets; a gym
            task whose module cannot be imported.
        ValueError: a gym task with a space vecsim cannot serve (named), or kwargs gymnasium refused.
    """
    task = get_task(task_id)
    if task.suite == "gym":
        return gym_spaces(task, camera, make_kwargs)
    if task.suite in LIBERO_SUITES:
        return libero_observation_space(camera), robot_action_space()
    return robot_observation_space(camera), robot_action_space()


def default_render(task_id: str) -> RenderPreset:
    """Return the render preset ``task_id``'s envs get when none is asked for.

    LIBERO tasks draw with ``full`` (robosuite's defaults: LIBERO's own pixels, docs/libero.md);
    every other task with ``lean``.
    """
    return "full" if normalize_task_id(task_id).partition("/")[0] in LIBERO_SUITES else "lean"


def episode_limit(task_id: str, max_episode_steps: int | None) -> int | None:
    """Return the episode length a pod gives ``task_id``'s envs under an assignment's ``max_episode_steps``.

    Set, it holds for every task. Unset, a LIBERO task gets its suite's limit (the step budget
    of LIBERO's published evaluations), a gym task its id's own limit (None where the id has
    none: only the env's own truncation) and any other task ``POD_MAX_EPISODE_STEPS``.

    Raises:
        UnknownTaskError: unknown task id.
        TaskSetupError: a LIBERO task, and LIBERO is not installed or lacks its assets.
    """
    if max_episode_steps is not None:
        return max_episode_steps
    task = get_task(task_id)
    if task.suite == "gym":
        return None
    return task.max_episode_steps if task.suite in LIBERO_SUITES else POD_MAX_EPISODE_STEPS


def make_env(
    task_id: str,
    camera: CameraConfig | None = None,
    render: RenderPreset | None = None,
    max_episode_steps: int | None = None,
    libero: LiberoProtocol | None = None,
    make_kwargs: Mapping[str, Any] | None = None,
) -> TaskEnv:
    """Build the env of ``task_id``: a :class:`TaskEnv` (a ``gymnasium.Env``).

    ``camera`` defaults to ``CameraConfig()``; ``render`` to :func:`default_render`;
    ``max_episode_steps`` to the task's own; ``libero`` (the conventions of LIBERO tasks, ignored
    by the others) to ``LiberoProtocol()``, LIBERO's published evaluation; ``make_kwargs`` (gym
    tasks only) go to ``gymnasium.make``.
    ``reset(options={"state_id": k})`` puts the env in fixed initial state ``k``.

    Raises:
        UnknownTaskError: unknown task id.
        TaskSetupError: LIBERO is not installed or lacks its assets.
        ValueError: a camera the scene lacks, an unknown render preset, or unsupported spaces.
    """
    task = get_task(task_id)
    camera = CameraConfig() if camera is None else camera
    render = default_render(task.task_id) if render is None else render
    if task.suite == "gym":
        return GymTaskEnv(task, camera, render, max_episode_steps, make_kwargs)
    steps = task.max_episode_steps if max_episode_steps is None else max_episode_steps
    if task.suite in LIBERO_SUITES:
        return make_libero_env(task, camera, render, steps, LiberoProtocol() if libero is None else libero)
    return make_robosuite_env(task, camera, render, steps)
