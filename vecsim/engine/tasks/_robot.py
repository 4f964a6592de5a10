"""Robot tasks on robosuite (robosuite's own single-arm tasks, the tiny suite, and LIBERO's scenes).

Every robot task has the same spaces for a given camera config: ``images`` (one upright uint8
HxWx3 per camera; absent without cameras) and ``proprio`` (the 23 floats of ``PROPRIO_KEYS``),
and a 7-dim OSC_POSE action in [-1, 1] on a Panda.

Resetting to a fixed initial state is exact: whatever the env did before, the same (task, state
id) gives bit-identical observations. robosuite keeps state outside ``sim.get_state()`` (MuJoCo's
solver warmstart, the arm controller's goals and nullspace posture, the gripper's integrated
command, step counters, object placements LIBERO writes into the model), so a reset reruns
robosuite's own reset under a seed derived from (task, state id), clears MuJoCo's history, sets
the flattened state, and only then makes the controllers, which read the state they start from.

Cameras are drawn by vecsim's batch renderer (:mod:`vecsim.engine.batch_render`), not by robosuite:
robosuite's camera observables and its own render context are switched off, and each env's
images are rendered once per reset or step, of the sim as the action's last physics substep
leaves it (where robosuite's camera observables render, with no extra ``mj_forward``, so the
pictures are robosuite's own). Standing alone, an env renders its own cameras as one batch; a pod's worker sets
``defer_images`` and renders every env it just stepped in one batch instead.
"""

from __future__ import annotations

import contextlib
import fcntl
import random
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import gymnasium
import mujoco
import numpy as np

from vecsim.engine import render as render_presets
from vecsim.engine.batch_render import BatchRenderer, CameraView, fixed_camera, shared_renderer
from vecsim.config import CameraConfig, RenderPreset
from vecsim.suites import ROBOSUITE_SUITES
from vecsim.engine.tasks._base import (
    TaskEnv,
    TaskSetupError,
    TaskSpec,
    cache_dir,
    derive_seed,
    ensure_gl_backend,
    log,
    scene_seed,
)
from vecsim.engine.tasks._fast_step import DEFAULT_STEP_PATH, make_step
from vecsim.files import write_whole

PROPRIO_KEYS: tuple[str, ...] = (
    "robot0_joint_pos_cos",
    "robot0_joint_pos_sin",
    "robot0_eef_pos",
    "robot0_eef_quat",
    "robot0_gripper_qpos",
)
PROPRIO_DIM = 7 + 7 + 3 + 4 + 2
ACTION_DIM = 7

# Fixed initial states generated for robosuite tasks live in <cache>/init_states/<version>/;
# bump the version whenever the way they are generated changes.
STATES_VERSION = "v1"
GENERATED_STATES = 50
_RESET_ATTEMPTS = 10


def robot_observation_space(camera: CameraConfig) -> gymnasium.spaces.Dict:
    """Return the observation space every robot task has under ``camera``."""
    spaces: dict[str, gymnasium.Space] = {}
    if camera.names:
        spaces["images"] = gymnasium.spaces.Dict(
            {name: gymnasium.spaces.Box(0, 255, (camera.height, camera.width, 3), np.uint8) for name in camera.names}
        )
    spaces["proprio"] = gymnasium.spaces.Box(-np.inf, np.inf, (PROPRIO_DIM,), np.float32)
    return gymnasium.spaces.Dict(spaces)


def robot_action_space() -> gymnasium.spaces.Box:
    """Return the action space of every robot task: OSC_POSE delta (6) and gripper (1) in [-1, 1]."""
    return gymnasium.spaces.Box(-1.0, 1.0, (ACTION_DIM,), np.float32)


@contextlib.contextmanager
def seeded_global_rngs(seed: int) -> Iterator[None]:
    """Seed Python's and numpy's global generators for the block, then restore them.

    robosuite and LIBERO draw model parts, placements and joint noise from those generators.
    """
    np_state, py_state = np.random.get_state(), random.getstate()
    np.random.seed(seed)
    random.seed(seed)
    try:
        yield
    finally:
        np.random.set_state(np_state)
        random.setstate(py_state)


def robosuite_reset_without_observing(inner: Any, without_acceleration: bool = False) -> None:
    """Run robosuite 1.4's ``reset()`` for ``hard_reset=False``, minus computing observations. Returns None.

    With ``without_acceleration``, its forwards run without their acceleration stage
    (:func:`forwards_without_acceleration`): for a caller that sets the state and runs a full
    ``mj_forward`` afterwards, reading nothing in between that the acceleration stage computes.
    """
    with forwards_without_acceleration(inner.sim) if without_acceleration else contextlib.nullcontext():
        inner.sim.reset()
        inner._reset_internal()
        inner.sim.forward()
    inner._obs_cache = {}
    inner.visualize(vis_settings={vis: False for vis in inner._visualizations})


@contextlib.contextmanager
def forwards_without_acceleration(sim: Any) -> Iterator[None]:
    """Make robosuite's ``sim.forward()`` run MuJoCo's position and velocity stages only, for the block.

    Each such forward computes ``mj_forward``'s position and velocity stages and their sensors
    (kinematics, contacts, constraint rows, mass matrix, velocities, bias forces: what robosuite's
    reset reads, for the controller it builds and the objects it places) from the same inputs,
    so those outputs are ``mj_forward``'s bit for bit. It skips the acceleration stage (actuation,
    the constraint solver, accelerations and their sensors), which reads and writes nothing the
    next ``mj_forward`` does not compute again from scratch: MuJoCo saves the solver's warmstart
    in the integrator, not in ``mj_forward``. On the scene ``sim.reset()`` leaves (every object at
    its default pose, inside one another) that stage costs ~25 ms a forward (libero_10/0).
    Only for envs the exact step path covers (no control or sensor callback, plugins or energy,
    whose calls or outputs the acceleration stage would own).
    """
    model, data = sim.model._model, sim.data._data

    def forward() -> None:
        mujoco.mj_fwdPosition(model, data)
        mujoco.mj_sensorPos(model, data)
        mujoco.mj_fwdVelocity(model, data)
        mujoco.mj_sensorVel(model, data)

    sim.forward = forward
    try:
        yield
    finally:
        del sim.forward


def _seeded_reset(task_id: str, state_id: int, inner: Any) -> None:
    from robosuite.utils.errors import RandomizationError

    for attempt in range(_RESET_ATTEMPTS):
        with seeded_global_rngs(derive_seed(task_id, state_id, attempt)):
            try:
                robosuite_reset_without_observing(inner)
                return
            except RandomizationError:
                continue
    raise RuntimeError(f"{task_id}: robosuite could not place the objects for state {state_id}")


def state_width(inner: Any) -> int:
    """Return the length of a flattened MuJoCo state (time, qpos, qvel) of a robosuite env."""
    model = inner.sim.model
    return 1 + model.nq + model.nv


class RobotTaskEnv(TaskEnv):
    """A robosuite (or LIBERO) env behind vecsim's observation, action and reset contract.

    ``states`` holds one flattened MuJoCo state per state id. ``terminated`` is success, as in
    LIBERO; the reward is the env's own (sparse) reward. ``render`` is the render preset; None
    takes the one :func:`vecsim.engine.render.apply_to_robosuite` gave ``inner.sim`` (else ``lean``).

    Camera images come from :attr:`renderer`, this process's batch renderer for the camera size
    and preset; :attr:`camera_views` holds one view per camera name. With :attr:`defer_images`
    set, observations leave ``images`` out and whoever set it renders them (in a batch).

    Raises:
        TaskSetupError: ``states`` do not fit the scene.
        ValueError: a camera the scene does not have, or an unknown render preset.
    """

    def __init__(
        self,
        task: TaskSpec,
        inner: Any,
        states: np.ndarray,
        camera: CameraConfig,
        max_episode_steps: int,
        owner: Any = None,
        render: RenderPreset | None = None,
    ) -> None:
        super().__init__(task, max_episode_steps)
        if states.ndim != 2 or states.shape[0] < task.num_states or states.shape[1] != state_width(inner):
            raise TaskSetupError(
                f"{task.task_id}: expected {task.num_states} initial states of {state_width(inner)} "
                f"floats, got an array of shape {states.shape}"
            )
        preset = render or "lean"
        render_presets.settings(preset)
        self.inner = inner
        self.states = states
        self.camera = camera
        self.observation_space = robot_observation_space(camera)
        self.action_space = robot_action_space()
        # LIBERO's wrapper owns the robosuite env; closing it closes both.
        self._owner = owner
        self.defer_images = False
        self.image_names: tuple[str, ...] = tuple(camera.names)
        _release_robosuite_cameras(inner)
        self.camera_views = _camera_views(task, inner, camera.names)
        self.renderer: BatchRenderer | None = None
        if camera.names:
            self.renderer = shared_renderer(camera.height, camera.width, preset)
            self.renderer.attach(inner.sim.model._model, len(camera.names))
        self._step_fn, self.step_path = make_step(inner, DEFAULT_STEP_PATH)

    def set_step_path(self, path: str) -> None:
        """Step with ``path`` (:mod:`vecsim.engine.tasks._fast_step`). Returns None.

        ``exact`` (the default) and ``library`` (the env's own ``step``) give bit-identical
        trajectories. :attr:`step_path` names the path taken (``exact`` falls back to
        ``library`` where it does not cover the env). A LIBERO task's reset takes the path too
        (:class:`vecsim.engine.tasks._libero.LiberoTaskEnv`).

        Raises:
            ValueError: an unknown path.
        """
        self._step_fn, self.step_path = make_step(self.inner, path)

    def render_images(self) -> dict[str, np.ndarray]:
        """Render this env's cameras as the scene is now; return ``{camera name: HxWx3 uint8}``."""
        if self.renderer is None:
            return {}
        frames = self.renderer.render(self.camera_views)
        return dict(zip(self.image_names, frames))

    def _reset_to(self, state_id: int) -> tuple[dict[str, Any], bool]:
        inner = self.inner
        _seeded_reset(self.task.task_id, state_id, inner)
        data = inner.sim.data._data
        data.qacc_warmstart[:] = 0.0
        data.ctrl[:] = 0.0
        data.qfrc_applied[:] = 0.0
        data.xfrc_applied[:] = 0.0
        data.act[:] = 0.0
        inner.sim.set_state_from_flattened(self.states[state_id])
        inner.sim.forward()
        if hasattr(inner, "tracking_object_states_change"):
            # LIBERO: object states that follow the sim (a stove turned on by its knob, ...).
            inner._post_process()
        for robot in inner.robots:
            robot._load_controller()
            robot.controller.update_base_pose(robot.base_pos, robot.base_ori)
            robot.gripper.current_action = np.zeros(robot.gripper.dof)
        inner.timestep = 0
        inner.cur_time = 0
        inner.done = False
        inner._obs_cache = {}
        for observable in inner._observables.values():
            observable.reset()
        observation = self._observation(inner._get_observations(force_update=True))
        return observation, bool(inner._check_success())

    def _step(self, action: Any) -> tuple[dict[str, Any], float, bool, bool, bool]:
        raw, reward, success = self._step_fn(np.asarray(action, dtype=np.float64))
        return self._observation(raw), reward, success, False, success

    def _observation(self, raw: dict[str, np.ndarray]) -> dict[str, Any]:
        observation: dict[str, Any] = {}
        if self.camera.names and not self.defer_images:
            observation["images"] = self.render_images()
        observation["proprio"] = np.concatenate([raw[key] for key in PROPRIO_KEYS]).astype(np.float32)
        return observation

    def close(self) -> None:
        """Free the sim and release its share of the renderer. Returns None."""
        if self.renderer is not None and self.inner is not None:
            self.renderer.detach(self.inner.sim.model._model, len(self.image_names))
            self.renderer = None
        if self._owner is not None:
            self._owner.close()
        elif self.inner is not None and self.inner.sim is not None:
            self.inner.close()
        self.inner = None
        self._owner = None


def _release_robosuite_cameras(inner: Any) -> None:
    """Switch off robosuite's own camera path: its image observables and its render context."""
    for name, observable in inner._observables.items():
        if name.endswith("_image") and observable.modality == "image":
            inner.modify_observable(name, "enabled", False)
    context = inner.sim._render_context_offscreen
    if context is not None:
        # Freed with its own GL context current: freeing GL objects in another context would
        # delete that context's objects of the same names.
        context.gl_ctx.make_current()
        context.con.free()
        context.gl_ctx.free()
        inner.sim._render_context_offscreen = None
    # robosuite's reset makes a new render context whenever it has none and this is set.
    inner.has_offscreen_renderer = False


def _camera_views(task: TaskSpec, inner: Any, names: tuple[str, ...]) -> list[CameraView]:
    model, data = inner.sim.model._model, inner.sim.data._data
    views = []
    for name in names:
        try:
            camera = fixed_camera(model, name)
        except ValueError as exc:
            raise ValueError(f"{task.task_id}: cannot build it with cameras {list(names)}: {exc}") from None
        # robosuite's renderer shows visual meshes and hides collision meshes (geom groups 1, 0).
        option = mujoco.MjvOption()
        option.geomgroup[0] = int(bool(inner.render_collision_mesh))
        option.geomgroup[1] = int(bool(inner.render_visual_mesh))
        views.append(CameraView(model, data, camera, option))
    return views


# robosuite task name -> (robosuite env, scene, instruction)
ROBOSUITE_TASKS: dict[str, tuple[str, str, str]] = {
    "Lift": ("Lift", "Lift", "lift the red cube"),
    "Stack": ("Stack", "Stack", "stack the red cube on top of the green cube"),
    "PickPlace": ("PickPlace", "PickPlace", "put each object into its bin"),
    "PickPlaceMilk": ("PickPlaceMilk", "PickPlace", "put the milk carton into its bin"),
    "PickPlaceBread": ("PickPlaceBread", "PickPlace", "put the bread into its bin"),
    "PickPlaceCereal": ("PickPlaceCereal", "PickPlace", "put the cereal box into its bin"),
    "PickPlaceCan": ("PickPlaceCan", "PickPlace", "put the can into its bin"),
    "NutAssembly": (
        "NutAssembly",
        "NutAssembly",
        "fit the square nut onto the square peg and the round nut onto the round peg",
    ),
    "NutAssemblySquare": ("NutAssemblySquare", "NutAssembly", "fit the square nut onto the square peg"),
    "NutAssemblyRound": ("NutAssemblyRound", "NutAssembly", "fit the round nut onto the round peg"),
    "Door": ("Door", "Door", "open the door"),
}
ROBOSUITE_MAX_EPISODE_STEPS = 500

# The tiny suite: cheap robosuite scenes with short episodes, for tests and the demo.
TINY_TASKS: dict[str, str] = {"lift": "Lift", "stack": "Stack", "door": "Door"}
TINY_MAX_EPISODE_STEPS = 50


def robosuite_specs() -> dict[str, list[TaskSpec]]:
    """Return the ``robosuite`` and ``tiny`` suites' tasks, named and ordered by the task catalogue."""
    robosuite_suite = [
        TaskSpec(
            task_id=f"robosuite/{name}",
            suite="robosuite",
            instruction=ROBOSUITE_TASKS[name][2],
            scene=ROBOSUITE_TASKS[name][1],
            num_states=GENERATED_STATES,
            max_episode_steps=ROBOSUITE_MAX_EPISODE_STEPS,
        )
        for name in ROBOSUITE_SUITES["robosuite"]
    ]
    tiny_suite = [
        TaskSpec(
            task_id=f"tiny/{name}",
            suite="tiny",
            instruction=ROBOSUITE_TASKS[TINY_TASKS[name]][2],
            scene=ROBOSUITE_TASKS[TINY_TASKS[name]][1],
            num_states=GENERATED_STATES,
            max_episode_steps=TINY_MAX_EPISODE_STEPS,
        )
        for name in ROBOSUITE_SUITES["tiny"]
    ]
    return {"robosuite": robosuite_suite, "tiny": tiny_suite}


def robosuite_env_name(task: TaskSpec) -> str:
    """Return the robosuite environment class name behind a ``robosuite/*`` or ``tiny/*`` task."""
    name = task.task_id.split("/", 1)[1]
    return TINY_TASKS[name] if task.suite == "tiny" else ROBOSUITE_TASKS[name][0]


def make_robosuite_env(task: TaskSpec, camera: CameraConfig, render: str, max_episode_steps: int) -> RobotTaskEnv:
    """Build a robosuite task env (Panda, OSC_POSE, no hard reset, never done by itself).

    Raises:
        ValueError: a camera the scene does not have, or an unknown render preset.
    """
    render_presets.settings(render)
    ensure_gl_backend()
    import robosuite

    # vecsim renders the cameras itself (RobotTaskEnv), so robosuite makes no render context.
    with seeded_global_rngs(scene_seed(task.task_id)):
        inner = robosuite.make(
            robosuite_env_name(task),
            robots="Panda",
            controller_configs=robosuite.load_controller_config(default_controller="OSC_POSE"),
            has_renderer=False,
            has_offscreen_renderer=False,
            use_camera_obs=False,
            reward_shaping=False,
            hard_reset=False,
            ignore_done=True,
            horizon=max_episode_steps,
        )
    try:
        states = generated_states(task, inner)
        return RobotTaskEnv(task, inner, states, camera, max_episode_steps, render=render)
    except BaseException:
        inner.close()
        raise


def states_path(task: TaskSpec) -> Path:
    """Return where the generated initial states of ``task`` are cached."""
    return cache_dir() / "init_states" / STATES_VERSION / f"{task.task_id}.npy"


def _load_states(path: Path, shape: tuple[int, int]) -> np.ndarray | None:
    try:
        states = np.load(path, allow_pickle=False)
    except (OSError, ValueError):
        return None
    if states.shape != shape or states.dtype != np.float64:
        log.warning("ignoring cached initial states %s: shape %s, expected %s", path, states.shape, shape)
        return None
    return states


@contextlib.contextmanager
def _file_lock(path: Path) -> Iterator[None]:
    with open(path, "a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def generated_states(task: TaskSpec, inner: Any) -> np.ndarray:
    """Return ``task``'s fixed initial states, from the cache or generated (and cached) now.

    State id ``k`` is what robosuite's reset gives under the seed ``derive_seed(task_id, k)``,
    flattened (time, qpos, qvel). The cache file is written atomically; processes that need it
    at the same time wait for the one that generates it.
    """
    path = states_path(task)
    shape = (task.num_states, state_width(inner))
    states = _load_states(path, shape)
    if states is not None:
        return states
    path.parent.mkdir(parents=True, exist_ok=True)
    with _file_lock(path.with_name(path.name + ".lock")):
        states = _load_states(path, shape)
        if states is not None:
            return states
        log.info("generating %d initial states for %s into %s", task.num_states, task.task_id, path)
        rows = []
        for state_id in range(task.num_states):
            _seeded_reset(task.task_id, state_id, inner)
            rows.append(inner.sim.get_state().flatten())
        states = np.stack(rows).astype(np.float64)

        def save(partial: Path) -> None:
            with open(partial, "wb") as handle:  # a handle: np.save would add ".npy" to a name
                np.save(handle, states, allow_pickle=False)

        write_whole(path, save)
    return states
