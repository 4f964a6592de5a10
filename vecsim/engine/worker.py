"""The worker's side: the envs one worker process hosts, and the process that runs them.

A worker hosts ``envs_per_worker`` consecutive env indices of a pod, whatever their tasks
(:class:`WorkerSpec`); an env's *local index* is its place among them. :func:`worker_process` is
the process: it builds a :class:`Worker`, then answers the pod's orders
(:mod:`vecsim.engine.protocol`) until its pipe closes. Observations and per-env, per-action result
rows (reward, terminated, truncated, success: the columns :data:`REWARD` ...) go straight into
the worker's part of the pod's shared memory (:func:`results_space`); what is small or ragged
travels back in the :class:`~vecsim.engine.protocol.Reply`. Cameras are drawn once per call, after
every order ran, all of the worker's touched envs in one batch of its renderer
(:mod:`vecsim.engine.batch_render`).

Once its envs are built, a worker frees what MuJoCo's XML compiler keeps for the life of the
process (the last model's parsed spec and the asset cache): for a LIBERO scene that is ~950 MB of
a worker's ~2.4 GB, paid once per process however many envs it then builds (``docs/pod.md``).
Module-level code imports nothing heavy and starts nothing: it is safe under ``forkserver``.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import dataclasses
import glob
import json
import logging
import multiprocessing.connection
import os
import time
import traceback
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import gymnasium
import numpy as np
from gymnasium.vector.utils import batch_space, read_from_shared_memory

from vecsim import wire
from vecsim.config import CameraConfig, LiberoProtocol, RenderPreset
from vecsim.engine import protocol
from vecsim.engine.base import DEFAULT_MAX_CHUNK
from vecsim.engine.errors import SimBuildError
from vecsim.engine.protocol import Order, Reply
from vecsim.engine.tasks import TaskEnv, episode_limit, make_env
from vecsim.engine.tasks._gym import VECSIM_INFO_KEYS, GymTaskEnv

log = logging.getLogger("vecsim.engine.worker")

# Columns of a worker's per-env, per-action result rows.
REWARD, TERMINATED, TRUNCATED, SUCCESS = 0, 1, 2, 3


def _describe(task_ids: Sequence[str], env_indices: Sequence[int]) -> str:
    """Name the envs of a run of env indices by task: ``tiny/lift (envs 0-1), tiny/door (envs 2-2)``."""
    runs: list[tuple[str, int, int]] = []
    for task_id, env in zip(task_ids, env_indices):
        if runs and runs[-1][0] == task_id:
            runs[-1] = (task_id, runs[-1][1], env)
        else:
            runs.append((task_id, env, env))
    return ", ".join(f"{task_id} (envs {first}-{last})" for task_id, first, last in runs)


@dataclass(frozen=True)
class WorkerSpec:
    """What one worker process hosts: env ``env_indices[i]`` of task ``task_ids[i]`` at local
    index ``i``, room for ``envs_per_worker`` envs (the rows beyond ``len(env_indices)`` idle)."""

    task_ids: tuple[str, ...]
    env_indices: tuple[int, ...]
    envs_per_worker: int
    camera: CameraConfig
    render: RenderPreset | None
    max_episode_steps: int | None
    observation_space: gymnasium.Space
    action_space: gymnasium.Space
    max_chunk: int = DEFAULT_MAX_CHUNK
    libero: LiberoProtocol = LiberoProtocol()
    make_kwargs: Any = None

    def describe(self) -> str:
        """Return the hosted envs by task, e.g. ``tiny/lift (envs 0-1), tiny/door (envs 2-2)``."""
        return _describe(self.task_ids, self.env_indices)


def _warm_action(space: gymnasium.spaces.Box) -> np.ndarray:
    """An action a quarter of the way from the centre of ``space`` to its upper bound in every
    dimension (0.25 where unbounded): it moves and turns the arm and the gripper, so a step
    with it reaches every branch a trainer's actions reach."""
    low, high = np.asarray(space.low, np.float64), np.asarray(space.high, np.float64)
    bounded = np.isfinite(low) & np.isfinite(high)
    centre = np.where(bounded, (low + high) / 2, 0.0)
    return (centre + np.where(bounded, (high - low) / 8, 0.25)).astype(space.dtype)


def _release_compiler_memory() -> None:
    """Free what MuJoCo's XML compiler holds after a model is made, and give freed heap back.

    ``mj_loadXML`` keeps the last model's parsed spec (meshes and textures decoded) for
    ``mj_saveLastXML``, and the compiler caches assets (500 MB by default): for a LIBERO scene
    ~950 MB that no built env uses. Only ``mj_saveLastXML`` (robosuite's ``MjModel.get_xml``)
    needs the spec, and no worker calls it. The Python bindings do not wrap ``mj_freeLastXML``,
    so it is called in the library they load.
    """
    import mujoco

    mujoco.mj_clearCache(mujoco.mj_getCache())
    libraries = sorted(glob.glob(os.path.join(os.path.dirname(mujoco.__file__), "libmujoco.so*")))
    if libraries:
        ctypes.CDLL(libraries[0]).mj_freeLastXML()
    else:
        log.debug("no libmujoco beside the mujoco package: the last model's spec stays in memory")
    libc_name = ctypes.util.find_library("c")
    libc = ctypes.CDLL(libc_name) if libc_name else None
    # glibc keeps freed heap pages mapped until trimmed; other C libraries have no malloc_trim.
    if libc is not None and hasattr(libc, "malloc_trim"):
        libc.malloc_trim(0)


def _zeros(space: gymnasium.Space) -> Any:
    if isinstance(space, gymnasium.spaces.Dict):
        return {key: _zeros(sub) for key, sub in space.spaces.items()}
    if isinstance(space, gymnasium.spaces.Tuple):
        return tuple(_zeros(sub) for sub in space.spaces)
    return np.zeros(space.shape, dtype=space.dtype)


def _write_obs(out: Any, local: int, value: Any) -> None:
    """Write one env's observation at its local index ``local`` into the batched ``out``
    (a dict may leave keys out: deferred images)."""
    if isinstance(value, dict):
        for key, item in value.items():
            _write_obs(out[key], local, item)
    elif isinstance(value, tuple):
        for sub, item in zip(out, value):
            _write_obs(sub, local, item)
    else:
        out[local] = value


def _own_info(env: TaskEnv, info: dict[str, Any]) -> dict[str, Any]:
    """An env's own info: a native gym env's whole, a robot task's without vecsim's keys (those
    travel as flags)."""
    if getattr(env, "native", False):
        return info
    return {key: value for key, value in info.items() if key not in VECSIM_INFO_KEYS}


def _success(info: dict[str, Any]) -> bool:
    """The success flag of an env's info: a robot task's, or a gym env's own ``success`` key if
    it gives one that reads as a bool (anything else: False)."""
    try:
        return bool(info.get("success", False))
    except (TypeError, ValueError):  # an array of several values, say
        return False


def _view(value: Any) -> Any:
    """A JSON-safe view of a spec: gymnasium's ``EnvSpec`` as its own ``to_json``, a dataclass
    (a task's ``TaskSpec``) as its fields; any other value as it is."""
    if isinstance(value, gymnasium.envs.registration.EnvSpec):
        return json.loads(value.to_json())
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return dataclasses.asdict(value)
    return value


def _jsonable(value: Any, what: str) -> Any:
    """``value`` (a spec: its view, :func:`_view`) as plain JSON data, or ValueError saying it
    cannot travel. An array of bools or integers (a ``render()`` frame) stays an array: the
    answer's encoding makes it JSON in one pass, as it cannot fail."""
    value = _view(value)
    if isinstance(value, np.ndarray) and value.dtype.kind in "biu" and value.dtype.itemsize <= 8:
        return value
    try:
        data = wire.to_jsonable(value)
        json.dumps(data, allow_nan=False)
    except (wire.WireError, TypeError, ValueError) as exc:
        raise ValueError(f"{what} is a {type(value).__name__}, not JSON-serialisable: {exc}") from None
    return data


def _attr_op(target: gymnasium.Env, op: str, name: str, payload: Any) -> Any:
    what = f"attribute {name!r}"
    if op == "get":
        return _jsonable(target.get_wrapper_attr(name), what)
    if op == "call":
        attr = target.get_wrapper_attr(name)
        args, kwargs = payload
        return _jsonable(attr(*args, **kwargs) if callable(attr) else attr, f"the result of {name!r}")
    try:
        current = target.get_wrapper_attr(name)
    except AttributeError:
        # gymnasium's set_wrapper_attr (force=True) makes an attribute no layer has yet, as
        # its vector envs' set_attr does; the value came as JSON.
        target.set_wrapper_attr(name, payload)
        return None
    if callable(current) or isinstance(current, (gymnasium.Space, np.random.Generator)):
        raise ValueError(f"{what} is a {type(current).__name__}; set_attr sets JSON-valued attributes only")
    _jsonable(current, what)
    if isinstance(current, np.ndarray):
        value = np.asarray(payload, dtype=current.dtype)
        if value.shape != current.shape:
            raise ValueError(f"{what}: expected shape {list(current.shape)}, got {list(value.shape)}")
        payload = value
    target.set_wrapper_attr(name, payload)
    return None


def results_space(worker: WorkerSpec) -> gymnasium.spaces.Dict:
    """One worker's part of the shared memory: its envs' observations and result rows, by local index."""
    return gymnasium.spaces.Dict(
        {
            "obs": batch_space(worker.observation_space, worker.envs_per_worker),
            # Per env and chunk action: reward, terminated, truncated, success (zeros after the
            # action an env stopped at).
            "flags": gymnasium.spaces.Box(-np.inf, np.inf, (worker.envs_per_worker, worker.max_chunk, 4), np.float64),
        }
    )


class Worker:
    """The envs one worker process hosts (a run of envs, of one task or several), run by orders.

    ``out`` is where observations and result rows go (:func:`results_space`): this worker's part
    of the pod's shared memory in a worker process, plain arrays when made in process (tests).
    :meth:`build` makes the envs and puts each in state 0.
    """

    def __init__(self, worker: WorkerSpec, out: dict[str, Any] | None = None) -> None:
        self.worker = worker
        self._envs: list[TaskEnv] = []
        self._out: dict[str, Any] = _zeros(results_space(worker)) if out is None else out
        # Per call: each env's own info and the exceptions envs raised, by local index.
        self._infos: list[tuple[int, dict[str, Any]]] = []
        self._errors: list[tuple[int, str, str]] = []

    def build(self) -> dict[str, float]:
        """Make this worker's envs, reset each to state 0 (a native gym env is left unreset, as
        its factory made it), warm the step path and render them, so that the first step a
        trainer sends costs what later ones do.

        Returns:
            how long each part took, in seconds (``make``, ``reset``, ``warm``, ``render``), and
            ``envs``, how many envs were made.

        Raises:
            SimBuildError: an env could not be made or reset; the message names its task and env
                index (``tiny/door (envs 2-2)``), or all the worker's envs when rendering failed.
        """
        worker = self.worker
        local = 0
        took: dict[str, float] = {}
        clock = time.perf_counter()

        def lap(part: str) -> None:
            nonlocal clock
            took[part] = time.perf_counter() - clock
            clock = time.perf_counter()

        try:
            for local, task_id in enumerate(worker.task_ids):
                steps = episode_limit(task_id, worker.max_episode_steps)
                kwargs = (worker.make_kwargs or {}).get(task_id)
                env = make_env(task_id, worker.camera, worker.render, steps, worker.libero, kwargs)
                self._envs.append(env)
                spaces = (env.observation_space, env.action_space)
                if spaces != (worker.observation_space, worker.action_space):
                    raise ValueError(
                        f"its env's spaces differ from the ones the task declares: "
                        f"{env.observation_space}, {env.action_space}"
                    )
            for env in self._envs:
                env.defer_images = True
            lap("make")
            for local, env in enumerate(self._envs):
                # A native gym env stays as its factory left it (its seeds, its generators), as
                # gymnasium's vector envs take it; the first reset is the trainer's.
                if not getattr(env, "native", False):
                    self._reset_env(local, 0)
            lap("reset")
            local = self._warm_step_path()
            lap("warm")
            local = -1
            self._render(list(range(len(self._envs))))
            lap("render")
        except Exception as exc:
            failed = slice(None) if local < 0 else slice(local, local + 1)
            where = _describe(worker.task_ids[failed], worker.env_indices[failed])
            raise SimBuildError(f"{where}: {type(exc).__name__}: {exc}") from exc
        _release_compiler_memory()
        return {"envs": float(len(self._envs)), **took}

    def _warm_step_path(self) -> int:
        """Step the first env of each step path once and put it back in state 0, so that what a
        first step compiles or loads happens here, not on the trainer's first step: the exact
        path's compiled controller (a fresh checkout: seconds), and robosuite's own numba kernels
        that only a turning arm reaches.

        The action is off-centre in every dimension: robosuite's OSC ``set_goal`` (robosuite 1.4,
        controllers/osc.py:258-261) skips ``set_goal_orientation`` for a zero rotation, and only
        that calls the numba-compiled ``quat2mat`` (utils/control_utils.py:176), so a zero action
        left it to the trainer's first step (~0.1 s a worker loading it from numba's cache,
        measured; compiling it takes seconds). The reset restores state 0 whole, so the env is
        as the build left it. Returns the last env stepped's local index, or -1 when no env has
        a step path (gym tasks: nothing of theirs is compiled)."""
        warmed: set[str] = set()
        last = -1
        for local, env in enumerate(self._envs):
            path = getattr(env, "step_path", None)
            if path is None or path in warmed:
                continue
            env.step(_warm_action(env.action_space))
            self._reset_env(local, 0)
            warmed.add(path)
            last = local
        return last

    def _reset_env(
        self,
        local: int,
        state_id: int,
        seed: int | None = None,
        seeded: bool = False,
        options: dict[str, Any] | None = None,
    ) -> None:
        """Reset one env: to fixed state ``state_id``, or (``seeded``) the env's own reset with
        ``seed`` and ``options``."""
        env = self._envs[local]
        if seeded:
            observation, info = env.reset(seed=seed, options=options)
        else:
            observation, info = env.reset(options={"state_id": state_id})
        _write_obs(self._out["obs"], local, observation)
        self._out["flags"][local] = 0.0
        self._out["flags"][local, 0, SUCCESS] = _success(info)
        self._keep_info(local, info)

    def _keep_info(self, local: int, info: dict[str, Any]) -> None:
        own = _own_info(self._envs[local], info)
        if own:
            self._infos.append((local, own))

    def _step_env(
        self, local: int, chunk: np.ndarray, record: bool, past_end: bool = False
    ) -> tuple[list[dict[str, np.ndarray]], float]:
        """Apply ``chunk``'s actions to one env until it terminates or truncates (``past_end``: all
        of them, as LIBERO's and the trainers' own envs are stepped on); return the frames
        recorded after each applied action but the last, and the seconds spent drawing them."""
        env = self._envs[local]
        if not getattr(env, "native", False):  # a gym env takes actions as sent; a robot task in its dtype
            chunk = chunk.astype(env.action_space.dtype, copy=False)
        rows = self._out["flags"][local]
        rows[:] = 0.0
        frames: list[dict[str, np.ndarray]] = []
        render_s = 0.0
        observation = None
        info: dict[str, Any] = {}
        for k, action in enumerate(chunk):
            observation, reward, terminated, truncated, info = env.step(action)
            rows[k] = (reward, terminated, truncated, _success(info))
            if (terminated or truncated) and not past_end:
                break
            if record and k + 1 < len(chunk) and env.renderer is not None:
                drawn = time.perf_counter()
                frames.append(self._draw([local]))
                render_s += time.perf_counter() - drawn
        if observation is not None:
            _write_obs(self._out["obs"], local, observation)
            self._keep_info(local, info)
        return frames, render_s

    def run(self, *orders: Order) -> Reply:
        """Carry out ``orders`` (each env's reset or chunk step, in order), then render the
        cameras of every env reset or stepped, once, in one batch; return the :class:`Reply`.

        An env that raises is named in the reply (its result rows zeroed); the others go on."""
        started = time.perf_counter()
        touched: list[int] = []
        recorded: list[tuple[int, list[dict[str, np.ndarray]]]] = []
        render_s = 0.0
        self._infos, self._errors = [], []
        for order in orders:
            for i, local in enumerate(order.local_indices.tolist()):
                try:
                    if order.actions is not None:
                        record = order.record is not None and bool(order.record[i])
                        frames, drawing_s = self._step_env(local, order.actions[i], record, order.past_end)
                        render_s += drawing_s
                        if record:
                            recorded.append((local, frames))
                    elif order.seeds is not None:
                        seed = int(order.seeds[i])
                        self._reset_env(local, 0, None if seed < 0 else seed, True, order.options)
                    else:
                        assert order.state_ids is not None
                        self._reset_env(local, int(order.state_ids[i]))
                except Exception as exc:  # noqa: BLE001 - the env's own exception goes back to its caller
                    self._out["flags"][local] = 0.0
                    self._errors.append((local, type(exc).__name__, str(exc)))
                    continue
                touched.append(local)
        stepped = time.perf_counter()
        physics_s = stepped - started - render_s
        self._render(touched)
        render_s += time.perf_counter() - stepped
        renders = sum(len(frames) for _, frames in recorded) + (
            len(touched) if self._envs and self._envs[0].renderer else 0
        )
        return Reply(physics_s, render_s, renders, recorded, self._infos, self._errors)

    def env_attr(self, requests: dict[int, tuple[str, str, Any]]) -> list[tuple[int, bool, Any]]:
        """Run ``get``, ``call`` or ``set`` on this worker's envs named in ``requests`` (env index
        -> ``(op, name, payload)``); return ``(env index, ok, JSON result or error text)`` each.

        ``get``: the attribute; ``call``: the attribute called with ``payload`` ``(args, kwargs)``
        if callable, else the attribute; ``set``: ``payload`` replaces a JSON-valued attribute
        (an array one keeps its dtype and shape). A gym task's attributes are those of the env its
        id or factory returned (through that env's wrappers, none of vecsim's).
        """
        out: list[tuple[int, bool, Any]] = []
        for local, env_index in enumerate(self.worker.env_indices):
            if env_index not in requests:
                continue
            op, name, payload = requests[env_index]
            env = self._envs[local]
            target = env.served if isinstance(env, GymTaskEnv) else env
            try:
                out.append((env_index, True, _attr_op(target, op, name, payload)))
            except Exception as exc:  # noqa: BLE001 - the env's own exception goes back to its caller
                out.append((env_index, False, (type(exc).__name__, str(exc))))
        return out

    def _draw(self, local_indices: list[int]) -> dict[str, np.ndarray]:
        """Render every camera of the envs at ``local_indices`` in one batch; return
        ``{camera: uint8[len(local_indices), H, W, 3]}``."""
        # Every env of a worker renders at one size and preset, so they share one renderer.
        names = self._envs[0].image_names
        views = [self._envs[local].camera_views[camera] for camera in range(len(names)) for local in local_indices]
        frames = self._envs[0].renderer.render(views)
        return {
            name: frames[index * len(local_indices) : (index + 1) * len(local_indices)]
            for index, name in enumerate(names)
        }

    def _render(self, local_indices: list[int]) -> None:
        if not local_indices or self._envs[0].renderer is None:
            return
        images = self._out["obs"]["images"]
        for name, frames in self._draw(local_indices).items():
            images[name][local_indices] = frames

    def close(self) -> None:
        """Close every env of the worker. Returns None."""
        for env in self._envs:
            env.close()
        self._envs = []


def _index_tree(tree: Any, index: int) -> Any:
    if isinstance(tree, dict):
        return {key: _index_tree(sub, index) for key, sub in tree.items()}
    if isinstance(tree, tuple):
        return tuple(_index_tree(sub, index) for sub in tree)
    return tree[index]


def worker_process(
    index: int, spec: WorkerSpec, pipe: multiprocessing.connection.Connection, shared: Any, workers: int
) -> None:
    """A worker process: build a :class:`Worker` writing into its part of ``shared``, then answer
    orders until the pipe closes: a binary run order (:func:`~vecsim.engine.protocol.decode_run`) or an ``(order, args)``
    object, each with ``(True, result)``; a failure answers ``(False, (type name, message,
    traceback))`` and ends the process."""
    out = _index_tree(read_from_shared_memory(results_space(spec), shared, n=workers), index)
    worker = Worker(spec, out)
    try:
        while True:
            try:
                message = protocol.receive(pipe)
            except EOFError:
                return  # the pod closed its end
            if message[0] == protocol.RUN:
                pipe.send((True, worker.run(protocol.decode_run(message, spec.action_space))))
                continue
            if message[0] != protocol.PICKLED:
                raise RuntimeError(f"unknown message kind {message[0]!r}")
            order, args = pipe.recv()
            if order not in protocol.WORKER_ORDERS:
                raise RuntimeError(f"unknown order {order!r}")
            pipe.send((True, getattr(worker, order)(*args)))
    except KeyboardInterrupt:
        return
    except Exception as exc:  # noqa: BLE001 - the pod is told, then this process ends
        failure = (False, (type(exc).__name__, str(exc), traceback.format_exc()))
        with contextlib.suppress(OSError):
            pipe.send(failure)
    finally:
        worker.close()
