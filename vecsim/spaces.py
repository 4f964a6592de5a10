"""gymnasium spaces to and from JSON, for ``/v1/info`` and the client that reads it.

Supported: ``Box``, ``Discrete``, ``MultiBinary``, ``MultiDiscrete`` and (nested) ``Dict`` and
``Tuple``: the spaces gymnasium's vector envs batch. Every space is an object with a ``"type"`` key::

    {"type": "Box", "dtype": "float32", "shape": [39], "low": "-Infinity", "high": "Infinity"}
    {"type": "Discrete", "n": 4, "start": 0, "dtype": "int64"}
    {"type": "MultiBinary", "n": [2, 3]}
    {"type": "MultiDiscrete", "nvec": [3, 4], "start": [0, 0], "dtype": "int64"}
    {"type": "Dict", "spaces": {"images": {...}, "proprio": {...}}}
    {"type": "Tuple", "spaces": [{...}, {...}]}

A Box bound is one number when every element is equal (an image Box stays small), else a
nested list. Infinities use the spellings of :func:`vecsim.wire.to_jsonable` (``"Infinity"``,
``"-Infinity"``), so the result passes ``json.dumps(..., allow_nan=False)``. Dict keys keep
their order. A space that was seeded (its generator made, gymnasium's PCG64) carries its
generator's state as ``"rng"`` (integers as decimal strings, as JSON readers cap them at 64
bits), so the space rebuilt samples as the original would next; :func:`without_rng` leaves it out.

On the wire (:mod:`vecsim.wire`, nested dicts of arrays) a value of a ``Tuple`` space travels as
a dict keyed ``"0"``, ``"1"``, ...: :func:`tuples_as_dicts` writes it, the reader puts it back
into the tuple its space says. A value of a ``Box`` or ``Discrete`` space is an array (batched:
``[n, *shape]``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
from gymnasium import spaces

from vecsim.wire import WireError, from_jsonable, to_jsonable

__all__ = [
    "check_action_space",
    "check_travels",
    "in_kind_of",
    "space_from_json",
    "space_to_json",
    "tuples_as_dicts",
    "wire_action_space",
    "without_rng",
]

_FIELDS = {
    "Box": {"type", "dtype", "shape", "low", "high"},
    "Discrete": {"type", "n", "start", "dtype"},
    "MultiBinary": {"type", "n"},
    "MultiDiscrete": {"type", "nvec", "start", "dtype"},
    "Dict": {"type", "spaces"},
    "Tuple": {"type", "spaces"},
}
_SUPPORTED = "Box, Discrete, MultiBinary, MultiDiscrete, Dict, Tuple"
_ARRAY_SPACES = (spaces.Box, spaces.Discrete, spaces.MultiDiscrete, spaces.MultiBinary)
_COMPOSITE = (spaces.Dict, spaces.Tuple)
# The dtypes the wire carries (vecsim.wire).
_WIRE_KINDS = frozenset("biuf")


def _bound(values: np.ndarray) -> Any:
    flat = values.reshape(-1)
    if flat.size and (flat == flat[0]).all():
        return to_jsonable(flat[0])
    return to_jsonable(values)


def _to_json(space: spaces.Space, where: str) -> dict[str, Any]:
    out = _describe(space, where)
    generator = space._np_random  # None until the space is seeded or sampled
    if generator is not None and isinstance(generator.bit_generator, np.random.PCG64):
        state = generator.bit_generator.state
        out["rng"] = {
            "state": str(state["state"]["state"]),
            "inc": str(state["state"]["inc"]),
            "has_uint32": int(state["has_uint32"]),
            "uinteger": str(state["uinteger"]),
        }
    return out


def _rng(d: Any, where: str) -> np.random.Generator:
    """The generator a ``"rng"`` field describes."""
    try:
        state = {
            "bit_generator": "PCG64",
            "state": {"state": int(d["state"]), "inc": int(d["inc"])},
            "has_uint32": int(d["has_uint32"]),
            "uinteger": int(d["uinteger"]),
        }
        bit_generator = np.random.PCG64()
        bit_generator.state = state
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{where}.rng: not a PCG64 state: {exc}") from None
    return np.random.Generator(bit_generator)


def without_rng(d: Any) -> Any:
    """A space description (:func:`space_to_json`) without its generators' states: two spaces
    that are equal describe alike, however far each has been sampled."""
    if isinstance(d, Mapping):
        return {key: without_rng(value) for key, value in d.items() if key != "rng"}
    if isinstance(d, (list, tuple)):
        return [without_rng(item) for item in d]
    return d


def _describe(space: spaces.Space, where: str) -> dict[str, Any]:
    # Exact types: a subclass may carry state that these fields would silently drop.
    kind = type(space)
    if kind is spaces.Box:
        return {
            "type": "Box",
            "dtype": space.dtype.name,
            "shape": list(space.shape),
            "low": _bound(space.low),
            "high": _bound(space.high),
        }
    if kind is spaces.Discrete:
        return {"type": "Discrete", "n": int(space.n), "start": int(space.start), "dtype": space.dtype.name}
    if kind is spaces.MultiBinary:
        n = space.n
        return {"type": "MultiBinary", "n": int(n) if np.ndim(n) == 0 else [int(k) for k in n]}
    if kind is spaces.MultiDiscrete:
        return {
            "type": "MultiDiscrete",
            "nvec": space.nvec.tolist(),
            "start": space.start.tolist(),
            "dtype": space.dtype.name,
        }
    if kind is spaces.Dict:
        out = {}
        for key, sub in space.spaces.items():
            if not isinstance(key, str):
                raise ValueError(f"{where}: Dict key {key!r} is not a str")
            out[key] = _to_json(sub, f"{where}.spaces.{key}")
        return {"type": "Dict", "spaces": out}
    if kind is spaces.Tuple:
        return {"type": "Tuple", "spaces": [_to_json(sub, f"{where}.spaces.{i}") for i, sub in enumerate(space.spaces)]}
    raise ValueError(f"{where}: {kind.__name__} is not supported ({_SUPPORTED})")


def space_to_json(space: spaces.Space) -> dict[str, Any]:
    """Describe ``space`` as JSON data.

    Returns:
        a dict of plain JSON values (see the module docstring for the layout).

    Raises:
        ValueError: ``space`` (or a space nested in it, named by path) is of an unsupported type.
    """
    return _to_json(space, "space")


def _dtype(value: Any, where: str, kinds: str) -> np.dtype:
    try:
        dtype = np.dtype(value) if isinstance(value, str) else None
    except TypeError:
        dtype = None
    if dtype is None or dtype.kind not in kinds:
        raise ValueError(f"{where}.dtype: {value!r:.50} is not a usable dtype here")
    return dtype


def _ints(value: Any, where: str, *, scalar: bool = False) -> Any:
    """``value`` as an int (``scalar``) or a rectangular int array, else ValueError naming ``where``."""
    try:
        arr = from_jsonable(value, like=np.int64)
    except WireError as exc:
        raise ValueError(f"{where}: {exc}") from None
    if scalar:
        if arr.ndim:
            raise ValueError(f"{where}: expected an int, got {value!r:.50}")
        return int(arr)
    return arr


def _require(d: Any, where: str) -> str:
    if not isinstance(d, Mapping):
        raise ValueError(f"{where}: expected an object, got {type(d).__name__}")
    kind = d.get("type")
    if kind not in _FIELDS:
        raise ValueError(f"{where}.type: {kind!r:.50} is not one of {sorted(_FIELDS)}")
    missing = _FIELDS[kind] - set(d)
    extra = set(d) - _FIELDS[kind] - {"rng"}
    if missing or extra:
        raise ValueError(
            f"{where}: a {kind} needs exactly the fields {sorted(_FIELDS[kind])}; "
            f"missing {sorted(missing)}, unknown {sorted(extra)}"
        )
    return kind


def _construct(where: str, kind: str, make: Callable[[], spaces.Space]) -> spaces.Space:
    try:
        return make()
    except (ValueError, TypeError, AssertionError) as exc:
        # gymnasium's own checks (n > 0, low <= high, shapes that broadcast) name no field.
        raise ValueError(f"{where}: not a valid {kind}: {exc}") from None


def _bounds(d: Mapping[str, Any], where: str, dtype: np.dtype) -> tuple[np.ndarray, np.ndarray]:
    out = []
    for name in ("low", "high"):
        try:
            bound = from_jsonable(d[name], like=dtype)
        except WireError as exc:
            raise ValueError(f"{where}.{name}: {exc}") from None
        if dtype.kind == "f" and np.isnan(bound).any():
            raise ValueError(f"{where}.{name}: NaN is not a bound")
        out.append(bound)
    return out[0], out[1]


def _from_json(d: Any, where: str) -> spaces.Space:
    space = _build(d, where)
    if "rng" in d:
        space._np_random = _rng(d["rng"], where)
    return space


def _build(d: Any, where: str) -> spaces.Space:
    kind = _require(d, where)
    if kind == "Box":
        dtype = _dtype(d["dtype"], where, "biuf")
        if not isinstance(d["shape"], list):
            raise ValueError(f"{where}.shape: expected a list of ints, got {d['shape']!r:.50}")
        shape = tuple(int(k) for k in _ints(d["shape"], f"{where}.shape"))
        low, high = _bounds(d, where, dtype)

        def make_box() -> spaces.Box:
            # gymnasium takes a Python scalar for a uniform bound but not a 0-d array.
            full_low = np.full(shape, low, dtype=dtype) if low.ndim == 0 else low
            full_high = np.full(shape, high, dtype=dtype) if high.ndim == 0 else high
            return spaces.Box(low=full_low, high=full_high, shape=shape, dtype=dtype)

        return _construct(where, kind, make_box)
    if kind == "Discrete":
        dtype = _dtype(d["dtype"], where, "iu")
        n = _ints(d["n"], f"{where}.n", scalar=True)
        start = _ints(d["start"], f"{where}.start", scalar=True)
        return _construct(where, kind, lambda: spaces.Discrete(n, start=start, dtype=dtype))
    if kind == "MultiBinary":
        n = _ints(d["n"], f"{where}.n")
        return _construct(where, kind, lambda: spaces.MultiBinary(int(n) if n.ndim == 0 else n.tolist()))
    if kind == "MultiDiscrete":
        dtype = _dtype(d["dtype"], where, "iu")
        nvec = _ints(d["nvec"], f"{where}.nvec")
        start = _ints(d["start"], f"{where}.start")
        return _construct(where, kind, lambda: spaces.MultiDiscrete(nvec, dtype=dtype, start=start))
    children = d["spaces"]
    if kind == "Tuple":
        if not isinstance(children, list):
            raise ValueError(f"{where}.spaces: expected a list, got {type(children).__name__}")
        return spaces.Tuple([_from_json(sub, f"{where}.spaces.{i}") for i, sub in enumerate(children)])
    if not isinstance(children, Mapping):
        raise ValueError(f"{where}.spaces: expected an object, got {type(children).__name__}")
    # A sequence of pairs keeps the order that JSON gave (a plain dict would be sorted).
    return spaces.Dict([(key, _from_json(sub, f"{where}.spaces.{key}")) for key, sub in children.items()])


def space_from_json(d: Mapping[str, Any]) -> spaces.Space:
    """Build the space that :func:`space_to_json` described.

    Returns:
        a gymnasium space equal to the one that was described, its generators (where described)
        in the states described.

    Raises:
        ValueError: ``d`` is not a valid description; the message names the field (for
            example ``space.spaces.images.low``).
    """
    return _from_json(d, "space")


def check_travels(space: spaces.Space, where: str = "space") -> spaces.Space:
    """Return ``space`` if its values can be served (described in JSON, carried on the wire).

    Raises:
        ValueError: a space (named by path under ``where``) of another type or of a dtype the
            wire does not carry.
    """
    _to_json(space, where)
    for path, leaf in _leaf_spaces(space, where):
        if leaf.dtype is None or np.dtype(leaf.dtype).kind not in _WIRE_KINDS:
            raise ValueError(f"{path}: dtype {leaf.dtype} cannot travel on the wire (bool, ints, floats)")
    return space


def check_action_space(space: spaces.Space, where: str = "action space") -> spaces.Space:
    """Return ``space`` if vecsim can take actions of it: an array space (Box, Discrete,
    MultiDiscrete, MultiBinary), or a Dict or Tuple of them (nested), which travels flattened
    (:func:`wire_action_space`).

    Raises:
        ValueError: any other space, named by its path under ``where``.
    """
    leaves = _leaf_spaces(space, where) if type(space) in _COMPOSITE else [(where, space)]
    for path, leaf in leaves:
        if type(leaf) not in _ARRAY_SPACES:
            raise ValueError(
                f"{path}: {type(leaf).__name__} actions are not served; vecsim takes arrays (Box, "
                "Discrete, MultiDiscrete, MultiBinary) and Dict or Tuple spaces of them"
            )
    return check_travels(space, where)


def wire_action_space(space: spaces.Space) -> spaces.Space:
    """The array space an action of ``space`` travels in: ``space`` itself, or for a Dict or
    Tuple action space gymnasium's ``flatten_space`` of it (each action ``flatten``-ed by the
    client, ``unflatten``-ed before the env takes it: exact, one-hot for Discrete parts)."""
    return spaces.flatten_space(space) if type(space) in _COMPOSITE else space


def _leaf_spaces(space: spaces.Space, where: str) -> list[tuple[str, spaces.Space]]:
    if isinstance(space, spaces.Dict):
        return [leaf for key, sub in space.spaces.items() for leaf in _leaf_spaces(sub, f"{where}.{key}")]
    if isinstance(space, spaces.Tuple):
        return [leaf for i, sub in enumerate(space.spaces) for leaf in _leaf_spaces(sub, f"{where}.{i}")]
    return [(where, space)]


def tuples_as_dicts(value: Any) -> Any:
    """Return ``value`` (a space's value, nested dicts and tuples of arrays) with every tuple
    written as a dict keyed ``"0"``, ``"1"``, ...: the form the wire carries."""
    if isinstance(value, tuple):
        return {str(i): tuples_as_dicts(item) for i, item in enumerate(value)}
    if isinstance(value, dict):
        return {key: tuples_as_dicts(item) for key, item in value.items()}
    return value


# Kinds of numpy dtypes that hold the same kind of number: an action of one of them keeps its dtype.
_KINDS = {"b": "b", "i": "iu", "u": "iu", "f": "f"}


def in_kind_of(values: np.ndarray, dtype: Any) -> np.ndarray:
    """``values`` as they are if their dtype holds the kind of number ``dtype`` does (floats for a
    float space, integers for an integer one, bools for bools; 8 bytes at most, as the wire's), else
    cast to ``dtype``: actions
    reach the env in the dtype the user sent them in, as gymnasium's vector envs hand them on."""
    if values.dtype.kind in _KINDS.get(np.dtype(dtype).kind, "") and values.dtype.itemsize <= 8:
        return values
    return values.astype(dtype)
