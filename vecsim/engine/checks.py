"""Request checks: what a call must satisfy before any worker is touched.

Each function checks one argument of a :class:`~vecsim.engine.vector_env.TaskGroupedVectorEnv`
call (or an assignment) and returns it in the form the workers take, or raises the error that
names the field at fault: :class:`~vecsim.engine.errors.UnknownEnvError` for an env index the pod
does not have, :class:`~vecsim.engine.errors.InvalidRequestError` for anything else. Nothing here
has a side effect, so a rejected call changes nothing.
"""

from __future__ import annotations

import keyword
import math
from collections.abc import Sequence
from typing import Any

import gymnasium
import numpy as np

from vecsim.config import Assignment
from vecsim.engine.errors import InvalidRequestError, SpacesDifferError, UnknownEnvError
from vecsim.engine.tasks import task_spaces
from vecsim.spaces import in_kind_of

MAX_SEED = 2**63 - 1
# What get_attr / call / set_attr may name: public attributes; close stays the pod's to call.
REFUSED_ATTRS = frozenset({"close", "reset", "step", "unwrapped", "np_random"})
# Private names served all the same (get and call): TimeLimit's limit, which gymnasium's own
# code and trainers' eval loops (LeRobot's rollout) read by this name.
SERVED_PRIVATE_ATTRS = frozenset({"_max_episode_steps"})


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
        SpacesDifferError: the tasks do not share one observation space and one action space
            (an InvalidRequestError and a RuntimeError, as gymnasium's vector envs raise).
        ValueError: a gym task with a space vecsim cannot serve (named).
    """
    first: tuple[str, gymnasium.Space, gymnasium.Space] | None = None
    for block in assignment.tasks:
        kwargs = assignment.make_kwargs.get(block.task_id)
        observation_space, action_space = task_spaces(block.task_id, assignment.camera, kwargs)
        if first is None:
            first = (block.task_id, observation_space, action_space)
        else:
            for what, space, reference in (
                ("observation", observation_space, first[1]),
                ("action", action_space, first[2]),
            ):
                if space != reference:
                    raise SpacesDifferError(
                        f"tasks: {block.task_id!r} and {first[0]!r} have different {what} spaces ({space} and "
                        f"{reference}); one pod's tasks must share one observation space and one action space"
                    )
    return _empty_spaces() if first is None else first[1:]


def env_indices(values: Any, num_envs: int, field: str = "env_indices") -> np.ndarray:
    """``values`` (the request's ``field``) as int64 env indices of a pod of ``num_envs`` envs,
    each named once."""
    ids = _int_array(field, values)
    if ids.size:
        bad = ids[(ids < 0) | (ids >= num_envs)]
        if bad.size:
            have = f"envs 0..{num_envs - 1}" if num_envs else "no envs"
            raise UnknownEnvError(f"{field}: env {int(bad[0])} does not exist; this pod has {have}")
        unique, counts = np.unique(ids, return_counts=True)
        if (counts > 1).any():
            twice = int(unique[counts > 1][0])
            raise InvalidRequestError(f"{field}: env {twice} is named more than once")
    return ids.astype(np.int64)


def state_ids(
    values: Any, ids: np.ndarray, num_states: np.ndarray, task_ids: Sequence[str], field: str = "state_ids"
) -> np.ndarray:
    """``values`` (the request's ``field``) as int64 state ids, one per env of ``ids``, each
    within its env's task (``num_states[env]`` states, task ``task_ids[env]``)."""
    states = _int_array(field, values)
    if states.size != ids.size:
        raise InvalidRequestError(f"{field}: {states.size} state ids for {ids.size} env_indices")
    if ids.size:
        limits = num_states[ids]
        bad = np.flatnonzero((states < 0) | (states >= limits))
        if bad.size:
            i = int(bad[0])
            env = int(ids[i])
            raise InvalidRequestError(
                f"{field}: state {int(states[i])} for env {env} is out of range "
                f"0..{int(limits[i]) - 1} of task {task_ids[env]!r}"
            )
    return states.astype(np.int64)


def seeds(values: Any, ids: np.ndarray) -> np.ndarray:
    """``values`` (a list of non-negative ints or None, one per env) as int64, None as -1."""
    if not isinstance(values, (list, tuple, np.ndarray)):
        raise InvalidRequestError(f"seeds: expected a list of ints or nulls, got {type(values).__name__}")
    if len(values) != ids.size:
        raise InvalidRequestError(f"seeds: {len(values)} seeds for {ids.size} env_indices")
    out = np.full(ids.size, -1, dtype=np.int64)
    for i, seed in enumerate(values):
        if seed is None:
            continue
        if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer)):
            raise InvalidRequestError(f"seeds: seed {i} is {seed!r:.50}, not an int or null")
        if not 0 <= int(seed) <= MAX_SEED:
            raise InvalidRequestError(f"seeds: seed {i} ({seed}) is outside 0..{MAX_SEED}")
        out[i] = int(seed)
    return out


def actions(values: Any, ids: np.ndarray, space: gymnasium.Space) -> np.ndarray:
    """Return ``values`` (one action of ``space`` per env, ``[n, *action shape]``) as a chunk of one per env."""
    numbers = _numbers(values, space)
    if ids.size == 0 and numbers.size == 0:
        return np.zeros((0, 1, *space.shape), dtype=space.dtype)
    expected = (ids.size, *space.shape)
    if numbers.shape != expected:
        raise InvalidRequestError(f"actions: expected shape {expected}, got {numbers.shape}")
    return _finite(numbers[:, None], ids, space)


def chunk(values: Any, ids: np.ndarray, space: gymnasium.Space, max_chunk: int) -> np.ndarray:
    """Return ``values`` (``[n, K, *action shape]``, K from 0 to ``max_chunk``) checked."""
    if not isinstance(space, gymnasium.spaces.Box):
        raise InvalidRequestError(
            f"actions: chunks of actions are for Box action spaces; this pod's is {type(space).__name__}: "
            "send one action per env"
        )
    numbers = _numbers(values, space)
    if ids.size == 0 and numbers.size == 0 and numbers.ndim != 2 + len(space.shape):
        return np.zeros((0, 0, *space.shape), dtype=space.dtype)
    if numbers.ndim != 2 + len(space.shape) or numbers.shape[0] != ids.size or numbers.shape[2:] != space.shape:
        expected = f"({ids.size}, K, {', '.join(map(str, space.shape))})"
        raise InvalidRequestError(f"actions: expected a chunk of shape {expected}, got {numbers.shape}")
    if numbers.shape[1] > max_chunk:
        raise InvalidRequestError(
            f"actions: a chunk of {numbers.shape[1]} actions per env exceeds this pod's limit of {max_chunk}"
        )
    return _finite(numbers, ids, space)


def record(values: Any, ids: np.ndarray) -> np.ndarray:
    """Return the rows of ``ids`` that ``values`` (``record_env_indices``) names, in its order."""
    recorded = _int_array("record_env_indices", values)
    if recorded.size == 0:
        return np.zeros(0, dtype=np.int64)
    unique, counts = np.unique(recorded, return_counts=True)
    if (counts > 1).any():
        raise InvalidRequestError(f"record_env_indices: env {int(unique[counts > 1][0])} is named more than once")
    rows = {int(env): row for row, env in enumerate(ids)}
    missing = [int(env) for env in recorded if int(env) not in rows]
    if missing:
        raise InvalidRequestError(f"record_env_indices: env {missing[0]} is not one of the env_indices stepped")
    return np.array([rows[int(env)] for env in recorded], dtype=np.int64)


def attr_request(op: str, name: Any, payload: Any, ids: np.ndarray) -> None:
    """Check an attribute call: ``op`` get, call or set; ``name`` a public attribute the pod
    serves; for ``set``, ``payload`` one value per env of ``ids``."""
    if op not in ("get", "call", "set"):
        raise InvalidRequestError(f"op: {op!r} is not one of get, call, set")
    if not isinstance(name, str) or not name.isidentifier() or keyword.iskeyword(name):
        raise InvalidRequestError(f"name: {name!r:.60} is not a public attribute name")
    if name.startswith("_") and (name not in SERVED_PRIVATE_ATTRS or op == "set"):
        raise InvalidRequestError(f"name: {name!r:.60} is not a public attribute name")
    if name in REFUSED_ATTRS:
        raise InvalidRequestError(f"name: {name!r} is the pod's to use; it is not served")
    if op == "set" and (not isinstance(payload, list) or len(payload) != ids.size):
        raise InvalidRequestError(f"values: expected one value per env id ({ids.size})")


def _numbers(values: Any, space: gymnasium.Space) -> np.ndarray:
    """``values`` as an array of numbers (bools too, for a space of bools)."""
    try:
        numbers = np.asarray(values)
    except ValueError as exc:
        raise InvalidRequestError(f"actions: not a rectangular array: {exc}") from None
    kinds = "bfiu" if np.dtype(space.dtype).kind == "b" else "fiu"
    if numbers.size and numbers.dtype.kind not in kinds:
        raise InvalidRequestError(f"actions: expected numbers, got dtype {numbers.dtype}")
    return numbers


def _finite(chunk: np.ndarray, ids: np.ndarray, space: gymnasium.Space) -> np.ndarray:
    if np.dtype(space.dtype).kind != "f":
        return _in_range(chunk, ids, space)
    cast = chunk.astype(space.dtype)
    finite = np.isfinite(cast.reshape(*cast.shape[:2], math.prod(cast.shape[2:]))).all(axis=2)
    if not finite.all():
        row, k = (int(i[0]) for i in np.nonzero(~finite))
        where = f"action {k} of the chunk" if chunk.shape[1] > 1 else "the action"
        raise InvalidRequestError(f"actions: {where} for env {int(ids[row])} is not finite (NaN, inf or too large)")
    return in_kind_of(chunk, space.dtype)


def _in_range(chunk: np.ndarray, ids: np.ndarray, space: gymnasium.Space) -> np.ndarray:
    """``chunk``, each action a member of the integer (or bool) action space (its dtype kept
    where it is of the space's kind, :func:`~vecsim.spaces.in_kind_of`)."""
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
    return in_kind_of(chunk, space.dtype)


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
