"""A pod's engine: task-grouped envs in worker processes, stepped and reset by env index.

:class:`TaskGroupedVectorEnv` runs the envs of one :class:`~vecsim.config.Assignment` as contiguous
blocks, one per task, in a pool of worker processes of its own (:class:`_WorkerPool`,
``forkserver`` processes: the default fork context hangs once the parent holds an EGL context).
A worker hosts ``envs_per_worker`` consecutive env indices, whatever their tasks: a run of envs
may cross from one task block into the next, each env built for its own task (the last worker
may host fewer; ``envs_per_worker`` 0 lets the pod pick, :func:`resolve_envs_per_worker`). An
env's *local index* is its place among its worker's envs (env index ``w * envs_per_worker + i``
is local index ``i`` of worker ``w``); a ``run`` order and its reply name envs by local index.

The worker protocol is explicit, one pipe per worker (nothing from the network is unpickled):
the pod sends an order and the worker answers with its result, or with its failure
``(type name, message, traceback)`` and exits. Orders: ``build`` (make the envs, each in state 0),
``run`` (one :class:`_Order`: reset these envs (by local index) to these state ids, reset them by the env's own
``reset(seed=..., options=...)`` (seed -1: None), or step them through a chunk of K actions each,
recording the frames of some), ``env_attr`` (get, call or set attributes of named envs). A
``run`` travels as a small binary message (local indices, then state ids, seeds or the actions in the
action space's dtype: :func:`_encode_run`); the other orders (``build``, ``env_attr``, a seeded
reset with options) as a one-byte message saying that an object follows, then the object; every
reply is one object. Objects are multiprocessing's own pickled messages (``Connection.send``,
``recv``) between the pod and its own processes: vecsim's code unpickles nothing itself. One
exchange is in flight on a pipe at a time. A call sends an order only to the workers that
host an env it names; the others hear nothing, and the call waits for those it messaged alone
(up to the step timeout: a hung worker is found when it has work, a dead one on any call, since
every call first and last polls every worker's pipe and process, one ``poll`` for all).

Observations and per-env, per-action result rows (reward, terminated, truncated, success) are
written by each worker straight into one shared-memory block (``[workers, local index, ...]``,
:func:`_results_space`); the pod copies out the named envs' entries. A step applies each env's
chunk (``[envs, K, ...]``, K from 1 to ``max_chunk``) in order and stops an env at its first
termination or truncation. The pipe's reply (:class:`_Reply`) carries what is small or ragged:
the worker's physics and render seconds (``last_timing``), an env's own ``info`` (beyond
vecsim's keys), the exceptions envs raised (the env that raised is named in the answer and every
other env of the call goes on: :class:`EnvError`), and recorded frames. Camera images are
rendered once, after every order of a call has run (after an env's last applied action), for
exactly the envs reset or stepped, all their cameras in one batch of this worker's renderer
(:mod:`vecsim.engine.batch_render`: one GL context per worker; envs of one scene share a render context,
and each scene's views are read back at once). An env whose frames are recorded is also rendered
after each of its other applied actions; those frames travel back through the pipe.

Once its envs are built, a worker frees what MuJoCo's XML compiler keeps for the life of the
process (the last model's parsed spec and the asset cache): for a LIBERO scene that is ~950 MB of
a worker's ~2.4 GB, paid once per process however many envs it then builds (``docs/pod.md``).

Every argument is validated before any worker is touched, so a rejected call changes nothing.
Module-level code imports nothing heavy and starts nothing: it is safe under ``forkserver``.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import dataclasses
import glob
import itertools
import json
import keyword
import logging
import math
import multiprocessing
import multiprocessing.connection
import os
import select
import struct
import threading
import time
import traceback
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
from gymnasium.vector.utils import batch_space, create_empty_array, create_shared_memory, read_from_shared_memory

from vecsim import wire
from vecsim.config import AUTO_ENVS_PER_WORKER, Assignment, CameraConfig, LiberoProtocol, RenderPreset
from vecsim.engine.tasks import TaskEnv, episode_limit, get_task, make_env, task_spaces
from vecsim.engine.tasks._gym import VECSIM_INFO_KEYS, GymTaskEnv

log = logging.getLogger("vecsim.engine.sim")

_MAX_STATE_ID = 2**31 - 1
_MAX_SEED = 2**63 - 1
# What get_attr / call / set_attr may name: public attributes; close stays the pod's to call.
_REFUSED_ATTRS = frozenset({"close", "reset", "step", "unwrapped", "np_random"})
# Private names served all the same (get and call): TimeLimit's limit, which gymnasium's own
# code and trainers' eval loops (LeRobot's rollout) read by this name.
_SERVED_PRIVATE_ATTRS = frozenset({"_max_episode_steps"})
# Columns of a worker's per-env, per-action result rows.
_REWARD, _TERMINATED, _TRUNCATED, _SUCCESS = 0, 1, 2, 3
# The longest chunk a pod takes by default: the chunk axis of a worker's shared result rows.
DEFAULT_MAX_CHUNK = 64
_PROGRESS_EVERY_S = 10.0


class UnknownEnvError(LookupError):
    """An env index this pod does not have (HTTP 404)."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


class InvalidRequestError(ValueError):
    """A request that cannot be served as given: shape, dtype, value or length (HTTP 422)."""


class SimCrashedError(RuntimeError):
    """A worker process died, hung or failed; the envs must be rebuilt (pod not ready)."""


class SimBuildError(RuntimeError):
    """Building the envs failed; the message names the task and what went wrong."""


@dataclass(frozen=True)
class EnvError:
    """An exception an env raised in a reset, step or attribute call: ``row`` of the answer (the
    env ``env_indices[row]``), the exception's type name and its message. The env stays as the
    exception left it; the pod's other envs are not touched."""

    row: int
    type_name: str
    message: str


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
class _WorkerSpec:
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


def _gather(tree: Any, workers: np.ndarray, local_indices: np.ndarray) -> Any:
    # Fancy indexing copies, so results never alias the shared memory the next call overwrites.
    if isinstance(tree, dict):
        return {key: _gather(sub, workers, local_indices) for key, sub in tree.items()}
    if isinstance(tree, tuple):
        return tuple(_gather(sub, workers, local_indices) for sub in tree)
    return tree[workers, local_indices]


def _own_info(info: dict[str, Any]) -> dict[str, Any]:
    """An env's info without vecsim's own keys (those travel as flags)."""
    return {key: value for key, value in info.items() if key not in VECSIM_INFO_KEYS}


def _jsonable(value: Any, what: str) -> Any:
    """``value`` as plain JSON data, or ValueError saying it cannot travel."""
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


def _results_space(worker: _WorkerSpec) -> gymnasium.spaces.Dict:
    """One worker's part of the shared memory: its envs' observations and result rows, by local index."""
    return gymnasium.spaces.Dict(
        {
            "obs": batch_space(worker.observation_space, worker.envs_per_worker),
            # Per env and chunk action: reward, terminated, truncated, success (zeros after the
            # action an env stopped at).
            "flags": gymnasium.spaces.Box(-np.inf, np.inf, (worker.envs_per_worker, worker.max_chunk, 4), np.float64),
        }
    )


@dataclass(frozen=True)
class _Order:
    """Work for one worker in one call: its envs at ``local_indices`` (in that order), each reset
    to a fixed state (``state_ids``), reset by the env's own ``reset(seed, options)`` (``seeds``,
    -1 for None), or stepped through a chunk of actions (``actions`` ``[m, K, ...]``, ``record``
    the envs whose every frame is kept; ``past_end``: apply every action, also after the env
    terminated or truncated). Exactly one of ``state_ids``, ``seeds``, ``actions``."""

    local_indices: np.ndarray
    state_ids: np.ndarray | None = None
    seeds: np.ndarray | None = None
    options: dict[str, Any] | None = None
    actions: np.ndarray | None = None
    record: np.ndarray | None = None
    past_end: bool = False


@dataclass(frozen=True)
class _Reply:
    """A worker's answer to its orders of one call (observations and result rows are in shared
    memory): seconds in physics and in rendering and the env renders made; the frames of recorded
    envs before their last action ``[(local index, [{camera: image}, ...])]``; each env's own info
    ``[(local index, info)]``; the exceptions envs raised ``[(local index, type name, message)]``."""

    physics_s: float
    render_s: float
    renders: int
    frames: list[tuple[int, list[dict[str, np.ndarray]]]]
    env_info: list[tuple[int, dict[str, Any]]]
    errors: list[tuple[int, str, str]]


class _Worker:
    """The envs one worker process hosts (a run of envs, of one task or several), run by orders.

    ``out`` is where observations and result rows go (:func:`_results_space`): this worker's part
    of the pod's shared memory in a worker process, plain arrays when made in process (tests).
    :meth:`build` makes the envs and puts each in state 0.
    """

    def __init__(self, worker: _WorkerSpec, out: dict[str, Any] | None = None) -> None:
        self.worker = worker
        self._envs: list[TaskEnv] = []
        self._out: dict[str, Any] = _zeros(_results_space(worker)) if out is None else out
        # Per call: each env's own info and the exceptions envs raised, by local index.
        self._infos: list[tuple[int, dict[str, Any]]] = []
        self._errors: list[tuple[int, str, str]] = []

    def build(self) -> dict[str, float]:
        """Make this worker's envs, reset each to state 0, warm the step path and render them, so
        that the first step a trainer sends costs what later ones do.

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
            for local in range(len(self._envs)):
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
        """Step the first env on the ``exact`` step path once and put it back in state 0: its
        compiled controller is compiled (a fresh checkout: seconds) or loaded from numba's cache
        here, not on the trainer's first step. The reset restores state 0 whole, so the env is
        as the build left it. Returns the env's local index, or -1 when no env takes that path."""
        for local, env in enumerate(self._envs):
            if getattr(env, "step_path", None) == "exact":
                env.step(np.zeros(env.action_space.shape, env.action_space.dtype))
                self._reset_env(local, 0)
                return local
        return -1

    def _reset_env(
        self, local: int, state_id: int, seed: int | None = None, seeded: bool = False, options: dict[str, Any] | None = None
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
        self._out["flags"][local, 0, _SUCCESS] = info["success"]
        self._keep_info(local, info)

    def _keep_info(self, local: int, info: dict[str, Any]) -> None:
        own = _own_info(info)
        if own:
            self._infos.append((local, own))

    def _step_env(
        self, local: int, chunk: np.ndarray, record: bool, past_end: bool = False
    ) -> tuple[list[dict[str, np.ndarray]], float]:
        """Apply ``chunk``'s actions to one env until it terminates or truncates (``past_end``: all
        of them, as LIBERO's and the trainers' own envs are stepped on); return the frames
        recorded after each applied action but the last, and the seconds spent drawing them."""
        env = self._envs[local]
        rows = self._out["flags"][local]
        rows[:] = 0.0
        frames: list[dict[str, np.ndarray]] = []
        render_s = 0.0
        observation = None
        info: dict[str, Any] = {}
        for k, action in enumerate(chunk):
            observation, reward, terminated, truncated, info = env.step(action)
            rows[k] = (reward, terminated, truncated, info["success"])
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

    def run(self, *orders: _Order) -> _Reply:
        """Carry out ``orders`` (each env's reset or chunk step, in order), then render the
        cameras of every env reset or stepped, once, in one batch; return the :class:`_Reply`.

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
        renders = sum(len(frames) for _, frames in recorded) + (len(touched) if self._envs and self._envs[0].renderer else 0)
        return _Reply(physics_s, render_s, renders, recorded, self._infos, self._errors)

    def env_attr(self, requests: dict[int, tuple[str, str, Any]]) -> list[tuple[int, bool, Any]]:
        """Run ``get``, ``call`` or ``set`` on this worker's envs named in ``requests`` (env index
        -> ``(op, name, payload)``); return ``(env index, ok, JSON result or error text)`` each.

        ``get``: the attribute; ``call``: the attribute called with ``payload`` ``(args, kwargs)``
        if callable, else the attribute; ``set``: ``payload`` replaces a JSON-valued attribute
        (an array one keeps its dtype and shape). A gym task's attributes are its gymnasium env's
        (through its wrappers).
        """
        out: list[tuple[int, bool, Any]] = []
        for local, env_index in enumerate(self.worker.env_indices):
            if env_index not in requests:
                continue
            op, name, payload = requests[env_index]
            env = self._envs[local]
            target = env.inner if isinstance(env, GymTaskEnv) else env
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
        return {name: frames[index * len(local_indices) : (index + 1) * len(local_indices)] for index, name in enumerate(names)}

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


# What a worker process is asked to do: a _Worker method, with its arguments.
_WORKER_ORDERS = frozenset({"build", "run", "env_attr"})

# An order to a worker is one multiprocessing frame (``Connection.send_bytes``) whose first byte
# says what it is: a binary run order, or _PICKLED, "an object follows": the next message is
# multiprocessing's own pickled ``(order, args)`` (``Connection.send``/``recv``). A worker's reply
# is always such an object, ``(ok, result)``. vecsim's code unpickles nothing itself; these are
# the pod's own processes, as with any multiprocessing pipe. One exchange (an order, then its
# reply) is in flight on a pipe at a time.
_PICKLED = ord("p")
# A run order in binary: _RUN_HEAD (tag, kind, whether frames are recorded, m envs, chunk K),
# their local indices int64[m], then for _STEP the actions [m, K, *action shape] in the action space's
# dtype and, when recorded, bool[m]; for _STATE the state ids int64[m]; for _SEED the seeds
# int64[m] (-1: None). Every field at an offset its dtype's size divides.
_RUN = ord("r")
_RUN_HEAD = struct.Struct("<BBBxIQ")
_STEP, _STATE, _SEED = 0, 1, 2


def _send(pipe: multiprocessing.connection.Connection, *parts: bytes) -> None:
    """Send one message, ``parts`` joined, as one frame of ``pipe``."""
    pipe.send_bytes(b"".join(parts))


def _receive(pipe: multiprocessing.connection.Connection) -> bytearray:
    """Receive one message from ``pipe``, writable (so arrays decoded from it are too).

    Raises:
        EOFError: the other end closed the pipe before a message began.
        OSError: the pipe closed inside a message.
    """
    return bytearray(pipe.recv_bytes())


def _encode_run(order: _Order) -> bytes | None:
    """``order`` as a binary run message, or None for a seeded reset with options (pickled)."""
    local = np.ascontiguousarray(order.local_indices, dtype=np.int64).tobytes()
    m = len(order.local_indices)
    if order.actions is not None:
        k = order.actions.shape[1]
        # The flags byte: bit 0 a record mask follows, bit 1 step past each env's end.
        flags = int(order.record is not None) | (int(order.past_end) << 1)
        head = _RUN_HEAD.pack(_RUN, _STEP, flags, m, k)
        parts = [head, local, np.ascontiguousarray(order.actions).tobytes()]
        if order.record is not None:
            parts.append(np.ascontiguousarray(order.record, dtype=bool).tobytes())
        return b"".join(parts)
    if order.seeds is not None:
        if order.options is not None:
            return None
        values = order.seeds
        head = _RUN_HEAD.pack(_RUN, _SEED, False, m, 0)
    else:
        assert order.state_ids is not None
        values = order.state_ids
        head = _RUN_HEAD.pack(_RUN, _STATE, False, m, 0)
    return b"".join((head, local, np.ascontiguousarray(values, dtype=np.int64).tobytes()))


def _decode_run(message: bytearray, action_space: gymnasium.Space) -> _Order:
    """The :class:`_Order` of a binary run message (:func:`_encode_run`); arrays are views of it."""
    _tag, kind, record, m, k = _RUN_HEAD.unpack_from(message)
    offset = _RUN_HEAD.size
    local = np.frombuffer(message, np.int64, m, offset)
    offset += local.nbytes
    if kind == _STEP:
        shape = (m, k, *action_space.shape)
        actions = np.frombuffer(message, action_space.dtype, math.prod(shape), offset).reshape(shape)
        offset += actions.nbytes
        recorded = np.frombuffer(message, bool, m, offset) if record & 1 else None
        return _Order(local, actions=actions, record=recorded, past_end=bool(record & 2))
    values = np.frombuffer(message, np.int64, m, offset)
    return _Order(local, seeds=values) if kind == _SEED else _Order(local, state_ids=values)


def _index_tree(tree: Any, index: int) -> Any:
    if isinstance(tree, dict):
        return {key: _index_tree(sub, index) for key, sub in tree.items()}
    if isinstance(tree, tuple):
        return tuple(_index_tree(sub, index) for sub in tree)
    return tree[index]


def _send_object(pipe: multiprocessing.connection.Connection, obj: Any) -> None:
    """Send ``obj`` through multiprocessing's own pickled message, announced by a ``_PICKLED`` one."""
    _send(pipe, bytes((_PICKLED,)))
    pipe.send(obj)


def _worker_process(index: int, spec: _WorkerSpec, pipe: multiprocessing.connection.Connection, shared: Any, workers: int) -> None:
    """A worker process: build a :class:`_Worker` writing into its part of ``shared``, then answer
    orders until the pipe closes: a binary run order (:func:`_decode_run`) or an ``(order, args)``
    object, each with ``(True, result)``; a failure answers ``(False, (type name, message,
    traceback))`` and ends the process."""
    out = _index_tree(read_from_shared_memory(_results_space(spec), shared, n=workers), index)
    worker = _Worker(spec, out)
    try:
        while True:
            try:
                message = _receive(pipe)
            except EOFError:
                return  # the pod closed its end
            if message[0] == _RUN:
                pipe.send((True, worker.run(_decode_run(message, spec.action_space))))
                continue
            if message[0] != _PICKLED:
                raise RuntimeError(f"unknown message kind {message[0]!r}")
            order, args = pipe.recv()
            if order not in _WORKER_ORDERS:
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


class _WorkerFailure(RuntimeError):
    """A worker process answered an order with an exception (it then exits)."""

    def __init__(self, worker: int, type_name: str, message: str) -> None:
        super().__init__(f"{type_name}: {message}")
        self.worker, self.type_name, self.message = worker, type_name, message


class _WorkerPool:
    """The pod's worker processes: one per :class:`_WorkerSpec`, each with its own pipe for
    orders and replies, and one shared-memory block of every worker's observations and result
    rows (``results``, ``[workers, local index, ...]``, :func:`_results_space`). Only workers sent an
    order are waited for."""

    def __init__(self, specs: Sequence[_WorkerSpec], context: str) -> None:
        ctx = multiprocessing.get_context(context)
        space = _results_space(specs[0])
        shared = create_shared_memory(space, n=len(specs), ctx=ctx)
        # Held for the pool's life: a worker process attaches to it after start() returns.
        self._shared = shared
        self.results: dict[str, Any] = read_from_shared_memory(space, shared, n=len(specs))
        self.pipes: list[multiprocessing.connection.Connection] = []
        self.processes: list[Any] = []
        for index, spec in enumerate(specs):
            parent, child = ctx.Pipe()
            process = ctx.Process(
                target=_worker_process,
                name=f"vecsim-worker-{index}",
                args=(index, spec, child, shared, len(specs)),
                daemon=True,
            )
            process.start()
            child.close()
            self.pipes.append(parent)
            self.processes.append(process)
        self._fds = [pipe.fileno() for pipe in self.pipes]
        self._worker_of = {fd: index for index, fd in enumerate(self._fds)}
        # Every worker's pipe and process sentinel, watched at once: one poll finds any that ended.
        self._ended = select.poll()
        for index, process in enumerate(self.processes):
            for fd in (self._fds[index], process.sentinel):
                self._ended.register(fd, select.POLLIN)
                self._worker_of[fd] = index

    def send(self, worker: int, order: str, *args: Any) -> None:
        """Send worker ``worker`` an order (a :class:`_Worker` method) and its arguments: a ``run``
        of one :class:`_Order` in binary where it can be (:func:`_encode_run`), else pickled."""
        message = _encode_run(args[0]) if order == "run" and len(args) == 1 else None
        if message is None:
            _send_object(self.pipes[worker], (order, args))
        else:
            _send(self.pipes[worker], message)

    def receive(self, workers: Sequence[int], timeout_s: float | None) -> dict[int, Any]:
        """Wait for the reply of each of ``workers``; return ``{worker: result}``.

        Raises:
            multiprocessing.TimeoutError: not every one answered within ``timeout_s``.
            _WorkerFailure: a worker answered with an exception.
            EOFError, OSError: a worker's pipe closed (it died).
        """
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        pending = {self._fds[worker]: worker for worker in workers}
        waiting = select.poll()
        for fd in pending:
            waiting.register(fd, select.POLLIN)
        replies: dict[int, Any] = {}
        while pending:
            wait_ms = None if deadline is None else max(math.ceil(1e3 * (deadline - time.monotonic())), 0)
            ready = waiting.poll(wait_ms)
            if not ready:
                raise multiprocessing.TimeoutError(f"{len(pending)} of {len(workers)} workers did not answer")
            for fd, _events in ready:
                worker = pending.pop(fd)
                waiting.unregister(fd)
                replies[worker] = self._decode_reply(worker, self.pipes[worker])
        return replies

    @staticmethod
    def _decode_reply(worker: int, pipe: multiprocessing.connection.Connection) -> Any:
        """Read a worker's reply (an object read by multiprocessing itself); return its result.
        Raises _WorkerFailure for a failure."""
        ok, result = pipe.recv()
        if not ok:
            type_name, text, trace = result
            log.error("worker %d failed:\n%s", worker, trace)
            raise _WorkerFailure(worker, type_name, text)
        return result

    def dead(self) -> int | None:
        """The first worker whose process has ended, or None (one poll of every pipe and process).

        Between calls no reply is due, so a worker's pipe that can be read is one that closed:
        the process has ended, seen before its parent learns its exit code."""
        ended = self._ended.poll(0)
        if not ended:
            return None
        return min(self._worker_of[fd] for fd, _events in ended)

    def close(self) -> None:
        """End every worker process (terminating cannot hang on a stuck one). Returns None."""
        for process in self.processes:
            if process.is_alive():
                process.terminate()
        for pipe in self.pipes:
            pipe.close()
        for process in self.processes:
            process.join()


def _empty_spaces() -> tuple[gymnasium.Space, gymnasium.Space]:
    return gymnasium.spaces.Dict({}), gymnasium.spaces.Box(-1.0, 1.0, (0,), np.float32)


def assignment_spaces(assignment: Assignment) -> tuple[gymnasium.Space, gymnasium.Space]:
    """Check that ``assignment`` can be built; return its ``(observation_space, action_space)``.

    Cheap (no env is built, except that a gym task's env is made to read its spaces), so a pod
    can answer a bad assignment at once. An assignment with no tasks has an empty Dict
    observation space and a zero-length action Box.

    Raises:
        UnknownTaskError: a task id no provider knows.
        TaskSetupError: a LIBERO task, and LIBERO is not installed or lacks its assets.
        InvalidRequestError: the tasks do not share one observation space and one action space.
        ValueError: a gym task with a space vecsim cannot serve (named).
    """
    first: tuple[str, gymnasium.Space, gymnasium.Space] | None = None
    for block in assignment.tasks:
        kwargs = assignment.make_kwargs.get(block.task_id)
        observation_space, action_space = task_spaces(block.task_id, assignment.camera, kwargs)
        if first is None:
            first = (block.task_id, observation_space, action_space)
        elif (observation_space, action_space) != first[1:]:
            raise InvalidRequestError(
                f"tasks: {block.task_id!r} and {first[0]!r} have different observation or action "
                "spaces; one pod's tasks must share them"
            )
    return _empty_spaces() if first is None else first[1:]


def available_cores() -> int:
    """Return how many cores this process may use: its CPU affinity, capped by a cgroup v2
    CPU quota (a Kubernetes CPU limit) when one is set. At least 1."""
    cores = len(os.sched_getaffinity(0))
    try:
        quota, period = Path("/sys/fs/cgroup/cpu.max").read_text().split()
        if quota != "max":
            cores = min(cores, math.ceil(int(quota) / int(period)))
    except (OSError, ValueError):
        pass
    return max(cores, 1)


def auto_envs_per_worker(block_sizes: Sequence[int], cores: int) -> int:
    """Return the fewest envs per worker that keep a pod's workers within ``cores``.

    A worker hosts consecutive envs whatever their tasks, so the blocks pack as one run:
    ``ceil(envs / cores)`` envs per worker, ``ceil(envs / that)`` workers (at most ``cores``).
    No envs at all: 1.
    """
    envs = sum(max(n, 0) for n in block_sizes)
    return max(1, math.ceil(envs / max(cores, 1)))


def resolve_envs_per_worker(assignment: Assignment, cores: int | None = None) -> int:
    """Return the envs per worker a pod runs ``assignment`` with.

    Its ``envs_per_worker``, or for 0 (auto) :func:`auto_envs_per_worker` over its task blocks and
    ``cores`` (default :func:`available_cores`): at most one worker per core, whatever the scenes.
    Cheap gym scenes gain most (a worker costs ~0.1 ms of pipe and shared-memory traffic per call,
    more than their physics); robot scenes with cameras step about as fast as with one env per
    worker (the cores are busy either way) in a fraction of the memory, since most of a worker's
    memory is paid once per process (``docs/pod.md``: a LIBERO worker ~1.2 GB, ~0.3 GB per env).
    """
    if assignment.envs_per_worker != AUTO_ENVS_PER_WORKER:
        return assignment.envs_per_worker
    return auto_envs_per_worker([b.num_envs for b in assignment.tasks], cores or available_cores())


@dataclass(frozen=True)
class CallTiming:
    """Worker seconds of one reset or step call, summed over the pod's workers: ``physics_s``
    in the scenes' resets and steps, ``render_s`` rendering their cameras; and ``renders``, how
    many env renders (all of one env's cameras drawn once) the call made."""

    physics_s: float = 0.0
    render_s: float = 0.0
    renders: int = 0


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


class TaskGroupedVectorEnv:
    """The envs of one assignment, in worker processes, addressed by env index.

    Env indices run ``0..num_envs-1`` in contiguous blocks, one per task block of the assignment;
    worker ``w`` hosts envs ``w * envs_per_worker`` onwards, across blocks. After construction every env is in state 0. Thread-safe: calls are serialised.
    ``last_timing`` (:class:`CallTiming`) tells where the workers spent the last call's time.

    Args:
        assignment: what to run (tasks and their env counts, camera, render preset,
            ``envs_per_worker`` (0: :func:`resolve_envs_per_worker` picks),
            ``max_episode_steps``).
        context: multiprocessing start method for the workers.
        timeout_s: longest wait for the workers on one reset or step; None waits forever.
        build_timeout_s: longest wait for the workers to build; None waits forever.
        max_chunk: the most actions per env one step call takes (:meth:`chunk_step_envs`).

    Raises:
        UnknownTaskError: a task id no provider knows.
        TaskSetupError: a LIBERO task, and LIBERO is not installed or lacks its assets.
        InvalidRequestError: the tasks do not share their spaces.
        SimBuildError: a worker failed to build its envs (the message names the task).
    """

    def __init__(
        self,
        assignment: Assignment,
        *,
        context: str = "forkserver",
        timeout_s: float | None = None,
        build_timeout_s: float | None = None,
        max_chunk: int = DEFAULT_MAX_CHUNK,
    ) -> None:
        if max_chunk < 1:
            raise ValueError(f"max_chunk: must be at least 1, got {max_chunk}")
        self.assignment = assignment
        self.max_chunk = max_chunk
        self.single_observation_space, self.single_action_space = assignment_spaces(assignment)
        self.num_envs = assignment.num_envs
        self.task_ids: list[str] = []
        self._num_states = np.zeros(self.num_envs, dtype=np.int64)
        self._timeout_s = timeout_s
        self._lock = threading.Lock()
        self._broken: str | None = None
        self._closed = False
        self._pool: _WorkerPool | None = None
        self.last_timing = CallTiming()

        per_worker = self.envs_per_worker = resolve_envs_per_worker(assignment)
        for block in assignment.tasks:
            task = get_task(block.task_id)
            self.task_ids += [task.task_id] * block.num_envs
            self._num_states[block.env_start : block.env_start + block.num_envs] = task.num_states
        # Worker w hosts envs w*per_worker ... (w+1)*per_worker - 1, across task boundaries.
        self._workers = [
            _WorkerSpec(
                task_ids=tuple(self.task_ids[first : first + per_worker]),
                env_indices=tuple(range(first, min(first + per_worker, self.num_envs))),
                envs_per_worker=per_worker,
                camera=assignment.camera,
                render=assignment.render,
                max_episode_steps=assignment.max_episode_steps,
                observation_space=self.single_observation_space,
                action_space=self.single_action_space,
                max_chunk=max_chunk,
                libero=assignment.libero,
                make_kwargs=assignment.make_kwargs,
            )
            for first in range(0, self.num_envs, per_worker)
        ]
        envs = np.arange(self.num_envs, dtype=np.int64)
        self._location = np.stack(divmod(envs, per_worker), axis=1).reshape(-1, 2)
        if self._workers:
            self._start(context, build_timeout_s)

    @property
    def num_workers(self) -> int:
        """Number of worker processes (0 for a spare pod)."""
        return len(self._workers)

    @property
    def worker_pids(self) -> list[int]:
        """Process ids of the workers, in worker order."""
        return [] if self._pool is None else [process.pid for process in self._pool.processes]

    def _start(self, context: str, build_timeout_s: float | None) -> None:
        counts = Counter(self.task_ids)
        log.info(
            "building %d envs (%s) in %d worker processes, %d envs per worker",
            self.num_envs,
            ", ".join(f"{task} x{n}" for task, n in counts.items()),
            len(self._workers),
            self.envs_per_worker,
        )
        started = time.monotonic()
        self._pool = _WorkerPool(self._workers, context)
        try:
            for worker in range(len(self._workers)):
                self._pool.send(worker, "build")
            self._wait_for_build(started, build_timeout_s)
        except SimBuildError:
            self._pool.close()
            raise
        except _WorkerFailure as exc:
            self._pool.close()
            if exc.type_name == SimBuildError.__name__:
                raise SimBuildError(exc.message) from None
            raise SimBuildError(f"building envs failed: {exc}") from None
        except Exception as exc:
            self._pool.close()
            raise SimBuildError(f"building envs failed: {type(exc).__name__}: {exc}") from exc
        log.info("built %d envs in %.1f s", self.num_envs, time.monotonic() - started)

    def _wait_for_build(self, started: float, build_timeout_s: float | None) -> None:
        assert self._pool is not None
        pipes = {pipe: index for index, pipe in enumerate(self._pool.pipes)}
        pending = set(pipes)
        last_report = started
        while pending:
            elapsed = time.monotonic() - started
            if build_timeout_s is not None and elapsed > build_timeout_s:
                raise SimBuildError(
                    f"building envs took over {build_timeout_s} s; "
                    f"{len(pipes) - len(pending)} of {len(pipes)} workers were ready"
                )
            wait_s = _PROGRESS_EVERY_S
            if build_timeout_s is not None:
                wait_s = min(wait_s, max(build_timeout_s - elapsed, 0.0))
            for pipe in multiprocessing.connection.wait(list(pending), timeout=wait_s):
                pending.discard(pipe)
                index = pipes[pipe]
                took = self._pool.receive([index], timeout_s=None)[index]
                log.info(
                    "worker %d/%d ready: %s (%.1f s: made %.1f s, reset %.1f s, step path warmed %.1f s, rendered %.1f s)",
                    index + 1,
                    len(pipes),
                    self._workers[index].describe(),
                    time.monotonic() - started,
                    took["make"],
                    took["reset"],
                    took["warm"],
                    took["render"],
                )
            if pending and time.monotonic() - last_report >= _PROGRESS_EVERY_S:
                last_report = time.monotonic()
                log.info(
                    "still building: %d of %d workers ready after %.0f s",
                    len(pipes) - len(pending),
                    len(pipes),
                    last_report - started,
                )

    # Validation: everything is checked before any worker is touched.

    def _env_indices(self, env_indices: Any) -> np.ndarray:
        ids = _int_array("env_indices", env_indices)
        if ids.size:
            bad = ids[(ids < 0) | (ids >= self.num_envs)]
            if bad.size:
                have = f"envs 0..{self.num_envs - 1}" if self.num_envs else "no envs"
                raise UnknownEnvError(f"env_indices: env {int(bad[0])} does not exist; this pod has {have}")
            values, counts = np.unique(ids, return_counts=True)
            if (counts > 1).any():
                twice = int(values[counts > 1][0])
                raise InvalidRequestError(f"env_indices: env {twice} is named more than once")
        return ids.astype(np.int64)

    def _state_ids(self, state_ids: Any, ids: np.ndarray) -> np.ndarray:
        states = _int_array("state_ids", state_ids)
        if states.size != ids.size:
            raise InvalidRequestError(f"state_ids: {states.size} state ids for {ids.size} env_indices")
        if ids.size:
            limits = self._num_states[ids]
            bad = np.flatnonzero((states < 0) | (states >= limits))
            if bad.size:
                i = int(bad[0])
                env = int(ids[i])
                raise InvalidRequestError(
                    f"state_ids: state {int(states[i])} for env {env} is out of range "
                    f"0..{int(limits[i]) - 1} of task {self.task_ids[env]!r}"
                )
        return states.astype(np.int64)

    def _actions(self, actions: Any, ids: np.ndarray) -> np.ndarray:
        """Return ``actions`` (one per env, ``[n, *action shape]``) as a chunk of one per env."""
        space = self.single_action_space
        values = self._numbers(actions)
        if ids.size == 0 and values.size == 0:
            return np.zeros((0, 1, *space.shape), dtype=space.dtype)
        expected = (ids.size, *space.shape)
        if values.shape != expected:
            raise InvalidRequestError(f"actions: expected shape {expected}, got {values.shape}")
        return self._finite(values[:, None], ids)

    def _chunk(self, actions: Any, ids: np.ndarray) -> np.ndarray:
        """Return ``actions`` (``[n, K, *action shape]``, K from 0 to ``max_chunk``) checked."""
        space = self.single_action_space
        if not isinstance(space, gymnasium.spaces.Box):
            raise InvalidRequestError(
                f"actions: chunks of actions are for Box action spaces; this pod's is {type(space).__name__}: "
                "send one action per env"
            )
        values = self._numbers(actions)
        if ids.size == 0 and values.size == 0 and values.ndim != 2 + len(space.shape):
            return np.zeros((0, 0, *space.shape), dtype=space.dtype)
        if values.ndim != 2 + len(space.shape) or values.shape[0] != ids.size or values.shape[2:] != space.shape:
            expected = f"({ids.size}, K, {', '.join(map(str, space.shape))})"
            raise InvalidRequestError(f"actions: expected a chunk of shape {expected}, got {values.shape}")
        if values.shape[1] > self.max_chunk:
            raise InvalidRequestError(
                f"actions: a chunk of {values.shape[1]} actions per env exceeds this pod's limit of {self.max_chunk}"
            )
        return self._finite(values, ids)

    def _numbers(self, actions: Any) -> np.ndarray:
        try:
            values = np.asarray(actions)
        except ValueError as exc:
            raise InvalidRequestError(f"actions: not a rectangular array: {exc}") from None
        if values.size and values.dtype.kind not in "fiu":
            raise InvalidRequestError(f"actions: expected numbers, got dtype {values.dtype}")
        return values

    def _finite(self, chunk: np.ndarray, ids: np.ndarray) -> np.ndarray:
        space = self.single_action_space
        if np.dtype(space.dtype).kind != "f":
            return self._in_range(chunk, ids)
        cast = chunk.astype(space.dtype)
        finite = np.isfinite(cast.reshape(*cast.shape[:2], math.prod(cast.shape[2:]))).all(axis=2)
        if not finite.all():
            row, k = (int(i[0]) for i in np.nonzero(~finite))
            where = f"action {k} of the chunk" if chunk.shape[1] > 1 else "the action"
            raise InvalidRequestError(
                f"actions: {where} for env {int(ids[row])} is not finite (NaN, inf or too large)"
            )
        return cast

    def _in_range(self, chunk: np.ndarray, ids: np.ndarray) -> np.ndarray:
        """``chunk`` in the integer action space's dtype, each action a member of the space."""
        space = self.single_action_space
        flat = chunk.reshape(*chunk.shape[:2], -1)
        if chunk.dtype.kind == "f" and not (np.isfinite(flat) & (flat == np.round(flat))).all():
            bad = int(np.nonzero(~(np.isfinite(flat) & (flat == np.round(flat))).all(axis=2))[0][0])
            raise InvalidRequestError(f"actions: the action for env {int(ids[bad])} is not a whole number")
        if isinstance(space, gymnasium.spaces.Discrete):
            low, high = np.int64(space.start), np.int64(space.start + space.n - 1)
        elif isinstance(space, gymnasium.spaces.MultiDiscrete):
            low, high = space.start.reshape(-1), (space.start + space.nvec - 1).reshape(-1)
        elif isinstance(space, gymnasium.spaces.MultiBinary):
            low, high = 0, 1
        else:
            low, high = space.low.reshape(-1), space.high.reshape(-1)
        inside = ((flat >= low) & (flat <= high)).all(axis=2)
        if not inside.all():
            row = int(np.nonzero(~inside)[0][0])
            raise InvalidRequestError(
                f"actions: the action {flat[row, 0].tolist()} for env {int(ids[row])} is not in the action space {space}"
            )
        return chunk.astype(space.dtype)

    def _record(self, record_env_indices: Any, ids: np.ndarray) -> np.ndarray:
        """Return the rows of ``ids`` that ``record_env_indices`` names, in its order."""
        record = _int_array("record_env_indices", record_env_indices)
        if record.size == 0:
            return np.zeros(0, dtype=np.int64)
        values, counts = np.unique(record, return_counts=True)
        if (counts > 1).any():
            raise InvalidRequestError(f"record_env_indices: env {int(values[counts > 1][0])} is named more than once")
        rows = {int(env): row for row, env in enumerate(ids)}
        missing = [int(env) for env in record if int(env) not in rows]
        if missing:
            raise InvalidRequestError(f"record_env_indices: env {missing[0]} is not one of the env_indices stepped")
        return np.array([rows[int(env)] for env in record], dtype=np.int64)

    # Calls.

    def reset_envs(
        self, env_indices: Any, state_ids: Any = None, *, seeds: Any = None, options: dict[str, Any] | None = None
    ) -> tuple[Any, dict[str, Any]]:
        """Reset the named envs; no other env changes.

        With ``state_ids``, each to the named fixed initial state; with ``seeds`` (one int or
        None per env) instead, as the env's own ``reset(seed=seeds[i], options=options)``.

        Returns:
            ``(obs, info)``: ``obs`` batched over the named envs in the given order, ``info``
            ``{"success": bool[n], "task_id": list[str], "env_info": list[dict], "errors":
            list[EnvError]}``. Empty ``env_indices``: empty results.

        Raises:
            UnknownEnvError: an env index out of range.
            InvalidRequestError: duplicate env ids, non-integer ids, lengths that differ, a
                state id out of its task's range, a seed that is not a non-negative int or None,
                or both or neither of ``state_ids`` and ``seeds``.
            SimCrashedError: a worker died, hung or failed (the pod must rebuild).
        """
        ids = self._env_indices(env_indices)
        if (state_ids is None) == (seeds is None):
            raise InvalidRequestError("give either state_ids (fixed initial states) or seeds (the envs' own reset)")
        if seeds is None:
            states = self._state_ids(state_ids, ids)
            if options:
                raise InvalidRequestError("options: go with seeds (the envs' own reset), not with state_ids")
        else:
            seed_values = self._seeds(seeds, ids)
        if ids.size == 0:
            return self._empty_obs(), {"success": np.zeros(0, dtype=bool), "task_id": [], "env_info": [], "errors": []}
        workers, local_indices = self._location[ids].T
        orders = {}
        for worker, rows in self._by_worker(workers, local_indices):
            if seeds is None:
                orders[worker] = _Order(local_indices[rows], state_ids=states[rows])
            else:
                orders[worker] = _Order(local_indices[rows], seeds=seed_values[rows], options=options)
        obs, rows, replies = self._run(orders, workers, local_indices)
        env_info, errors = self._per_row(replies, ids)
        return obs, {
            "success": rows[:, 0, _SUCCESS] != 0,
            "task_id": [self.task_ids[i] for i in ids],
            "env_info": env_info,
            "errors": errors,
        }

    def _seeds(self, seeds: Any, ids: np.ndarray) -> np.ndarray:
        """``seeds`` (a list of non-negative ints or None, one per env) as int64, None as -1."""
        if not isinstance(seeds, (list, tuple, np.ndarray)):
            raise InvalidRequestError(f"seeds: expected a list of ints or nulls, got {type(seeds).__name__}")
        if len(seeds) != ids.size:
            raise InvalidRequestError(f"seeds: {len(seeds)} seeds for {ids.size} env_indices")
        out = np.full(ids.size, -1, dtype=np.int64)
        for i, seed in enumerate(seeds):
            if seed is None:
                continue
            if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer)):
                raise InvalidRequestError(f"seeds: seed {i} is {seed!r:.50}, not an int or null")
            if not 0 <= int(seed) <= _MAX_SEED:
                raise InvalidRequestError(f"seeds: seed {i} ({seed}) is outside 0..{_MAX_SEED}")
            out[i] = int(seed)
        return out

    def _per_row(self, replies: dict[int, _Reply], ids: np.ndarray) -> tuple[list[dict[str, Any]], list[EnvError]]:
        """Each row's own env info and the rows whose env raised, from the workers' replies."""
        env_info: list[dict[str, Any]] = [{} for _ in range(ids.size)]
        errors: list[EnvError] = []
        if not any(reply.env_info or reply.errors for reply in replies.values()):
            return env_info, errors
        # Worker w's local index i is env w * envs_per_worker + i.
        row_of = {env: row for row, env in enumerate(ids.tolist())}
        for worker, reply in replies.items():
            first = worker * self.envs_per_worker
            for local, own in reply.env_info:
                env_info[row_of[first + local]] = own
            for local, type_name, message in reply.errors:
                errors.append(EnvError(row_of[first + local], type_name, message))
        errors.sort(key=lambda e: e.row)
        for error in errors:
            log.info("env %d (%s) raised %s: %s", int(ids[error.row]), self.task_ids[int(ids[error.row])], error.type_name, error.message)
        return env_info, errors

    def step_envs(
        self, env_indices: Any, actions: Any
    ) -> tuple[dict[str, Any], np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Step the named envs one control step each; no other env advances.

        Returns:
            ``(obs, reward float64[n], terminated bool[n], truncated bool[n], {"success": bool[n],
            "env_info", "errors"})`` over the named envs in the given order (``env_info`` and
            ``errors`` as in :class:`ChunkResult`). Empty ``env_indices``: empty results.

        Raises:
            UnknownEnvError: an env index out of range.
            InvalidRequestError: duplicate env ids, non-integer ids, actions of the wrong shape or
                dtype, or a NaN or infinite action.
            SimCrashedError: a worker died, hung or failed (the pod must rebuild).
        """
        ids = self._env_indices(env_indices)
        result = self._step_chunks(ids, self._actions(actions, ids), np.zeros(0, dtype=np.int64))
        return (
            result.obs,
            result.reward[:, 0],
            result.terminated[:, 0],
            result.truncated[:, 0],
            {"success": result.success[:, 0], "env_info": result.env_info, "errors": result.errors},
        )

    def chunk_step_envs(
        self, env_indices: Any, actions: Any, record_env_indices: Any = (), step_past_end: bool = False
    ) -> ChunkResult:
        """Apply a chunk of K actions to each named env, in order; no other env advances.

        Env ``env_indices[i]`` takes ``actions[i, 0]``, ``actions[i, 1]``, ... and stops at its first
        termination or truncation (its later actions are not applied), or with ``step_past_end``
        applies all K (an ended env is stepped on: physics go on, its flags and reward are what
        the scene computes, its episode limit keeps counting; ``num_steps`` is K). Cameras are rendered once
        per env, after its last applied action; the envs in ``record_env_indices`` (a subset of
        ``env_indices``) are also rendered after each of their other applied actions. K = 0 moves
        nothing and answers the envs' current observations.

        Returns:
            :class:`ChunkResult` over the named envs in the given order. Empty ``env_indices``: empty
            results.

        Raises:
            UnknownEnvError: an env index out of range.
            InvalidRequestError: duplicate env ids, non-integer ids, a chunk of the wrong shape or
                dtype or longer than ``max_chunk``, a NaN or infinite action (the message names
                the env and the chunk index), or ``record_env_indices`` not among ``env_indices``.
            SimCrashedError: a worker died, hung or failed (the pod must rebuild).
        """
        ids = self._env_indices(env_indices)
        chunk = self._chunk(actions, ids)
        return self._step_chunks(ids, chunk, self._record(record_env_indices, ids), bool(step_past_end))

    def _step_chunks(
        self, ids: np.ndarray, chunk: np.ndarray, recorded: np.ndarray, past_end: bool = False
    ) -> ChunkResult:
        n, k = chunk.shape[:2]
        workers, local_indices = self._location[ids].T
        if n == 0 or k == 0:
            obs = self._empty_obs() if n == 0 else self._current(workers, local_indices)
            result = self._result(obs, np.zeros((n, k, 4)), recorded, past_end)
            return dataclasses.replace(result, env_info=[{} for _ in range(n)])
        record = np.zeros(n, dtype=bool)
        record[recorded] = True
        orders = {
            worker: _Order(
                local_indices[rows], actions=chunk[rows], record=record[rows] if recorded.size else None, past_end=past_end
            )
            for worker, rows in self._by_worker(workers, local_indices)
        }
        obs, rows, replies = self._run(orders, workers, local_indices)
        env_info, errors = self._per_row(replies, ids)
        result = dataclasses.replace(
            self._result(obs, rows[:, :k], recorded, past_end), env_info=env_info, errors=errors
        )
        drawn = {(worker, local): frames for worker, reply in replies.items() for local, frames in reply.frames}
        for index, row in enumerate(recorded):
            before_last = drawn[(int(workers[row]), int(local_indices[row]))]
            last = int(result.num_steps[row]) - 1
            for camera, out in result.frames.items():
                for step, frame in enumerate(before_last):
                    out[index, step] = frame[camera][0]
                out[index, last] = obs["images"][camera][row]
        return result

    def _result(self, obs: dict[str, Any], rows: np.ndarray, recorded: np.ndarray, past_end: bool = False) -> ChunkResult:
        """The answer over result rows ``[n, K, 4]``; recorded envs' frames zeroed, to be filled."""
        n, k = rows.shape[:2]
        stopped = (rows[:, :, _TERMINATED] != 0) | (rows[:, :, _TRUNCATED] != 0)
        if past_end:
            stopped = np.zeros_like(stopped)  # every env applied all K
        # An env stops at its first termination or truncation; one that never did applied all K.
        first_stop = np.argmax(stopped, axis=1) if k else np.zeros(n, dtype=np.int64)
        num_steps = np.where(stopped.any(axis=1), first_stop + 1, k).astype(np.int32)
        images = self._images_space()
        cameras = images.spaces if images is not None and recorded.size else {}
        frames = {camera: np.zeros((recorded.size, k, *space.shape), space.dtype) for camera, space in cameras.items()}
        return ChunkResult(
            obs=obs,
            reward=rows[:, :, _REWARD].copy(),
            terminated=rows[:, :, _TERMINATED] != 0,
            truncated=rows[:, :, _TRUNCATED] != 0,
            success=rows[:, :, _SUCCESS] != 0,
            num_steps=num_steps,
            frames=frames,
        )

    def frame(self, env_index: int, camera: str) -> np.ndarray:
        """Return a copy of the uint8 HxWx3 image ``camera`` of env ``env_index`` saw last.

        Raises:
            UnknownEnvError: no env ``env_index``.
            InvalidRequestError: the envs have no camera ``camera``.
            SimCrashedError: the workers crashed or were closed.
        """
        ids = self._env_indices(np.array([env_index]))
        images = self._images_space()
        cameras = [] if images is None else list(images.spaces)
        if camera not in cameras:
            raise InvalidRequestError(f"camera: no camera {camera!r}; cameras: {cameras}")
        worker, local = self._location[ids[0]]
        with self._lock:
            self._check_usable()
            assert self._pool is not None
            return np.array(self._pool.results["obs"]["images"][camera][worker, local])

    def close(self) -> None:
        """Stop the worker processes. Idempotent. Returns None."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            if self._pool is not None:
                # Terminating cannot hang on a stuck worker, and the workers hold nothing to save.
                self._pool.close()
                log.info("closed %d worker processes", len(self._workers))

    def __enter__(self) -> TaskGroupedVectorEnv:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def env_attr(self, env_indices: Any, op: str, name: Any, payload: Any = None) -> tuple[list[Any], list[EnvError]]:
        """Get (``op`` ``get``), call (``call``, ``payload`` ``(args, kwargs)``) or set (``set``,
        ``payload`` one value per env) attribute ``name`` of each named env.

        Returns:
            ``(results, errors)``: one JSON result per env (None for ``set``), and the envs whose
            attribute raised (:class:`EnvError`; their result is None).

        Raises:
            UnknownEnvError: an env index out of range.
            InvalidRequestError: duplicate env ids, a name that is not a public attribute name
                (or one vecsim keeps: ``close``, ``reset``, ``step``, ...), a bad payload.
            SimCrashedError: a worker died, hung or failed.
        """
        ids = self._env_indices(env_indices)
        if op not in ("get", "call", "set"):
            raise InvalidRequestError(f"op: {op!r} is not one of get, call, set")
        if not isinstance(name, str) or not name.isidentifier() or keyword.iskeyword(name):
            raise InvalidRequestError(f"name: {name!r:.60} is not a public attribute name")
        if name.startswith("_") and (name not in _SERVED_PRIVATE_ATTRS or op == "set"):
            raise InvalidRequestError(f"name: {name!r:.60} is not a public attribute name")
        if name in _REFUSED_ATTRS:
            raise InvalidRequestError(f"name: {name!r} is the pod's to use; it is not served")
        if op == "set" and (not isinstance(payload, list) or len(payload) != ids.size):
            raise InvalidRequestError(f"values: expected one value per env id ({ids.size})")
        if ids.size == 0:
            return [], []
        requests: dict[int, dict[int, tuple[str, str, Any]]] = {}
        for row, env in enumerate(ids.tolist()):
            worker = int(self._location[env, 0])
            requests.setdefault(worker, {})[env] = (op, name, payload[row] if op == "set" else payload)
        with self._lock:
            answers = self._ask("env_attr", requests)
        by_env = {env: (ok, value) for entries in answers.values() for env, ok, value in entries}
        results: list[Any] = []
        errors: list[EnvError] = []
        for row, env in enumerate(ids):
            ok, value = by_env[int(env)]
            results.append(value if ok else None)
            if not ok:
                errors.append(EnvError(row, *value))
        return results, errors

    # Internals.

    def _images_space(self) -> gymnasium.spaces.Dict | None:
        space = self.single_observation_space
        return space.spaces.get("images") if isinstance(space, gymnasium.spaces.Dict) else None

    def _empty_obs(self) -> dict[str, Any]:
        return create_empty_array(self.single_observation_space, n=0, fn=np.zeros)

    @staticmethod
    def _by_worker(workers: np.ndarray, local_indices: np.ndarray) -> list[tuple[int, np.ndarray]]:
        """The rows of a call grouped by worker: ``[(worker, rows), ...]``, each worker's rows in
        local-index order (the order a worker runs its envs in)."""
        rows = np.lexsort((local_indices, workers))
        ordered = workers[rows]
        bounds = [0, *(np.flatnonzero(ordered[1:] != ordered[:-1]) + 1).tolist(), rows.size]
        return [(int(ordered[first]), rows[first:last]) for first, last in itertools.pairwise(bounds) if last > first]

    def _current(self, workers: np.ndarray, local_indices: np.ndarray) -> dict[str, Any]:
        """The named envs' observations as they stand, without a worker call."""
        with self._lock:
            self._check_usable()
            assert self._pool is not None
            return _gather(self._pool.results["obs"], workers, local_indices)

    def _dead_worker(self) -> str | None:
        assert self._pool is not None
        index = self._pool.dead()
        if index is None:
            return None
        hosted = self._workers[index].describe()
        process = self._pool.processes[index]
        process.join(timeout=0.5)  # its exit code, when its end is a matter of moments
        return f"worker {index} hosting {hosted} died with exit code {process.exitcode}"

    def _check_usable(self) -> None:
        if self._closed:
            raise SimCrashedError("the envs are closed")
        if self._broken is None:
            self._broken = self._dead_worker()
        if self._broken is not None:
            raise SimCrashedError(self._broken)

    def _failure(self, exc: Exception) -> str:
        if isinstance(exc, _WorkerFailure):
            hosted = self._workers[exc.worker].describe()
            return f"worker {exc.worker} hosting {hosted} failed: {exc}"
        # A worker whose pipe closed is exiting; give it a moment so the message can name it.
        deadline = time.monotonic() + 1.0
        dead = self._dead_worker()
        while dead is None and time.monotonic() < deadline:
            time.sleep(0.05)
            dead = self._dead_worker()
        return f"{dead or 'a worker failed'}: {type(exc).__name__}: {exc}"

    def _ask(self, order: str, args: dict[int, Any]) -> dict[int, Any]:
        """Send ``order`` to each worker in ``args`` (worker -> its one argument), and to no
        other; return each one's reply. Any worker found dead, before or after, breaks the pod.
        The caller holds ``self._lock``.

        Raises:
            SimCrashedError: a worker died, did not answer within the timeout, or failed.
        """
        self._check_usable()
        assert self._pool is not None
        try:
            for worker, arg in args.items():
                self._pool.send(worker, order, arg)
            replies = self._pool.receive(list(args), self._timeout_s)
        except multiprocessing.TimeoutError as exc:
            self._broken = f"the workers did not answer within {self._timeout_s} s ({exc})"
            raise SimCrashedError(self._broken) from exc
        except Exception as exc:
            self._broken = self._failure(exc)
            raise SimCrashedError(self._broken) from exc
        # A worker that died while others worked breaks the pod as surely as one that had work.
        self._check_usable()
        return replies

    def _run(
        self, orders: dict[int, _Order], workers: np.ndarray, local_indices: np.ndarray
    ) -> tuple[Any, np.ndarray, dict[int, _Reply]]:
        """Send each worker of ``orders`` its order (no other worker hears of the call); return
        the named envs' observations, their result rows ``[n, max_chunk, 4]`` and the replies."""
        with self._lock:
            replies: dict[int, _Reply] = self._ask("run", orders)
            assert self._pool is not None
            obs = _gather(self._pool.results["obs"], workers, local_indices)
            rows = self._pool.results["flags"][workers, local_indices]
        self.last_timing = CallTiming(
            float(sum(reply.physics_s for reply in replies.values())),
            float(sum(reply.render_s for reply in replies.values())),
            sum(reply.renders for reply in replies.values()),
        )
        return obs, rows, replies


def _int_array(name: str, values: Any) -> np.ndarray:
    try:
        array = np.asarray(values)
    except ValueError as exc:
        raise InvalidRequestError(f"{name}: not a flat list of integers: {exc}") from None
    if array.ndim != 1:
        raise InvalidRequestError(f"{name}: expected a 1-d list of integers, got shape {array.shape}")
    if array.size and array.dtype.kind not in "iu":
        raise InvalidRequestError(f"{name}: expected integers, got dtype {array.dtype}")
    return array
