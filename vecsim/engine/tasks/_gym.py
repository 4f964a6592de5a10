"""Any gymnasium env, as task ``gym/<id>``: a registered id, or ``gym/<module>:<id>``, whose module
the pod imports first (gymnasium's own ``"module:EnvId"`` form, for a user's package), or
``gym/<module>:<callable>``, a function of that module that returns the env (as an env factory
given to gymnasium's vector envs), called with the job's kwargs for the task.

Without cameras a gym task is the env itself: ``gymnasium.make(id, **make_kwargs)`` with the
env's own observation and action spaces (any kind :mod:`vecsim.spaces` describes; actions of an
array space, or a Dict or Tuple of them, which travel flattened), its own ``info`` (nothing added) and its
own seeding: ``reset(seed=s, options=o)`` is the env's, and a pod leaves a new env as
``gymnasium.make`` built it (never reset, its generators as its factory left them). With
cameras, a gym task takes vecsim's robot layout: ``proprio`` is the env's observation, flattened,
as float32, and ``images`` holds one ``render`` frame of the configured size (MuJoCo envs only,
upright): the picture gymnasium's ``env.render()`` gives, drawn by vecsim's batch renderer from
gymnasium's camera settings, so no gymnasium viewer (and no GL context of its own) is ever made;
that layout needs Box spaces.

Either way state id ``k`` is ``reset(seed=derive_seed(task_id, k))``: fixed initial states stay
available (``reset(options={"state_id": k})``).
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Mapping
from typing import Any

import gymnasium
import mujoco
import numpy as np

from vecsim.engine import render as render_presets
from vecsim.engine.batch_render import BatchRenderer, CameraView, shared_renderer
from vecsim.config import CameraConfig
from vecsim.spaces import check_action_space, check_travels, wire_action_space
from vecsim.engine.tasks._base import TaskEnv, TaskSetupError, TaskSpec, derive_seed, ensure_gl_backend

GYM_NUM_STATES = 50
GYM_DEFAULT_MAX_EPISODE_STEPS = 1000
RENDER_CAMERA = "render"
# The info keys vecsim itself gives every robot task env (a native gym env's info is its own).
VECSIM_INFO_KEYS = ("success", "task_id", "state_id")


def gym_id(task_id: str) -> str:
    """Return the gymnasium id of a ``gym/<id>`` task id (with its ``module:`` part, if any)."""
    return task_id.split("/", 1)[1]


def import_env_module(env_id: str) -> str:
    """Import the module of a ``module:EnvId`` id (registering its envs); return ``EnvId``.

    Raises:
        TaskSetupError: the module cannot be imported; the message names it and why.
    """
    module, sep, name = env_id.rpartition(":")
    if not sep:
        return env_id
    if not module or not name:
        raise TaskSetupError(f"gym/{env_id}: expected gym/<module>:<env id>")
    try:
        importlib.import_module(module)
    except Exception as exc:  # noqa: BLE001 - whatever the user's module raises, name it
        raise TaskSetupError(
            f"gym/{env_id}: cannot import module {module!r} in this process: {type(exc).__name__}: {exc}"
        ) from None
    return name


def env_factory(env_id: str) -> Callable[..., gymnasium.Env] | None:
    """Return the callable that ``<module>:<name>`` names, where ``name`` is no registered id
    but a callable of the module; None otherwise.

    Raises:
        TaskSetupError: the module cannot be imported.
    """
    name = import_env_module(env_id)
    module, sep, _ = env_id.rpartition(":")
    if not sep or name in gymnasium.registry:
        return None
    made = getattr(sys.modules[module], name, None)
    return made if callable(made) and not isinstance(made, type(sys)) else None


def gym_spec(task_id: str) -> TaskSpec | None:
    """Return the TaskSpec of ``gym/<id>`` (or ``gym/<module>:<id>``), or None when gymnasium has no such id.

    Raises:
        TaskSetupError: the id names a module that cannot be imported.
    """
    name = import_env_module(gym_id(task_id))
    try:
        spec = gymnasium.spec(name)
    except gymnasium.error.Error:
        if env_factory(gym_id(task_id)) is None:
            return None
        scene, limit = gym_id(task_id), None
    else:
        scene, limit = spec.id, spec.max_episode_steps
    return TaskSpec(
        task_id=task_id,
        suite="gym",
        instruction="",
        scene=scene,
        num_states=GYM_NUM_STATES,
        max_episode_steps=limit or GYM_DEFAULT_MAX_EPISODE_STEPS,
    )


def _check_box(task: TaskSpec, what: str, space: gymnasium.Space) -> gymnasium.spaces.Box:
    if not isinstance(space, gymnasium.spaces.Box):
        raise ValueError(f"{task.task_id}: its {what} space is {space}; with cameras vecsim serves Box spaces only")
    return space


def _make(task: TaskSpec, make_kwargs: Mapping[str, Any] | None, **extra: Any) -> tuple[gymnasium.Env, gymnasium.Env]:
    """Make the task's env with the job's kwargs for it (``extra`` wins): ``gymnasium.make`` of
    its id, or its factory called (a ``max_episode_steps`` becoming vecsim's ``TimeLimit``).

    Returns:
        ``(env, served)``: the env to step, and the env the id or factory returned, whose
        attributes ``get_attr``/``call``/``set_attr`` reach (``env`` less vecsim's wrapper).

    Raises:
        ValueError: the kwargs were refused, or a factory returned no gymnasium env (the
            message names the task).
    """
    kwargs = {**dict(make_kwargs or {}), **extra}
    factory = env_factory(gym_id(task.task_id))
    try:
        if factory is None:
            env = gymnasium.make(import_env_module(gym_id(task.task_id)), disable_env_checker=True, **kwargs)
            return env, env
        limit = kwargs.pop("max_episode_steps", None)
        served = factory(**kwargs)
    except TypeError as exc:
        raise ValueError(f"{task.task_id}: making the env refused the kwargs {sorted(kwargs)}: {exc}") from exc
    if not isinstance(served, gymnasium.Env):
        raise ValueError(f"{task.task_id}: the factory returned a {type(served).__name__}, not a gymnasium.Env")
    return (served if limit is None else gymnasium.wrappers.TimeLimit(served, limit)), served


def gym_spaces(
    task: TaskSpec, camera: CameraConfig, make_kwargs: Mapping[str, Any] | None = None
) -> tuple[gymnasium.Space, gymnasium.Space]:
    """Return ``(observation_space, action_space)`` of a gym task under ``camera``.

    Raises:
        ValueError: a space that cannot be served (named), or kwargs gymnasium refused.
    """
    env, _ = _make(task, make_kwargs)
    try:
        return _spaces(task, env, camera)
    finally:
        env.close()


def _spaces(task: TaskSpec, env: gymnasium.Env, camera: CameraConfig) -> tuple[gymnasium.Space, gymnasium.Space]:
    if not camera.names:
        where = task.task_id
        return check_travels(env.observation_space, f"{where}: observation space"), check_action_space(
            env.action_space, f"{where}: action space"
        )
    observation = _check_box(task, "observation", env.observation_space)
    spaces: dict[str, gymnasium.Space] = {
        "images": gymnasium.spaces.Dict(
            {RENDER_CAMERA: gymnasium.spaces.Box(0, 255, (camera.height, camera.width, 3), np.uint8)}
        )
    }
    size = int(np.prod(observation.shape))
    spaces["proprio"] = gymnasium.spaces.Box(-np.inf, np.inf, (size,), np.float32)
    return gymnasium.spaces.Dict(spaces), _check_box(task, "action", env.action_space)


def gymnasium_camera(env: gymnasium.Env) -> CameraView:
    """Return the camera view gymnasium's ``render()`` of ``env`` draws, as gymnasium sets it up.

    gymnasium's offscreen viewer starts from a free camera looking at the median geom position
    from ``model.stat.extent`` away, then applies the env's ``default_camera_config``; a named
    or numbered camera makes it a fixed camera. Call it before the first step, as gymnasium
    makes its viewer on the first ``render()`` of a fresh env.

    Raises:
        ValueError: ``env`` is not a gymnasium MuJoCo env rendering rgb arrays.
    """
    base = env.unwrapped
    renderer = getattr(base, "mujoco_renderer", None)
    if renderer is None or base.render_mode != "rgb_array":
        raise ValueError(
            f"render: {base.spec.id if base.spec else type(base).__name__} is not a MuJoCo env rendering rgb arrays"
        )
    model, data = base.model, base.data
    camera = mujoco.MjvCamera()
    camera.type = mujoco.mjtCamera.mjCAMERA_FREE
    camera.fixedcamid = -1
    camera.lookat[:] = np.median(data.geom_xpos, axis=0)
    camera.distance = model.stat.extent
    for key, value in (renderer.default_cam_config or {}).items():
        if isinstance(value, np.ndarray):
            getattr(camera, key)[:] = value
        else:
            setattr(camera, key, value)
    if renderer.camera_id is not None and renderer.camera_id != -1:
        camera.type = mujoco.mjtCamera.mjCAMERA_FIXED
        camera.fixedcamid = renderer.camera_id
    option = mujoco.MjvOption()
    for flag, value in renderer._vopt.items():
        option.flags[flag] = value
    return CameraView(model, data, camera, option)


class GymTaskEnv(TaskEnv):
    """A gymnasium env behind vecsim's task contract (see the module docstring).

    :attr:`served` is the env the id or factory returned (:attr:`inner` less vecsim's own
    wrapper). Without cameras (:attr:`native`) it is the env itself: ``reset(seed=, options=)`` and ``step``
    are the env's, its ``info`` keeps the env's keys, and truncation is the env's own
    (``max_episode_steps``, None: the id's own limit, if any). ``reset(options={"state_id": k})``
    puts it in fixed initial state ``k`` (the env's other options go on to its reset).
    With cameras, :attr:`camera_views` holds gymnasium's camera and :attr:`renderer` draws it;
    with :attr:`defer_images` set, observations leave ``images`` out for a batch to fill.
    """

    def __init__(
        self,
        task: TaskSpec,
        camera: CameraConfig,
        render: str,
        max_episode_steps: int | None,
        make_kwargs: Mapping[str, Any] | None = None,
    ) -> None:
        super().__init__(task, max_episode_steps or task.max_episode_steps)
        render_presets.settings(render)
        self.native = not camera.names
        extra: dict[str, Any] = {}
        if max_episode_steps is not None:
            extra["max_episode_steps"] = max_episode_steps
        if camera.names:
            ensure_gl_backend()
            extra.update(render_mode="rgb_array", width=camera.width, height=camera.height)
        try:
            self.inner, self.served = _make(task, make_kwargs, **extra)
        except ValueError as exc:
            if not camera.names:
                raise
            raise ValueError(
                f"{task.task_id}: cannot render camera images of it (only gymnasium MuJoCo envs "
                f"take a width and height): {exc}"
            ) from exc
        self.defer_images = False
        self.image_names: tuple[str, ...] = (RENDER_CAMERA,) if camera.names else ()
        self.camera_views: list[CameraView] = []
        self.renderer: BatchRenderer | None = None
        try:
            self.observation_space, self.action_space = _spaces(task, self.inner, camera)
            # A Dict or Tuple action space travels flattened; the env takes its actions unflattened.
            self._composite_actions = (
                None if self.action_space is wire_action_space(self.action_space) else self.action_space
            )
            self.action_space = wire_action_space(self.action_space)
            if camera.names:
                self.camera_views = [gymnasium_camera(self.inner)]
                self.renderer = shared_renderer(camera.height, camera.width, render)
                self.renderer.attach(self.camera_views[0].model, 1)
        except BaseException:
            self.inner.close()
            raise

    def render_images(self) -> dict[str, np.ndarray]:
        """Render the env as it is now; return ``{"render": HxWx3 uint8}`` (empty without cameras)."""
        if self.renderer is None:
            return {}
        return dict(zip(self.image_names, self.renderer.render(self.camera_views)))

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        """Reset the env: to fixed initial state ``options["state_id"]``, or (native) as the env's
        own ``reset(seed=seed, options=options)``.

        Returns:
            ``(observation, info)``: native, the env's own info, nothing added; else ``success``,
            ``task_id`` and ``state_id``.

        Raises:
            ValueError: a ``state_id`` that is not an int in range.
            Whatever the env's own reset raises.
        """
        if not self.native:
            return super().reset(seed=seed, options=options)
        rest = dict(options or {})
        state_id = rest.pop("state_id", None)
        if state_id is not None:
            seed = derive_seed(self.task.task_id, self._state_id({"state_id": state_id}))
        raw, info = self.inner.reset(seed=seed, options=rest or None)
        self._elapsed = 0
        # This env's generator is its gymnasium env's, as gymnasium's check_env expects of it.
        base = self.inner.unwrapped
        self._np_random, self._np_random_seed = base._np_random, base._np_random_seed
        return raw, info

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        """Advance one step: native envs exactly as the env's own ``step``.

        Returns:
            ``(observation, reward, terminated, truncated, info)``: native, the env's own info,
            nothing added; else ``success`` and ``task_id``.
        """
        if not self.native:
            return super().step(action)
        if self._composite_actions is not None:
            action = gymnasium.spaces.unflatten(self._composite_actions, action)
        raw, reward, terminated, truncated, info = self.inner.step(action)
        self._elapsed += 1
        return raw, float(reward), bool(terminated), bool(truncated), info

    def _reset_to(self, state_id: int) -> tuple[dict[str, Any], bool]:
        raw, info = self.inner.reset(seed=derive_seed(self.task.task_id, state_id))
        return self._observation(raw), bool(info.get("success", False))

    def _step(self, action: Any) -> tuple[dict[str, Any], float, bool, bool, bool]:
        raw, reward, terminated, truncated, info = self.inner.step(action)
        return self._observation(raw), float(reward), terminated, truncated, bool(info.get("success", False))

    def _observation(self, raw: Any) -> dict[str, Any]:
        observation: dict[str, Any] = {}
        if self.renderer is not None and not self.defer_images:
            observation["images"] = self.render_images()
        observation["proprio"] = np.asarray(raw, dtype=np.float32).reshape(-1)
        return observation

    def close(self) -> None:
        """Close the gymnasium env and release its share of the renderer. Returns None."""
        if self.renderer is not None:
            self.renderer.detach(self.camera_views[0].model, 1)
            self.renderer = None
        self.inner.close()
