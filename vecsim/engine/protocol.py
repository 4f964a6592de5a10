"""The pod<->worker protocol: the messages on one worker's pipe.

One pipe per worker, one exchange (an order, then its reply) in flight on it at a time. The pod
sends an order and the worker answers with its result, or with its failure ``(type name,
message, traceback)`` and exits. Orders (:data:`WORKER_ORDERS`): ``build`` (make the envs, each
in state 0), ``run`` (one :class:`Order`: reset these envs (by local index) to these state ids,
reset them by the env's own ``reset(seed=..., options=...)`` (seed -1: None), or step them
through a chunk of K actions each, recording the frames of some), ``env_attr`` (get, call or set
attributes of named envs). A ``run`` travels as a small binary message (local indices, then state
ids, seeds or the actions in the dtype they were sent in: :func:`encode_run`); the other orders (and
a seeded reset with options) as a one-byte message saying that an object follows, then the
object; every reply is one object (a :class:`Reply` for a ``run``). Objects are multiprocessing's
own pickled messages (``Connection.send``, ``recv``) between the pod and its own processes:
vecsim's code unpickles nothing itself, and nothing from the network travels this way.
"""

from __future__ import annotations

import math
import multiprocessing.connection
import struct
from dataclasses import dataclass
from typing import Any

import gymnasium
import numpy as np


@dataclass(frozen=True)
class Order:
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
class Reply:
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


# What a worker process is asked to do: a Worker method, with its arguments.
WORKER_ORDERS = frozenset({"build", "run", "env_attr"})

# An order to a worker is one multiprocessing frame (``Connection.send_bytes``) whose first byte
# says what it is: a binary run order, or PICKLED, "an object follows": the next message is
# multiprocessing's own pickled ``(order, args)`` (``Connection.send``/``recv``). A worker's reply
# is always such an object, ``(ok, result)``. vecsim's code unpickles nothing itself; these are
# the pod's own processes, as with any multiprocessing pipe. One exchange (an order, then its
# reply) is in flight on a pipe at a time.
PICKLED = ord("p")
# A run order in binary: _RUN_HEAD (tag, kind, whether frames are recorded, the actions' dtype
# as its index in _ACTION_DTYPES, m envs, chunk K), their local indices int64[m], then for _STEP
# the actions [m, K, *action shape] in that dtype (the one the user sent them in) and, when
# recorded, bool[m]; for _STATE the state ids int64[m]; for _SEED the seeds
# int64[m] (-1: None). Every field at an offset its dtype's size divides.
RUN = ord("r")
_RUN_HEAD = struct.Struct("<BBBBIQ")
# The dtypes actions travel in (those of the wire, vecsim.wire).
_ACTION_DTYPES = tuple(
    np.dtype(name)
    for name in (
        "bool",
        "int8",
        "int16",
        "int32",
        "int64",
        "uint8",
        "uint16",
        "uint32",
        "uint64",
        "float16",
        "float32",
        "float64",
    )
)
_DTYPE_CODES = {dtype: code for code, dtype in enumerate(_ACTION_DTYPES)}
_STEP, _STATE, _SEED = 0, 1, 2


def send(pipe: multiprocessing.connection.Connection, *parts: bytes) -> None:
    """Send one message, ``parts`` joined, as one frame of ``pipe``."""
    pipe.send_bytes(b"".join(parts))


def receive(pipe: multiprocessing.connection.Connection) -> bytearray:
    """Receive one message from ``pipe``, writable (so arrays decoded from it are too).

    Raises:
        EOFError: the other end closed the pipe before a message began.
        OSError: the pipe closed inside a message.
    """
    return bytearray(pipe.recv_bytes())


def encode_run(order: Order) -> bytes | None:
    """``order`` as a binary run message, or None for a seeded reset with options (pickled)."""
    local = np.ascontiguousarray(order.local_indices, dtype=np.int64).tobytes()
    m = len(order.local_indices)
    if order.actions is not None:
        k = order.actions.shape[1]
        # The flags byte: bit 0 a record mask follows, bit 1 step past each env's end.
        flags = int(order.record is not None) | (int(order.past_end) << 1)
        dtype = order.actions.dtype.newbyteorder("=")
        actions = np.ascontiguousarray(order.actions, dtype=dtype)
        head = _RUN_HEAD.pack(RUN, _STEP, flags, _DTYPE_CODES[dtype], m, k)
        parts = [head, local, actions.tobytes()]
        if order.record is not None:
            parts.append(np.ascontiguousarray(order.record, dtype=bool).tobytes())
        return b"".join(parts)
    if order.seeds is not None:
        if order.options is not None:
            return None
        values = order.seeds
        head = _RUN_HEAD.pack(RUN, _SEED, False, 0, m, 0)
    else:
        assert order.state_ids is not None
        values = order.state_ids
        head = _RUN_HEAD.pack(RUN, _STATE, False, 0, m, 0)
    return b"".join((head, local, np.ascontiguousarray(values, dtype=np.int64).tobytes()))


def decode_run(message: bytearray, action_space: gymnasium.Space) -> Order:
    """The :class:`Order` of a binary run message (:func:`encode_run`); arrays are views of it."""
    _tag, kind, record, dtype, m, k = _RUN_HEAD.unpack_from(message)
    offset = _RUN_HEAD.size
    local = np.frombuffer(message, np.int64, m, offset)
    offset += local.nbytes
    if kind == _STEP:
        shape = (m, k, *action_space.shape)
        actions = np.frombuffer(message, _ACTION_DTYPES[dtype], math.prod(shape), offset).reshape(shape)
        offset += actions.nbytes
        recorded = np.frombuffer(message, bool, m, offset) if record & 1 else None
        return Order(local, actions=actions, record=recorded, past_end=bool(record & 2))
    values = np.frombuffer(message, np.int64, m, offset)
    return Order(local, seeds=values) if kind == _SEED else Order(local, state_ids=values)


def send_object(pipe: multiprocessing.connection.Connection, obj: Any) -> None:
    """Send ``obj`` through multiprocessing's own pickled message, announced by a ``PICKLED`` one."""
    send(pipe, bytes((PICKLED,)))
    pipe.send(obj)
