"""The ``mjwarp`` engine: a pod's LIBERO envs as MuJoCo Warp worlds on one GPU.

Each task block of an assignment is one batch of worlds (one MuJoCo Warp model, ``nworld`` =
the block's envs), built from the task's exported scene (:mod:`vecsim.engine.mjwarp.scene`).
Per env action, 25 physics substeps run as robosuite runs them: ``step1`` (positions and
velocities), then the batched OSC_POSE and gripper controller writes ``ctrl`` (its goal taken at
the first substep), then ``step2`` (actuation, constraints, integration). The 8-float state and
proprio are taken where LIBERO samples its observables, after substep 24 of 25
(``observables.LIBERO_SAMPLE_SUBSTEP``), with a copy of the kinematics the cameras read; the
success predicates after the last substep, as LIBERO's reward. Cameras are drawn once per
chunk, from that copy of each world's last action, by MuJoCo Warp's ray tracer.

What a call guarantees, as on the CPU engine:

- arguments are checked before anything moves (a refused call changes nothing);
- a reset to ``(task, k)`` starts every world exactly where a CPU pod's reset to ``k`` ended,
  settle steps included (the state was recorded at export), and answers that reset's own
  observation, its images drawn from the kinematics the CPU pod's cameras saw;
- only the named envs move: MuJoCo Warp steps every world of a batch, so the state of each
  world that is not stepping (not named, or ended earlier in the chunk) is put back after each
  action;
- a world whose contact or constraint buffers overflowed (``nconmax``, ``njmax``) or whose state
  is no longer finite is that env's error, never a NaN observation; it must be reset.

Not supported (refused when the assignment is taken): tasks whose goal has no batched predicate
yet, fixtures that move from one init state to the next, render presets other than ``full``,
``reset`` with seeds, and attribute calls (``get_attr``/``call``/``set_attr``).
"""

from __future__ import annotations

import importlib.util
import logging
import threading
import time
from dataclasses import dataclass
from typing import Any

import gymnasium
import numpy as np
from gymnasium.vector.utils import create_empty_array

from vecsim.config import Assignment, TaskBlock
from vecsim.engine import checks
from vecsim.engine.base import DEFAULT_MAX_CHUNK, CallTiming, ChunkResult, EngineKind
from vecsim.engine.errors import EnvError, InvalidRequestError, SimBuildError
from vecsim.engine.mjwarp import host, stepping
from vecsim.engine.mjwarp.host import GpuTurn, HostImages
from vecsim.engine.mjwarp.scene import VIEW_FIELDS, Scene, load_scene, load_tables, refusal, scene_dir
from vecsim.engine.mjwarp.settings import ALLOW_CPU_ENV, GPU_ENV, MjwarpSettings
from vecsim.engine.tasks._libero import LIBERO_SUITES, libero_observation_space
from vecsim.engine.tasks._robot import ACTION_DIM, robot_action_space
from vecsim.envsettings import SettingsError

log = logging.getLogger(__name__)

# warp's compile settings on its CPU device (the engine there is for tests and debugging): LLVM
# -O1 and no adjoint kernels, in place of warp's -O2 with raised inlining thresholds and adjoints
# the engine never runs. The first build of 2 worlds of libero_10/0 on 2 busy cores: 171 s, 612 s
# with warp's settings (docs/mjwarp.md). Set only where warp has no CUDA device, so every kernel
# it compiles is a CPU one: nothing compiled for a GPU changes.
CPU_WARP_CONFIG = {"optimization_level": 1, "enable_backward": False}
# State arrays that make up a world between actions: what is put back where a world does not step.
_DATA_STATE = ("qpos", "qvel", "act", "ctrl", "qacc_warmstart", "time")
_CONTROLLER_STATE = ("goal_pos", "goal_ori", "initial_joint", "gripper_command")
# The kinematics MuJoCo Warp's renderer reads, copied where LIBERO samples (recorded at export
# for resets).
_VIEW = VIEW_FIELDS
_NONE = np.zeros(0, dtype=np.int64)


def _missing_packages() -> list[str]:
    return [name for name in ("warp", "mujoco_warp") if importlib.util.find_spec(name) is None]


def read_settings() -> MjwarpSettings:
    """The engine's settings in the pod's environment, read when an engine is built.

    Raises:
        SimBuildError: a variable the engine cannot use, named with its value.
    """
    try:
        return MjwarpSettings.from_env()
    except SettingsError as exc:
        raise SimBuildError(f"mjwarp: {exc}") from None


def use_device(settings: MjwarpSettings) -> None:
    """Make the device ``settings`` name warp's default for the engine's worlds: CUDA device
    ``settings.gpu`` (``VECSIM_MJWARP_GPU``), else warp's default one (or its CPU device where
    ``settings.allow_cpu`` and no GPU is seen; not when a GPU is named).

    Raises:
        SimBuildError: no CUDA GPU (why, as :func:`_require_cuda` says), or none of that number.
    """
    import warp as wp

    _require_cuda(settings.allow_cpu and settings.gpu is None)
    if settings.gpu is None:
        return
    count = wp.get_cuda_device_count()
    if settings.gpu >= count:
        raise SimBuildError(
            f"mjwarp: environment variable {GPU_ENV} is '{settings.gpu}': warp sees {count} CUDA GPU(s), "
            f"cuda:0 to cuda:{count - 1}"
        )
    wp.set_device(f"cuda:{settings.gpu}")


def _require_cuda(allow_cpu: bool) -> None:
    """Raise :class:`SimBuildError` naming the cause unless warp sees a CUDA GPU (or
    ``allow_cpu``, ``VECSIM_MJWARP_ALLOW_CPU=1``: then set :data:`CPU_WARP_CONFIG` for warp's CPU
    device)."""
    import warp as wp

    if wp.is_cuda_available():
        return
    if allow_cpu:
        for name, value in CPU_WARP_CONFIG.items():
            setattr(wp.config, name, value)
        log.warning("mjwarp: no CUDA GPU; building on warp's CPU device (%s)", ALLOW_CPU_ENV)
        return
    driver, needed = wp.get_cuda_driver_version(), wp.get_cuda_toolkit_version()
    if driver is None:
        why = "no NVIDIA driver (libcuda.so.1) was found"
    elif needed is not None and driver[0] < needed[0]:
        why = (
            f"the NVIDIA driver supports CUDA {driver[0]}.{driver[1]}; warp {wp.config.version} needs CUDA {needed[0]}"
        )
    else:
        why = "the NVIDIA driver sees no GPU"
    raise SimBuildError(
        f"mjwarp: the engine runs on a CUDA GPU and warp found none: {why}; "
        f"{ALLOW_CPU_ENV}=1 builds on warp's CPU device instead (minutes of compiling)"
    )


def _suite(task_id: str) -> str:
    return task_id.partition("/")[0]


def check_scene(assignment: Assignment, block: TaskBlock) -> Scene:
    """The exported scene of ``block``'s task, checked against what this engine serves.

    Raises:
        InvalidRequestError: the field at fault named.
    """
    task_id = block.task_id
    if _suite(task_id) not in LIBERO_SUITES:
        raise InvalidRequestError(
            f"tasks: {task_id!r} is not a LIBERO task; the mjwarp engine serves LIBERO tasks only"
        )
    path = scene_dir(task_id, assignment.libero)
    try:
        scene = load_scene(path)
    except (FileNotFoundError, ValueError) as exc:
        raise InvalidRequestError(f"tasks: {task_id}: {exc}") from None
    refused = refusal(scene.manifest)
    if refused:
        raise InvalidRequestError(f"tasks: {task_id}: {refused}")
    missing = [name for name in assignment.camera.names if name not in scene.manifest["robot"]["cameras"]]
    if missing:
        raise InvalidRequestError(f"camera: {task_id} has no camera {missing[0]!r}")
    return scene


def spaces(assignment: Assignment) -> tuple[gymnasium.Space, gymnasium.Space]:
    """Check that the mjwarp engine can run ``assignment``; return its spaces (the CPU engine's
    for the same LIBERO tasks and cameras).

    Raises:
        InvalidRequestError: the field at fault named: ``engine`` (the extra is not installed),
            ``tasks``, ``camera``, ``render``, ``make_kwargs``.
    """
    if assignment.tasks:
        missing = _missing_packages()
        if missing:
            raise InvalidRequestError(
                f"engine: the mjwarp engine needs the mjwarp extra (pip install 'vecsim[mjwarp]'); missing {missing}"
            )
    if assignment.render not in (None, "full"):
        raise InvalidRequestError(
            f"render: the mjwarp engine draws with MuJoCo Warp's ray tracer only; {assignment.render!r} is a CPU preset"
        )
    if assignment.make_kwargs:
        raise InvalidRequestError("make_kwargs: the mjwarp engine serves LIBERO tasks, which take none")
    for block in assignment.tasks:
        check_scene(assignment, block)
    if not assignment.tasks:
        return gymnasium.spaces.Dict({}), gymnasium.spaces.Box(-1.0, 1.0, (0,), np.float32)
    return libero_observation_space(assignment.camera), robot_action_space()


@dataclass
class _Batch:
    """One task block's worlds and what runs over them."""

    block: TaskBlock
    scene: Scene
    mjm: Any
    model: Any
    data: Any
    controller: Any
    observables: Any
    goal: Any
    render: Any
    max_steps: int
    # The action of every world for the action being applied (zeros where a world does not step).
    action: Any
    # One camera's pixels of every world, uint8 [nworld, H, W, 3], on the GPU and in pinned host
    # memory (None without cameras).
    pixels: Any = None
    host: Any = None
    # Each world's _VIEW arrays as LIBERO's cameras see them: at the sample substep of its last
    # action, or at its reset (None without cameras).
    view: dict[str, Any] | None = None
    # One action's substeps as a CUDA graph, captured at the first action (None on a CPU device).
    graph: Any = None
    # The pixel each of a camera's rays draws (frames.order_rays; None without cameras).
    ray_order: Any = None


def build_batch(assignment: Assignment, settings: MjwarpSettings, block: TaskBlock) -> _Batch:
    """One task block's worlds, on warp's default device, as ``assignment`` and ``settings``
    say: the model, data, controller, observables, goal and (with cameras) render context."""
    import mujoco
    import mujoco_warp as mjw
    import warp as wp

    from vecsim.engine.mjwarp import frames
    from vecsim.engine.mjwarp.controller import PandaController
    from vecsim.engine.mjwarp.observables import PandaObservables
    from vecsim.engine.mjwarp.predicates import GoalEvaluator
    from vecsim.engine.mjwarp.tables import GoalTable, ObservableIndex, PandaIndex, mass_index

    scene = check_scene(assignment, block)
    tables = load_tables(scene)
    mjm = mujoco.MjModel.from_xml_path(str(scene.xml))
    states = scene.states
    mjm.body_pos[:], mjm.body_quat[:] = states["body_pos"][0], states["body_quat"][0]
    nworld = block.num_envs
    model = mjw.put_model(mjm)
    if settings.deterministic:
        model.opt.deterministic = int(mjw.DeterminismType.ALL)
    data = mjw.make_data(mjm, nworld=nworld, nconmax=settings.nconmax, njmax=settings.njmax)
    panda = dict(tables["panda"])
    # Indexed in this model's CSR mass matrix, the layout MuJoCo Warp holds.
    panda["mass_index"] = mass_index(mjm, panda["arm_dofs"])
    controller = PandaController(PandaIndex(**panda), nworld)
    observables = PandaObservables(ObservableIndex(**tables["obs"]), nworld)
    goal = GoalEvaluator(GoalTable(atoms=tuple(scene.manifest["goal"]["atoms"]), **tables["goal"]), nworld)
    render = order = None
    camera = assignment.camera
    if camera.names:
        render, order = frames.render_context(mjm, nworld, camera)
    limit = assignment.max_episode_steps or int(scene.manifest["max_episode_steps"])
    log.info("mjwarp: %s x%d built (%d bodies, %d geoms, nv %d)", block.task_id, nworld, mjm.nbody, mjm.ngeom, mjm.nv)
    action = wp.zeros((nworld, ACTION_DIM), dtype=wp.float32, device=controller.device)
    batch = _Batch(block, scene, mjm, model, data, controller, observables, goal, render, limit, action)
    if render is not None:
        shape = (nworld, camera.height, camera.width, 3)
        batch.pixels = wp.zeros(shape, dtype=wp.uint8, device=controller.device)
        # Pinned: the copy to the host runs at the bus's rate, not through a staging buffer.
        batch.host = wp.zeros(shape, dtype=wp.uint8, device="cpu", pinned=controller.device.is_cuda)
        batch.view = {name: wp.clone(getattr(data, name)) for name in _VIEW}
        batch.ray_order = order
    return batch


class MjwarpEngine:
    """The envs of one assignment as MuJoCo Warp worlds, addressed by env index (a
    :class:`~vecsim.engine.base.PodEngine`). Thread-safe: calls are serialised. ``timeout_s``
    and ``build_timeout_s`` are taken for the pod's sake and not used: there is no worker
    process to wait for.

    Raises:
        InvalidRequestError: what :func:`spaces` refuses.
        SimBuildError: a ``VECSIM_MJWARP_*`` variable it cannot use (:mod:`.settings`), no
            CUDA GPU, a scene failed to load, or MuJoCo Warp failed to build.
    """

    def __init__(
        self,
        assignment: Assignment,
        *,
        timeout_s: float | None = None,
        build_timeout_s: float | None = None,
        max_chunk: int = DEFAULT_MAX_CHUNK,
    ) -> None:
        if max_chunk < 1:
            raise ValueError(f"max_chunk: must be at least 1, got {max_chunk}")
        self.assignment = assignment
        self.max_chunk = max_chunk
        self.settings = read_settings()
        self.single_observation_space, self.single_action_space = spaces(assignment)
        self.num_envs = assignment.num_envs
        self.task_ids: list[str] = [b.task_id for b in assignment.tasks for _ in range(b.num_envs)]
        self.last_timing = CallTiming()
        self._lock = threading.Lock()
        self._closed = False
        self._num_states = np.zeros(self.num_envs, dtype=np.int64)
        # The envs' last observation and success, answered for envs a call does not move.
        self._obs = create_empty_array(self.single_observation_space, n=self.num_envs, fn=np.zeros)
        self._images: HostImages | None = None  # self._obs["images"], once the device is known
        self._turn = GpuTurn(None, "none")
        self._steps = np.zeros(self.num_envs, dtype=np.int64)
        self._last_success = np.zeros(self.num_envs, dtype=bool)
        self._broken: dict[int, str] = {}
        self._batches: list[_Batch] = []
        if not assignment.tasks:
            return
        use_device(self.settings)
        self._turn, self._images = host.for_engine(assignment.camera, self.num_envs, self.settings)
        if assignment.camera.names:
            self._obs["images"] = self._images.current
        started = time.monotonic()
        try:
            for block in assignment.tasks:
                if block.num_envs:
                    self._batches.append(build_batch(self.assignment, self.settings, block))
                    self._num_states[block.env_start : block.env_start + block.num_envs] = self._batches[
                        -1
                    ].scene.num_states
            log.info("mjwarp: compiling the step, controller, predicates and renderer kernels (first run: minutes)")
            self.reset_envs(np.arange(self.num_envs), np.zeros(self.num_envs, dtype=np.int64))
            actions = np.zeros((self.num_envs, 1, *self.single_action_space.shape), dtype=np.float32)
            actions[..., -1] = -1.0
            self.chunk_step_envs(np.arange(self.num_envs), actions)
            self.reset_envs(np.arange(self.num_envs), np.zeros(self.num_envs, dtype=np.int64))
        except InvalidRequestError:
            raise
        except Exception as exc:
            raise SimBuildError(f"mjwarp: building {self.num_envs} worlds failed: {type(exc).__name__}: {exc}") from exc
        log.info(
            "mjwarp: %d worlds in %d batches ready in %.1f s (kernels compiled, one chunk run)",
            self.num_envs,
            len(self._batches),
            time.monotonic() - started,
        )

    # The PodEngine calls.

    def reset_envs(
        self, env_indices: Any, state_ids: Any = None, *, seeds: Any = None, options: dict[str, Any] | None = None
    ) -> tuple[Any, dict[str, Any]]:
        """Reset the named envs to LIBERO's init states (after their settle steps); no other env
        changes. ``seeds`` (the envs' own reset) is refused: a LIBERO env starts from its init
        states only."""
        ids = checks.env_indices(env_indices, self.num_envs)
        if seeds is not None or state_ids is None:
            raise InvalidRequestError("seeds: the mjwarp engine resets LIBERO envs to state_ids only")
        states = checks.state_ids(state_ids, ids, self._num_states, self.task_ids)
        if options:
            raise InvalidRequestError("options: go with seeds (the envs' own reset), not with state_ids")
        with self._lock, self._turn:
            self._check_open()
            started = time.perf_counter()
            self._reset(ids, states)
            physics = time.perf_counter() - started
            render_s, renders = self._render(ids)
            self.last_timing = CallTiming(physics, render_s, renders, self._turn.waited_s)
            return self._reset_answer(ids)

    def step_envs(self, env_indices: Any, actions: Any) -> tuple[Any, Any, Any, Any, dict[str, Any]]:
        """Step the named envs one action each (a chunk of one)."""
        ids = checks.env_indices(env_indices, self.num_envs)
        result = self.chunk_step_envs(ids, checks.actions(actions, ids, self.single_action_space))
        info = {"success": result.success[:, 0], "env_info": result.env_info, "errors": result.errors}
        return result.obs, result.reward[:, 0], result.terminated[:, 0], result.truncated[:, 0], info

    def chunk_step_envs(
        self, env_indices: Any, actions: Any, record_env_indices: Any = (), step_past_end: bool = False
    ) -> ChunkResult:
        """Apply ``chunk`` (``[n, K, 7]``) to the named envs in order, each stopping at its first
        termination or truncation unless ``step_past_end``; cameras drawn once, after the chunk,
        and after each action that an env of ``record_env_indices`` applied."""
        ids = checks.env_indices(env_indices, self.num_envs)
        chunk = checks.chunk(actions, ids, self.single_action_space, self.max_chunk).astype(np.float32)
        recorded = checks.record(record_env_indices, ids)
        if ids.size == 0 or chunk.shape[1] == 0:
            return self._unmoved(ids, chunk, recorded)
        with self._lock, self._turn:
            self._check_open()
            return self._chunk(ids, chunk, recorded, step_past_end)

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
    ) -> tuple[tuple[Any, dict[str, Any]], ChunkResult]:
        """Reset some envs and step others in one call (a refill), in one turn at the GPU: the
        resets first, then the chunk; the reset envs are drawn by the chunk's render, so a
        refill draws its batches once, as a chunk does (a reset alone draws them too)."""
        reset_ids = checks.env_indices(reset_env_indices, self.num_envs, "reset_env_indices")
        step_ids = checks.env_indices(env_indices, self.num_envs)
        if np.intersect1d(reset_ids, step_ids).size:
            raise InvalidRequestError("reset_env_indices: an env is both reset and stepped")
        if chunked:
            chunk = checks.chunk(actions, step_ids, self.single_action_space, self.max_chunk)
        else:
            chunk = checks.actions(actions, step_ids, self.single_action_space)  # a chunk of one
        recorded = checks.record(record_env_indices, step_ids)
        # Checked before the resets, so a refused call changes nothing.
        reset_states = checks.state_ids(state_ids, reset_ids, self._num_states, self.task_ids, "reset_state_ids")
        chunk = chunk.astype(np.float32)
        if step_ids.size == 0 or chunk.shape[1] == 0:
            return self.reset_envs(reset_ids, reset_states), self._unmoved(step_ids, chunk, recorded)
        with self._lock, self._turn:
            self._check_open()
            started = time.perf_counter()
            self._reset(reset_ids, reset_states)
            try:
                result = self._chunk(step_ids, chunk, recorded, step_past_end, reset_ids, time.perf_counter() - started)
            except Exception:
                self._render(reset_ids)  # the resets stand: so do their images
                raise
            return self._reset_answer(reset_ids), result

    def frame(self, env_index: int, camera: str) -> np.ndarray:
        """A copy of the uint8 HxWx3 image ``camera`` of env ``env_index`` saw last."""
        ids = checks.env_indices(np.array([env_index]), self.num_envs)
        if camera not in self.assignment.camera.names:
            raise InvalidRequestError(f"camera: no camera {camera!r}; cameras: {list(self.assignment.camera.names)}")
        with self._lock:
            return np.array(self._obs["images"][camera][ids[0]])

    def env_attr(self, env_indices: Any, op: str, name: Any, payload: Any = None) -> tuple[list[Any], list[EnvError]]:
        """Refused: a MuJoCo Warp world has no Python env object to read or call."""
        ids = checks.env_indices(env_indices, self.num_envs)
        if ids.size == 0:
            return [], []
        raise InvalidRequestError(f"name: the mjwarp engine has no env attributes to {op} ({name!r})")

    def close(self) -> None:
        """Free the worlds. Idempotent."""
        with self._lock:
            self._closed = True
            self._batches = []
            self._turn.close()

    def __enter__(self) -> MjwarpEngine:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    # Internals.

    def _check_open(self) -> None:
        if self._closed:
            raise InvalidRequestError("engine: the mjwarp engine is closed")

    def _reset(self, ids: np.ndarray, states: np.ndarray) -> None:
        for batch, rows, worlds in self._split(ids):
            self._reset_worlds(batch, worlds, states[rows])

    def _reset_answer(self, ids: np.ndarray) -> tuple[Any, dict[str, Any]]:
        """A reset's answer for ``ids``, after their images were drawn."""
        info = {
            "success": self._last_success[ids].copy(),
            "task_id": [self.task_ids[e] for e in ids],
            "env_info": [{} for _ in ids],
            "errors": [],
        }
        return self._gather(ids), info

    def _outcome(self, n: int, k: int, recorded: np.ndarray) -> tuple[dict[str, np.ndarray], tuple[np.ndarray, ...]]:
        """A chunk's empty frames (the recorded envs', zeros after an env stopped) and its reward,
        terminated, truncated, success and num_steps arrays, for ``n`` envs of ``k`` actions."""
        camera = self.assignment.camera
        frames = {
            name: np.zeros((recorded.size, k, camera.height, camera.width, 3), dtype=np.uint8)
            for name in (camera.names if recorded.size else ())
        }
        flags = tuple(np.zeros((n, k), dtype=bool) for _ in range(3))
        return frames, (np.zeros((n, k), dtype=np.float64), *flags, np.zeros(n, dtype=np.int32))

    def _unmoved(self, ids: np.ndarray, chunk: np.ndarray, recorded: np.ndarray) -> ChunkResult:
        """The answer of a chunk that moves nothing (no envs, or no actions)."""
        frames, arrays = self._outcome(ids.size, chunk.shape[1], recorded)
        return ChunkResult(self._gather(ids), *arrays, frames, [{} for _ in ids], [])

    def _chunk(
        self,
        ids: np.ndarray,
        chunk: np.ndarray,
        recorded: np.ndarray,
        step_past_end: bool,
        drawn: np.ndarray = _NONE,
        reset_s: float = 0.0,
    ) -> ChunkResult:
        """Step ``chunk`` (checked, ``[n >= 1, K >= 1, 7]``) under the lock and the GPU turn; the
        render after it draws the moved envs and ``drawn`` (a refill's reset envs)."""
        frames, (reward, terminated, truncated, success, num_steps) = self._outcome(*chunk.shape[:2], recorded)
        errors: list[EnvError] = []
        started = time.perf_counter()
        frames_s = 0.0  # the per-action frames' renders, counted as render time
        for batch, rows, _worlds in self._split(ids):
            broken = [r for r, e in zip(rows, ids[rows]) if int(e) in self._broken]
            for r in broken:
                errors.append(EnvError(int(r), "SimStateError", self._broken[int(ids[r])]))
            live = np.array([r for r in rows if r not in broken], dtype=np.int64)
            # The recorded envs of this batch: world -> their row in ``frames``.
            shots = {int(ids[r]) - batch.block.env_start: m for m, r in enumerate(recorded) if r in live}
            if live.size:
                frames_s += self._step_batch(
                    batch,
                    ids,
                    live,
                    chunk,
                    reward,
                    terminated,
                    truncated,
                    success,
                    num_steps,
                    step_past_end,
                    errors,
                    (shots, frames),
                )
        physics = time.perf_counter() - started - frames_s + reset_s
        render_s, renders = self._render(np.union1d(ids[num_steps > 0], drawn))
        self.last_timing = CallTiming(physics, render_s + frames_s, renders, self._turn.waited_s)
        errors.sort(key=lambda e: e.row)
        obs = self._gather(ids)
        return ChunkResult(obs, reward, terminated, truncated, success, num_steps, frames, [{} for _ in ids], errors)

    def _split(self, ids: np.ndarray) -> list[tuple[_Batch, np.ndarray, np.ndarray]]:
        """The call's rows per batch: ``(batch, rows of ids, world indices)``."""
        out = []
        for batch in self._batches:
            start, count = batch.block.env_start, batch.block.num_envs
            rows = np.flatnonzero((ids >= start) & (ids < start + count))
            if rows.size:
                out.append((batch, rows, ids[rows] - start))
        return out

    def _reset_worlds(self, batch: _Batch, worlds: np.ndarray, states: np.ndarray) -> None:
        import warp as wp

        recorded = batch.scene.states
        data = batch.data
        for name in _DATA_STATE:
            values = getattr(data, name).numpy()
            values[worlds] = recorded[name][states]
            getattr(data, name).assign(values)
        mask = np.zeros(batch.block.num_envs, dtype=np.int32)
        mask[worlds] = 1
        full = np.zeros((batch.block.num_envs, 7), dtype=np.float32)
        full[worlds] = recorded["initial_joint"][states]
        goal_pos = np.zeros((batch.block.num_envs, 3), dtype=np.float32)
        goal_pos[worlds] = recorded["goal_pos"][states]
        goal_ori = np.zeros((batch.block.num_envs, 3, 3), dtype=np.float32)
        goal_ori[worlds] = recorded["goal_ori"][states]
        device = batch.controller.device
        batch.controller.reset(
            wp.array(mask, dtype=wp.int32, device=device),
            wp.array(full, dtype=wp.float32, device=device),
            wp.array(goal_pos, dtype=wp.vec3, device=device),
            wp.array(goal_ori, dtype=wp.mat33, device=device),
        )
        command = batch.controller.gripper_command.numpy()
        command[worlds] = recorded["gripper_action"][states]
        batch.controller.gripper_command.assign(command)
        data.overflow.zero_()
        # The cameras see what a CPU pod's cameras drew for this reset: the kinematics at LIBERO's
        # last sample (substep 24 of the last settle step), not at the settled end state. The
        # next step1 computes the end state's own.
        if batch.view is not None:
            for name, view in batch.view.items():
                values = view.numpy()
                values[worlds] = recorded[f"view.{name}"][states].reshape(values[worlds].shape)
                view.assign(values)
        envs = worlds + batch.block.env_start
        self._obs["state"][envs] = recorded["obs_state"][states]
        self._obs["proprio"][envs] = recorded["obs_proprio"][states]
        self._last_success[envs] = recorded["success"][states]
        self._steps[envs] = 0
        for env in envs:
            self._broken.pop(int(env), None)

    @staticmethod
    def _state_arrays(batch: _Batch) -> dict[str, Any]:
        """Every per-world array that a world which does not step must keep."""
        arrays = {name: getattr(batch.data, name) for name in _DATA_STATE}
        arrays.update({f"controller.{n}": getattr(batch.controller, n) for n in _CONTROLLER_STATE})
        arrays.update({f"view.{n}": view for n, view in (batch.view or {}).items()})
        return arrays

    def _snapshot(self, batch: _Batch) -> dict[str, np.ndarray]:
        # A copy: on warp's CPU device numpy() is the array's own memory, which the step moves.
        return {key: array.numpy().copy() for key, array in self._state_arrays(batch).items()}

    def _put_back(self, batch: _Batch, saved: dict[str, np.ndarray], frozen: np.ndarray) -> None:
        """Give the ``frozen`` worlds (bool per world) their ``saved`` state again."""
        for key, array in self._state_arrays(batch).items():
            now = array.numpy()
            now[frozen] = saved[key][frozen]
            array.assign(now)

    def _step_batch(
        self,
        batch: _Batch,
        ids: np.ndarray,
        rows: np.ndarray,
        actions: np.ndarray,
        reward: np.ndarray,
        terminated: np.ndarray,
        truncated: np.ndarray,
        success: np.ndarray,
        num_steps: np.ndarray,
        step_past_end: bool,
        errors: list[EnvError],
        recording: tuple[dict[int, int], dict[str, np.ndarray]] = ({}, {}),
    ) -> float:
        """Step ``rows`` of ``ids`` (envs of ``batch``) through ``actions``, writing the outcome
        arrays in place; ``recording`` (world -> row of ``frames``) takes the recorded worlds'
        frame after each action. Returns the seconds those frames took to draw."""
        shots, frames = recording
        frames_s = 0.0
        nworld = batch.block.num_envs
        worlds = ids[rows] - batch.block.env_start
        running = np.zeros(nworld, dtype=bool)
        running[worlds] = True
        # Taken only when a world may not step: when every world steps, none is put back until
        # one ends (then that world's state is saved) or fails (then it must be reset anyway).
        saved = self._snapshot(batch) if not running.all() else None
        data = batch.data
        world_action = np.zeros((nworld, actions.shape[2]), dtype=np.float32)
        row_of_world = {int(w): int(r) for w, r in zip(worlds, rows)}
        world_rows = np.full(nworld, -1, dtype=np.int64)
        world_rows[worlds] = rows
        for k in range(actions.shape[1]):
            if not running.any():
                break
            world_action[:] = 0.0
            world_action[worlds] = actions[rows, k]
            batch.action.assign(world_action)
            stepping.apply_action(batch)
            overflow = data.overflow.numpy()
            qpos, qvel = data.qpos.numpy(), data.qvel.numpy()
            state, proprio = batch.observables.state.numpy(), batch.observables.proprio.numpy()
            won = batch.goal.success.numpy().astype(bool)
            frozen = ~running
            # Every running world's outcome of this action, as arrays over worlds.
            finite = np.isfinite(qpos).all(axis=1) & np.isfinite(qvel).all(axis=1)
            failed = running & (((overflow & stepping.OVERFLOW_BITS) != 0) | ~finite)
            for world in np.flatnonzero(failed):
                row = row_of_world[int(world)]
                env = int(ids[row])
                reason = stepping.overflow_reason(int(overflow[world])) or "the state is no longer finite"
                message = f"env {env}: MuJoCo Warp {reason} at action {k}; reset it"
                self._broken[env] = message
                errors.append(EnvError(row, "SimStateError", message))
            running &= ~failed
            frozen |= failed
            stepped = np.flatnonzero(running)
            if frames and any(running[w] for w in shots):
                frames_s += self._shoot(batch, k, [(m, w) for w, m in shots.items() if running[w]], frames)
            rows_now = world_rows[stepped]
            envs_now = ids[rows_now]
            num_steps[rows_now] += 1
            self._steps[envs_now] += 1
            success[rows_now, k] = won[stepped]
            reward[rows_now, k] = won[stepped]
            terminated[rows_now, k] = won[stepped]
            truncated[rows_now, k] = self._steps[envs_now] >= batch.max_steps
            self._obs["state"][envs_now] = state[stepped]
            self._obs["proprio"][envs_now] = proprio[stepped]
            self._last_success[envs_now] = won[stepped]
            ended = [] if step_past_end else stepped[terminated[rows_now, k] | truncated[rows_now, k]].tolist()
            # Those stop here: from the next action on, they are put back to this state.
            running[ended] = False
            if ended:
                now = self._snapshot(batch)
                if saved is None:
                    saved = now
                for key, values in now.items():
                    saved[key][ended] = values[ended]
            if frozen.any() and saved is not None:
                self._put_back(batch, saved, frozen)
        return frames_s

    def _render(self, ids: np.ndarray) -> tuple[float, int]:
        """Draw every camera of the batches holding ``ids`` (MuJoCo Warp draws every world of a
        batch); copy the named envs' images. Returns seconds and env renders."""
        if not self.assignment.camera.names or ids.size == 0:
            return 0.0, 0
        from vecsim.engine.mjwarp import frames

        started = time.perf_counter()
        renders = 0
        assert self._images is not None
        self._images.renew(every=ids.size == self.num_envs)
        images = self._images.current
        for batch, _rows, worlds in self._split(ids):
            self._draw(batch, *frames.writers(images, batch.block.env_start, batch.block.num_envs, worlds))
            renders += len(worlds)
        return time.perf_counter() - started, renders

    def _shoot(self, batch: _Batch, k: int, shots: list[tuple[int, int]], frames: dict[str, np.ndarray]) -> float:
        """Put action ``k``'s frame of each recorded world (``(frame row, world)``) into ``frames``;
        return the seconds it took."""
        started = time.perf_counter()

        def take(name: str, host: np.ndarray) -> None:
            for m, world in shots:
                frames[name][m, k] = host[world]

        self._draw(batch, take)
        return time.perf_counter() - started

    def _draw(self, batch: _Batch, take: Any, into: Any = None) -> None:
        from vecsim.engine.mjwarp import frames

        camera = self.assignment.camera
        orientation = self.assignment.libero.image_orientation
        frames.draw(batch, camera.names, camera.height, camera.width, orientation, take, into)

    def _gather(self, ids: np.ndarray) -> dict[str, Any]:
        """The observations of ``ids``, the caller's to keep. The images of a contiguous run of
        envs (the usual call: every env, in order) are views, not copies, lent until the next
        render (which then writes into another set, see :class:`HostImages`); the rest is copied."""
        run = contiguous_run(ids)

        def pick(tree: Any) -> Any:
            if isinstance(tree, dict):
                return {key: pick(sub) for key, sub in tree.items()}
            return tree[ids]

        obs = {}
        for key, sub in self._obs.items():
            if key == "images" and run is not None and self._images is not None:
                obs[key] = {name: self._images.lend(name, run) for name in sub}
            else:
                obs[key] = pick(sub)
        return obs


def contiguous_run(ids: np.ndarray) -> slice | None:
    """``ids`` as a slice when they are ``a, a + 1, ..., b - 1`` (at least one), else None."""
    if ids.size == 0 or int(ids[-1]) - int(ids[0]) + 1 != ids.size:
        return None
    first = int(ids[0])
    return slice(first, first + ids.size) if np.array_equal(ids, np.arange(first, first + ids.size)) else None


def build(
    assignment: Assignment,
    *,
    timeout_s: float | None = None,
    build_timeout_s: float | None = None,
    max_chunk: int = DEFAULT_MAX_CHUNK,
) -> MjwarpEngine:
    """The assignment's worlds, every env in state 0, kernels compiled and one chunk run."""
    return MjwarpEngine(assignment, timeout_s=timeout_s, build_timeout_s=build_timeout_s, max_chunk=max_chunk)


def task_info(assignment: Assignment, task_id: str) -> tuple[str, int]:
    """The task's instruction and number of init states, from its exported scene (no LIBERO)."""
    block = next(b for b in assignment.tasks if b.task_id == task_id)
    manifest = check_scene(assignment, block).manifest
    return manifest["instruction"], int(manifest["num_states"])


KIND = EngineKind(
    name="mjwarp", spaces=spaces, build=build, steps_on_event_loop=lambda assignment: False, task_info=task_info
)
