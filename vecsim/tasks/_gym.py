"""Any registered gymnasium env with Box observations and Box actions, as task ``gym/<id>``.

State id ``k`` is ``reset(seed=derive_seed(task_id, k))``. ``proprio`` is the env's own
observation, flattened, as float32; with cameras asked for, ``images`` holds one ``render``
frame of the configured size (MuJoCo envs only, upright): the picture gymnasium's
``env.render()`` gives, drawn by vecsim's batch renderer from gymnasium's camera settings, so no
gymnasium viewer (and no GL context of its own) is ever made.
"""

from __future__ import annotations

from typing import Any

import gymnasium
import mujoco
import numpy as np

from vecsim import render as render_presets
from vecsim.batch_render import BatchRenderer, CameraView, shared_renderer
from vecsim.config import CameraConfig
from vecsim.tasks._base import TaskEnv, TaskSpec, derive_seed, ensure_gl_backend

GYM_NUM_STATES = 50
GYM_DEFAULT_MAX_EPISODE_STEPS = 1000
RENDER_CAMERA = "render"


def gym_id(task_id: str) -> str:
    """Return the gymnasium id of a ``gym/<id>`` task id."""
    return task_id.split("/", 1)[1]


def gym_spec(task_id: str) -> TaskSpec | None:
    """Return the TaskSpec of ``gym/<id>``, or None when gymnasium has no such id."""
    try:
        spec = gymnasium.spec(gym_id(task_id))
    except gymnasium.error.Error:
        return None
    return TaskSpec(
        task_id=task_id,
        suite="gym",
        instruction="",
        scene=spec.id,
        num_states=GYM_NUM_STATES,
        max_episode_steps=spec.max_episode_steps or GYM_DEFAULT_MAX_EPISODE_STEPS,
    )


def _check_box(task: TaskSpec, what: str, space: gymnasium.Space) -> gymnasium.spaces.Box:
    if not isinstance(space, gymnasium.spaces.Box):
        raise ValueError(f"{task.task_id}: its {what} space is {space}; vecsim serves Box spaces only")
    return space


def gym_spaces(task: TaskSpec, camera: CameraConfig) -> tuple[gymnasium.spaces.Dict, gymnasium.spaces.Box]:
    """Return ``(observation_space, action_space)`` of a gym task under ``camera``.

    Raises:
        ValueError: the env's spaces are not Box spaces.
    """
    env = gymnasium.make(gym_id(task.task_id), disable_env_checker=True)
    try:
        return _observation_space(task, env, camera), _check_box(task, "action", env.action_space)
    finally:
        env.close()


def _observation_space(task: TaskSpec, env: gymnasium.Env, camera: CameraConfig) -> gymnasium.spaces.Dict:
    observation = _check_box(task, "observation", env.observation_space)
    spaces: dict[str, gymnasium.Space] = {}
    if camera.names:
        spaces["images"] = gymnasium.spaces.Dict(
            {RENDER_CAMERA: gymnasium.spaces.Box(0, 255, (camera.height, camera.width, 3), np.uint8)}
        )
    size = int(np.prod(observation.shape))
    spaces["proprio"] = gymnasium.spaces.Box(-np.inf, np.inf, (size,), np.float32)
    return gymnasium.spaces.Dict(spaces)


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
            f"render: {base.spec.id if base.spec else type(base).__name__} is not a MuJoCo env "
            "rendering rgb arrays"
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
    """A gymnasium env behind vecsim's observation and reset contract.

    With cameras, :attr:`camera_views` holds gymnasium's camera and :attr:`renderer` draws it;
    with :attr:`defer_images` set, observations leave ``images`` out for a batch to fill.
    """

    def __init__(self, task: TaskSpec, camera: CameraConfig, render: str, max_episode_steps: int) -> None:
        super().__init__(task, max_episode_steps)
        render_presets.settings(render)
        kwargs: dict[str, Any] = {}
        if camera.names:
            ensure_gl_backend()
            kwargs = {"render_mode": "rgb_array", "width": camera.width, "height": camera.height}
        try:
            self.inner = gymnasium.make(
                gym_id(task.task_id), max_episode_steps=max_episode_steps, disable_env_checker=True, **kwargs
            )
        except TypeError as exc:
            raise ValueError(
                f"{task.task_id}: cannot render camera images of it (only gymnasium MuJoCo envs "
                f"take a width and height): {exc}"
            ) from exc
        self.defer_images = False
        self.image_names: tuple[str, ...] = (RENDER_CAMERA,) if camera.names else ()
        self.camera_views: list[CameraView] = []
        self.renderer: BatchRenderer | None = None
        try:
            self.observation_space = _observation_space(task, self.inner, camera)
            self.action_space = _check_box(task, "action", self.inner.action_space)
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
