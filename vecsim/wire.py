"""Binary codec for nested dicts of numpy arrays: the body of every data-plane request.

A message is ``b"VSW1" | u32 little-endian header length | header (UTF-8 JSON) | pad to 64 |
payload``. The header lists every array (key path, dtype, shape, offset, nbytes) and holds the
non-array leaves under ``"values"``; the payload holds the raw array bytes, each one starting on
a 64-byte boundary. Decoding returns read-only views into the buffer (``np.frombuffer``
style), so a decoded message costs no copy of the array data.

Pure: no I/O, nothing is ever unpickled, and a hostile buffer can only make :func:`decode`
raise :class:`WireError`: every length, offset and shape in the header is checked against the
buffer before anything is built from it.

The JSON helpers :func:`to_jsonable` / :func:`from_jsonable` serve the pod's JSON path (curl,
debugging). JSON has no NaN or infinity, so they travel as the strings ``"NaN"``,
``"Infinity"`` and ``"-Infinity"`` (the spellings of JavaScript and of Python's ``json``);
:func:`from_jsonable` turns them back into floats wherever ``like`` says a float is expected.
"""

from __future__ import annotations

import json
import math
import struct
from collections.abc import Mapping
from typing import Any

import numpy as np

__all__ = [
    "ALIGN",
    "CONTENT_TYPE",
    "MAGIC",
    "MAX_ARRAYS",
    "MAX_DEPTH",
    "MAX_HEADER_BYTES",
    "MAX_NDIM",
    "WireError",
    "chunk_length",
    "decode",
    "encode",
    "encode_parts",
    "from_jsonable",
    "to_jsonable",
]

CONTENT_TYPE = "application/x-vecsim"
MAGIC = b"VSW1"
VERSION = 1
ALIGN = 64
MAX_HEADER_BYTES = 1 << 20
MAX_DEPTH = 32
MAX_ARRAYS = 4096
MAX_NDIM = 32

_PREFIX = struct.Struct("<4sI")
_ZEROS = bytes(ALIGN)
_HEADER_KEYS = frozenset({"v", "arrays", "values"})
_ARRAY_KEYS = frozenset({"path", "dtype", "shape", "offset", "nbytes"})

_ALLOWED_DTYPES = tuple(
    np.dtype(t)
    for t in (
        np.bool_,
        np.int8,
        np.int16,
        np.int32,
        np.int64,
        np.uint8,
        np.uint16,
        np.uint32,
        np.uint64,
        np.float16,
        np.float32,
        np.float64,
    )
)
_ALLOWED_KINDS = frozenset("biuf")
_ALLOWED_KIND_SIZES = frozenset((dt.kind, dt.itemsize) for dt in _ALLOWED_DTYPES)
# Leaves that JSON holds as they are; floats also need a finiteness check.
_PLAIN_TYPES = frozenset({str, int, bool, type(None)})
_ENCODER = json.JSONEncoder(separators=(",", ":"), allow_nan=False)


def chunk_length(shape: tuple[int, ...], action_shape: tuple[int, ...]) -> int | None:
    """What a step's actions of ``shape`` are, for actions of ``action_shape``: a chunk of K per
    env (``[n, K, ...]``, one axis more than ``[n, *action_shape]``: K) or one action per env
    (None). The one rule the client, the rollout loop and the pod decide it by; each checks the
    rest of the shape itself."""
    return int(shape[1]) if len(shape) == len(action_shape) + 2 else None


def _wire_dtype_name(dtype: np.dtype) -> str:
    # Always written with "<" (as in docs/api.md), even for one-byte types where numpy says "|".
    return f"<{dtype.kind}{dtype.itemsize}"


_DTYPE_BY_NAME: dict[str, np.dtype] = {}
for _dt in _ALLOWED_DTYPES:
    _little = _dt.newbyteorder("<")
    _DTYPE_BY_NAME[_wire_dtype_name(_dt)] = _little
    _DTYPE_BY_NAME[_little.str] = _little
del _dt, _little
_NAME_BY_DTYPE = {dtype: name for name, dtype in _DTYPE_BY_NAME.items() if name.startswith("<")}

_NONFINITE_TOKENS = {"NaN": math.nan, "Infinity": math.inf, "-Infinity": -math.inf}


class WireError(ValueError):
    """A message that cannot be encoded or decoded; the text names the key path or the field."""


def _fmt(path: tuple[str, ...] | list[str]) -> str:
    return "/".join(path) if path else "<root>"


def _at(path: tuple[str, ...]) -> str:
    """Prefix for an error message about the value at ``path`` (nothing for the top level)."""
    return f"{_fmt(path)}: " if path else ""


def _align(n: int) -> int:
    return (n + ALIGN - 1) // ALIGN * ALIGN


# --------------------------------------------------------------------------------------- encode


def _prepare_array(value: np.ndarray, path: tuple[str, ...]) -> np.ndarray:
    dtype = value.dtype
    if (dtype.kind, dtype.itemsize) not in _ALLOWED_KIND_SIZES:
        raise WireError(
            f"{_fmt(path)}: dtype {dtype} cannot travel on the wire "
            "(allowed: bool, int8..int64, uint8..uint64, float16/32/64)"
        )
    if dtype.byteorder == ">":
        value = value.astype(dtype.newbyteorder("<"))
    if not value.flags.c_contiguous:
        # np.ascontiguousarray would turn a 0-d array into shape (1,); reshape keeps the shape.
        value = np.ascontiguousarray(value).reshape(value.shape)
    return value


def _leaf(value: Any, path: tuple[str, ...], depth: int) -> Any:
    kind = type(value)
    if kind in _PLAIN_TYPES:
        return value
    if kind is float or isinstance(value, float):
        if not math.isfinite(value):
            raise WireError(
                f"{_fmt(path)}: non-finite float {value!r} cannot sit in the JSON header; send it inside a numpy array"
            )
        return float(value)
    if isinstance(value, (bool, str)):
        return value
    if isinstance(value, int):
        return int(value)
    if isinstance(value, np.generic):
        if value.dtype.kind not in _ALLOWED_KINDS:
            raise WireError(f"{_fmt(path)}: numpy scalar of dtype {value.dtype} is not supported")
        return _leaf(value.item(), path, depth)
    if isinstance(value, (list, tuple)):
        if depth > MAX_DEPTH:
            raise WireError(f"{_fmt(path)}: nested deeper than {MAX_DEPTH} levels")
        if set(map(type, value)) <= _PLAIN_TYPES:
            return list(value)  # the common case (task ids, names): no per-item work
        out = []
        for i, item in enumerate(value):
            if isinstance(item, (Mapping, np.ndarray)):
                raise WireError(
                    f"{_fmt(path)}[{i}]: lists may hold only strings, numbers, bools, None and "
                    f"lists of those, not {type(item).__name__}"
                )
            out.append(_leaf(item, path, depth + 1))
        return out
    raise WireError(f"{_fmt(path)}: cannot encode a value of type {type(value).__name__}")


def _split(
    obj: Mapping[str, Any],
    path: tuple[str, ...],
    depth: int,
    arrays: list[tuple[tuple[str, ...], np.ndarray]],
) -> dict[str, Any]:
    if depth > MAX_DEPTH:
        raise WireError(f"{_fmt(path)}: nested deeper than {MAX_DEPTH} levels")
    values: dict[str, Any] = {}
    for key, value in obj.items():
        if type(key) is not str and not isinstance(key, str):
            raise WireError(f"{_fmt(path)}: keys must be str, got {key!r} ({type(key).__name__})")
        kind = type(value)
        if kind is np.ndarray or isinstance(value, np.ndarray):
            arrays.append((path + (key,), _prepare_array(value, path + (key,))))
        elif kind is dict or isinstance(value, Mapping):
            values[key] = _split(value, path + (key,), depth + 1, arrays)
        elif kind in _PLAIN_TYPES:
            values[key] = value
        else:
            values[key] = _leaf(value, path + (key,), depth + 1)
    return values


def encode_parts(obj: Mapping[str, Any]) -> list[bytes | memoryview]:
    """Encode ``obj`` as a list of buffers whose concatenation is the message.

    The first part holds magic, header and padding; the others are padding and byte views of
    the arrays themselves (no copy), so an HTTP layer can send them without joining.

    Returns:
        the parts; ``len()`` of each is its size in bytes.

    Raises:
        WireError: ``obj`` is not a str-keyed mapping, or holds a value that cannot be encoded
            (object/str/void dtype, non-finite float outside an array, unknown type, too deep,
            too many arrays); the message names the key path.
    """
    if not isinstance(obj, Mapping):
        raise WireError(f"the top level must be a mapping of str keys, got {type(obj).__name__}")
    arrays: list[tuple[tuple[str, ...], np.ndarray]] = []
    values = _split(obj, (), 1, arrays)
    if len(arrays) > MAX_ARRAYS:
        raise WireError(f"{len(arrays)} arrays in one message, more than the cap of {MAX_ARRAYS}")

    specs = []
    payload: list[bytes | memoryview] = []
    cursor = 0
    for path, arr in arrays:
        # An empty array has no bytes to place; offset 0 is in bounds whatever the payload.
        offset = -(-cursor // ALIGN) * ALIGN if arr.nbytes else 0
        specs.append(
            {
                "path": list(path),
                "dtype": _NAME_BY_DTYPE.get(arr.dtype) or _wire_dtype_name(arr.dtype),
                "shape": list(arr.shape),
                "offset": offset,
                "nbytes": arr.nbytes,
            }
        )
        if arr.nbytes:
            if offset > cursor:
                payload.append(_ZEROS[: offset - cursor])
            payload.append(memoryview(arr).cast("B"))
            cursor = offset + arr.nbytes

    # ASCII escapes (json's default) keep even lone surrogates in keys encodable.
    header = _ENCODER.encode({"v": VERSION, "arrays": specs, "values": values}).encode("ascii")
    if len(header) > MAX_HEADER_BYTES:
        raise WireError(f"header of {len(header)} bytes is over the cap of {MAX_HEADER_BYTES}")
    head_end = _PREFIX.size + len(header)
    prefix = _PREFIX.pack(MAGIC, len(header)) + header + _ZEROS[: _align(head_end) - head_end]
    return [prefix, *payload]


def encode(obj: Mapping[str, Any]) -> bytes:
    """Encode ``obj`` (nested str-keyed dicts of numpy arrays and JSON-able leaves) to bytes.

    Returns:
        the whole message in one ``bytes`` object (one copy of the array data).

    Raises:
        WireError: as :func:`encode_parts`.
    """
    return b"".join(encode_parts(obj))


# --------------------------------------------------------------------------------------- decode


def _reject_constant(name: str) -> Any:
    raise WireError(f"header: {name} is not valid JSON")


def _parse_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise WireError(f"header: number {text:.50} is out of range")
    return value


# Duplicate keys in one JSON object: the last wins, as in Python's json; every field is
# checked after parsing, so nothing can hide behind a duplicate.
_DECODER = json.JSONDecoder(parse_constant=_reject_constant, parse_float=_parse_float)


def _check_values(node: dict[str, Any], path: tuple[str, ...], depth: int) -> None:
    if depth > MAX_DEPTH:
        raise WireError(f"header: values at {_fmt(path)} nest deeper than {MAX_DEPTH} levels")
    for key, child in node.items():
        if type(child) is dict:
            _check_values(child, path + (key,), depth + 1)
        elif type(child) is list:
            _check_list(child, path + (key,), depth + 1)


def _check_list(items: list[Any], path: tuple[str, ...], depth: int) -> None:
    if depth > MAX_DEPTH:
        raise WireError(f"header: values at {_fmt(path)} nest deeper than {MAX_DEPTH} levels")
    for item in items:
        if type(item) is dict:
            raise WireError(f"header: values at {_fmt(path)}: a list holds an object")
        if type(item) is list:
            _check_list(item, path, depth + 1)


_STR_ONLY = frozenset({str})
_INT_ONLY = frozenset({int})


def _array_spec(spec: Any, index: int, payload_len: int) -> tuple[list[str], np.dtype, tuple[int, ...], int, int]:
    # Messages are built only on failure: this runs once per array of every message.
    if type(spec) is not dict or spec.keys() != _ARRAY_KEYS:
        raise WireError(f"header: arrays[{index}]: expected an object with keys {sorted(_ARRAY_KEYS)}")
    path = spec["path"]
    if type(path) is not list or not 0 < len(path) <= MAX_DEPTH or not set(map(type, path)) <= _STR_ONLY:
        raise WireError(f"header: arrays[{index}].path: expected 1..{MAX_DEPTH} strings, got {path!r:.200}")
    dtype_name, shape, offset, nbytes = spec["dtype"], spec["shape"], spec["offset"], spec["nbytes"]
    dtype = _DTYPE_BY_NAME.get(dtype_name) if type(dtype_name) is str else None
    if dtype is None:
        raise WireError(f"header: array {_fmt(path)}: dtype {dtype_name!r:.50} is not allowed")
    if type(shape) is not list or len(shape) > MAX_NDIM or not set(map(type, shape)) <= _INT_ONLY:
        raise WireError(
            f"header: array {_fmt(path)}: shape must be a list of at most {MAX_NDIM} ints, got {shape!r:.200}"
        )
    if shape and min(shape) < 0:
        raise WireError(f"header: array {_fmt(path)}: negative dimension in shape {shape}")
    if type(offset) is not int or type(nbytes) is not int or offset < 0 or nbytes < 0:
        raise WireError(f"header: array {_fmt(path)}: offset and nbytes must be non-negative ints")
    if offset % ALIGN:
        raise WireError(f"header: array {_fmt(path)}: offset {offset} is not {ALIGN}-byte aligned")
    if offset + nbytes > payload_len:
        raise WireError(
            f"header: array {_fmt(path)}: bytes {offset}..{offset + nbytes} lie outside the {payload_len}-byte payload"
        )
    count = math.prod(shape)
    if count * dtype.itemsize != nbytes:
        raise WireError(f"header: array {_fmt(path)}: shape {shape} x itemsize {dtype.itemsize} != nbytes {nbytes}")
    return path, dtype, tuple(shape), offset, count


def _place(tree: dict[str, Any], path: list[str], value: np.ndarray) -> None:
    node = tree
    for i, key in enumerate(path[:-1]):
        child = node.setdefault(key, {})
        if not isinstance(child, dict):
            raise WireError(f"header: array {_fmt(path)} collides with the value at {_fmt(path[: i + 1])}")
        node = child
    if path[-1] in node:
        raise WireError(f"header: array {_fmt(path)} collides with another value or array at that path")
    node[path[-1]] = value


# Headers already checked, with the payload length they were checked against: (header bytes,
# payload length) -> the arrays' (path, dtype, shape, offset). Emptied when full; headers over
# _SPECS_MAX_HEADER bytes are not kept (at most 256 x 16 KiB held).
_SPECS: dict[tuple[bytes, int], list[tuple[list[str], np.dtype, tuple[int, ...], int]]] = {}
_SPECS_KEPT = 256
_SPECS_MAX_HEADER = 16 * 1024


def _checked_specs(header: Any, payload_len: int) -> list[tuple[list[str], np.dtype, tuple[int, ...], int]]:
    """Check a decoded header against a payload of ``payload_len`` bytes; return its arrays'
    (path, dtype, shape, offset)."""
    if not isinstance(header, dict) or set(header) != _HEADER_KEYS:
        raise WireError(f"header: expected an object with keys {sorted(_HEADER_KEYS)}")
    if type(header["v"]) is not int or header["v"] != VERSION:
        raise WireError(f"header: unsupported version {header['v']!r:.50}, this decoder reads {VERSION}")
    values, specs = header["values"], header["arrays"]
    if not isinstance(values, dict):
        raise WireError("header: 'values' must be an object")
    if not isinstance(specs, list):
        raise WireError("header: 'arrays' must be a list")
    if len(specs) > MAX_ARRAYS:
        raise WireError(f"header: {len(specs)} arrays, more than the cap of {MAX_ARRAYS}")
    _check_values(values, (), 1)
    checked = []
    for index, spec in enumerate(specs):
        path, dtype, shape, offset, _count = _array_spec(spec, index, payload_len)
        checked.append((path, dtype, shape, offset))
    return checked


def decode(buf: bytes | bytearray | memoryview) -> dict[str, Any]:
    """Decode one message.

    Arrays come back as read-only views into ``buf`` (no copy; they keep ``buf`` alive).
    Lists come back as lists. Key order within a dict: plain values first, then arrays.

    Returns:
        the nested dict that was encoded.

    Raises:
        WireError: ``buf`` is not a well-formed message (wrong magic, truncated, header not JSON
            or over the cap, too deep, too many arrays, an array outside the payload, a shape
            that does not match its byte count, a disallowed dtype, two entries at one path);
            the message names what is wrong. Nothing larger than ``buf`` is ever allocated.
    """
    try:
        view = memoryview(buf)
    except TypeError:
        raise WireError(f"expected a bytes-like object, got {type(buf).__name__}") from None
    if view.ndim != 1 or view.itemsize != 1:
        if not view.c_contiguous:
            raise WireError("the buffer is not contiguous")
        view = view.cast("B")
    size = view.nbytes
    if size < _PREFIX.size:
        raise WireError(f"truncated message: {size} bytes, a message has at least {_PREFIX.size}")
    magic, header_len = _PREFIX.unpack_from(view)
    if magic != MAGIC:
        raise WireError(f"bad magic {bytes(magic)!r}, expected {MAGIC!r}: not a vecsim wire message")
    if header_len > MAX_HEADER_BYTES:
        raise WireError(f"header length {header_len} is over the cap of {MAX_HEADER_BYTES}")
    head_end = _PREFIX.size + header_len
    if head_end > size:
        raise WireError(f"header length {header_len} runs past the end of the {size}-byte buffer")
    payload_start = _align(head_end)
    if payload_start > size:
        raise WireError(f"truncated message: the buffer ends inside the header padding ({size} bytes)")

    head = view[_PREFIX.size : head_end].tobytes()
    payload_len = size - payload_start
    try:
        header = _DECODER.decode(head.decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise WireError(f"header is not UTF-8: {exc}") from None
    except RecursionError:
        raise WireError(f"header nests deeper than {MAX_DEPTH} levels") from None
    except WireError:
        raise
    except ValueError as exc:
        raise WireError(f"header is not JSON: {exc}") from None

    # The same header over a payload of the same length passed every check below before: a
    # step's answers repeat their header call after call.
    specs = _SPECS.get((head, payload_len))
    if specs is None:
        specs = _checked_specs(header, payload_len)
        if len(head) <= _SPECS_MAX_HEADER:
            if len(_SPECS) >= _SPECS_KEPT:
                _SPECS.clear()
            _SPECS[head, payload_len] = specs
    values = header["values"]
    writable = not view.readonly
    for path, dtype, shape, offset in specs:
        try:
            arr = np.ndarray(shape, dtype, buffer=view, offset=payload_start + offset)
        except (ValueError, TypeError) as exc:
            raise WireError(f"header: array {_fmt(path)}: {exc}") from None
        if writable:
            arr.flags.writeable = False
        _place(values, path, arr)
    return values


# ------------------------------------------------------------------------------- JSON helpers


def _nonfinite_token(x: float) -> str:
    return "NaN" if math.isnan(x) else ("Infinity" if x > 0 else "-Infinity")


def to_jsonable(obj: Any, _path: tuple[str, ...] = ()) -> Any:
    """Turn a wire-encodable object into plain JSON data (arrays -> nested lists).

    Non-finite floats, in arrays or alone, become ``"NaN"``, ``"Infinity"``, ``"-Infinity"``,
    so ``json.dumps(..., allow_nan=False)`` always succeeds.

    Returns:
        dicts, lists, str, int, float, bool and None only.

    Raises:
        WireError: a value that :func:`encode` would reject too (named by key path).
    """
    if isinstance(obj, Mapping):
        out = {}
        for key, value in obj.items():
            if not isinstance(key, str):
                raise WireError(f"{_at(_path)}keys must be str, got {key!r} ({type(key).__name__})")
            out[key] = to_jsonable(value, _path + (key,))
        return out
    if isinstance(obj, np.ndarray):
        arr = _prepare_array(obj, _path)
        if arr.dtype.kind == "f" and not np.isfinite(arr).all():
            boxed = arr.astype(object)
            boxed[np.isnan(arr)] = "NaN"
            boxed[np.isposinf(arr)] = "Infinity"
            boxed[np.isneginf(arr)] = "-Infinity"
            return boxed.tolist()
        return arr.tolist()
    if isinstance(obj, np.generic):
        if obj.dtype.kind not in _ALLOWED_KINDS:
            raise WireError(f"{_at(_path)}numpy scalar of dtype {obj.dtype} is not supported")
        return to_jsonable(obj.item(), _path)
    if isinstance(obj, float) and not math.isfinite(obj):
        return _nonfinite_token(obj)
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(item, _path) for item in obj]
    if obj is None or isinstance(obj, (bool, int, float, str)):
        return obj
    raise WireError(f"{_at(_path)}cannot turn a value of type {type(obj).__name__} into JSON")


def _like_dtype(like: Any) -> np.dtype | None:
    """The dtype a ``like`` leaf asks for, or None where it asks for none (a plain value)."""
    if isinstance(like, np.dtype):
        return like
    if isinstance(like, type) and issubclass(like, np.generic):
        return np.dtype(like)
    dtype = getattr(like, "dtype", None)
    return np.dtype(dtype) if isinstance(dtype, np.dtype) else None


def _restore_tokens(node: Any, path: tuple[str, ...]) -> Any:
    if isinstance(node, list):
        return [_restore_tokens(item, path) for item in node]
    if isinstance(node, str):
        if node not in _NONFINITE_TOKENS:
            raise WireError(f"{_at(path)}expected a number, got the string {node!r:.50}")
        return _NONFINITE_TOKENS[node]
    return node


def _to_array(value: Any, dtype: np.dtype, path: tuple[str, ...]) -> np.ndarray:
    if dtype.kind not in _ALLOWED_KINDS:
        raise WireError(f"{_at(path)}cannot build an array of dtype {dtype}")
    if dtype.kind == "f":
        value = _restore_tokens(value, path)
    try:
        raw = np.asarray(value)
    except (ValueError, OverflowError) as exc:
        raise WireError(f"{_at(path)}not a rectangular array of numbers: {exc}") from None
    kind = raw.dtype.kind
    if dtype.kind in "iu" and kind in "fO" and raw.size:
        # Ints beyond int64 make numpy guess float64 or object: look at the values themselves.
        boxed = np.asarray(value, dtype=object)
        if boxed.shape == raw.shape and all(type(x) is int for x in boxed.flat):
            raw, kind = boxed, "i"
    # Which JSON number kinds may become which dtype: never a silent float -> int truncation.
    accepted = {"b": "b", "i": "iu", "u": "iu", "f": "iuf"}[dtype.kind]
    if raw.size and kind not in accepted:
        found = {"b": "bools", "i": "ints", "u": "ints", "f": "floats", "U": "strings"}.get(
            kind, "mixed or non-numeric values"
        )
        raise WireError(f"{_at(path)}expected {dtype} values, got {found}")
    if dtype.kind in "iu" and raw.size:
        info = np.iinfo(dtype)
        lo, hi = int(raw.min()), int(raw.max())
        if lo < info.min or hi > info.max:
            raise WireError(f"{_at(path)}values {lo}..{hi} do not fit in {dtype}")
    return raw.astype(dtype)


def from_jsonable(obj: Any, like: Any = None, _path: tuple[str, ...] = ()) -> Any:
    """Turn JSON data back into what :func:`decode` would give, guided by ``like``.

    ``like`` mirrors ``obj``: a mapping (or a gymnasium ``Dict`` space) recurses; a leaf that
    has a dtype (an array, a gymnasium ``Box``/``Discrete``/..., a numpy dtype or scalar type)
    makes the matching value an array of that dtype, with the non-finite tokens turned back
    into floats. Only the dtype is taken from ``like``: shapes are the caller's to check. So a
    decoded wire message is a valid ``like`` for the JSON form of the same answer. Where
    ``like`` says nothing (missing, None, a plain value), a rectangular list of numbers or
    bools becomes an array of numpy's own dtype, and everything else (strings, empty lists,
    ragged lists) stays as it is.

    Returns:
        dicts of arrays and plain values.

    Raises:
        WireError: a value does not fit the dtype ``like`` asks for (ragged, strings, floats
            for an int dtype, out of range) or a mapping was expected; names the key path.
    """
    spaces = getattr(like, "spaces", None)
    like_map = like if isinstance(like, Mapping) else (spaces if isinstance(spaces, Mapping) else None)
    if like_map is not None:
        if not isinstance(obj, Mapping):
            raise WireError(f"{_at(_path)}expected an object, got {type(obj).__name__}")
        return {key: from_jsonable(value, like_map.get(key), _path + (key,)) for key, value in obj.items()}
    dtype = _like_dtype(like)
    if dtype is not None:
        return _to_array(obj, dtype, _path)
    if isinstance(obj, Mapping):
        return {key: from_jsonable(value, None, _path + (key,)) for key, value in obj.items()}
    if isinstance(obj, list) and obj:
        try:
            arr = np.asarray(obj)
        except (ValueError, OverflowError):
            return obj
        return arr if arr.dtype.kind in "biuf" else obj
    return obj
