"""vecsim.wire: the binary codec and its JSON helpers, as specified in docs/api.md."""

from __future__ import annotations

import json
import math
import struct
import tracemalloc
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from vecsim import wire
from vecsim.wire import WireError

DTYPES = [
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
]

FUZZ = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])

keys = st.text(min_size=0, max_size=8)
arrays = st.sampled_from(DTYPES).flatmap(
    lambda dt: hnp.arrays(dt, hnp.array_shapes(min_dims=0, max_dims=4, min_side=0, max_side=5))
)
scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(2**70), max_value=2**70),
    st.floats(allow_nan=False, allow_infinity=False),
    st.text(max_size=10),
)
leaves = st.one_of(scalars, st.lists(st.one_of(scalars, st.lists(scalars, max_size=3)), max_size=4))
messages = st.recursive(
    st.dictionaries(keys, st.one_of(arrays, leaves), max_size=4),
    lambda children: st.dictionaries(keys, st.one_of(children, arrays, leaves), max_size=4),
    max_leaves=12,
)


def step_payload(n: int = 4) -> dict[str, Any]:
    """A small version of what a pod answers to /v1/step."""
    rng = np.random.default_rng(0)
    return {
        "env_indices": np.arange(n, dtype=np.int32),
        "obs": {
            "images": {"agentview": rng.integers(0, 255, (n, 8, 8, 3), dtype=np.uint8)},
            "proprio": rng.standard_normal((n, 23)).astype(np.float32),
        },
        "reward": np.zeros(n, np.float32),
        "terminated": np.zeros(n, bool),
        "truncated": np.zeros(n, bool),
        "info": {"success": np.zeros(n, bool), "task_id": ["tiny/lift"] * n},
    }


def assert_same(a: Any, b: Any, where: str = "<root>") -> None:
    """Structural equality: same keys, arrays equal in dtype, shape and bytes, lists for tuples."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and set(a) == set(b), where
        for key in a:
            assert_same(a[key], b[key], f"{where}/{key}")
    elif isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray), where
        assert a.dtype.newbyteorder("=") == b.dtype.newbyteorder("=") and a.shape == b.shape, where
        assert np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), where
    elif isinstance(a, (list, tuple)):
        assert isinstance(b, list) and len(a) == len(b), where
        for x, y in zip(a, b):
            assert_same(x, y, where)
    else:
        assert type(a) is type(b) and a == b, where


def hostile(header: Any, payload: bytes = b"", header_bytes: bytes | None = None) -> bytes:
    """A message with a hand-written header, laid out as the format says."""
    raw = json.dumps(header).encode() if header_bytes is None else header_bytes
    head = struct.pack("<4sI", wire.MAGIC, len(raw)) + raw
    return head + bytes(-len(head) % wire.ALIGN) + payload


def array_header(**overrides: Any) -> dict[str, Any]:
    spec = {"path": ["x"], "dtype": "<f4", "shape": [2], "offset": 0, "nbytes": 8}
    spec.update(overrides)
    return {"v": 1, "arrays": [spec], "values": {}}


# ------------------------------------------------------------------------------ round trips


@FUZZ
@given(messages)
def test_any_nested_dict_of_arrays_and_leaves_round_trips(obj: dict[str, Any]) -> None:
    assert_same(obj, wire.decode(wire.encode(obj)))


@FUZZ
@given(messages)
def test_encode_parts_concatenate_to_encode(obj: dict[str, Any]) -> None:
    parts = wire.encode_parts(obj)
    assert b"".join(parts) == wire.encode(obj)
    assert sum(len(p) for p in parts) == len(wire.encode(obj))


def test_step_payload_round_trips() -> None:
    payload = step_payload()
    assert_same(payload, wire.decode(wire.encode(payload)))


def test_a_repeated_header_decodes_to_fresh_values_each_time() -> None:
    # decode keeps the checks of a header it has seen; what it returns must still be new objects.
    message = wire.encode({"task_id": ["a", "b"], "reward": np.arange(2.0)})
    first = wire.decode(message)
    first["task_id"].append("c")
    first["reward"] = None
    second = wire.decode(message)
    assert second["task_id"] == ["a", "b"]
    np.testing.assert_array_equal(second["reward"], [0.0, 1.0])


def test_a_seen_header_over_a_shorter_payload_is_refused() -> None:
    message = wire.encode({"x": np.zeros(64, np.uint8)})
    wire.decode(message)
    with pytest.raises(WireError, match="outside"):
        wire.decode(message[:-1])


def test_decoded_arrays_are_read_only() -> None:
    decoded = wire.decode(bytearray(wire.encode(step_payload())))
    proprio = decoded["obs"]["proprio"]
    assert not proprio.flags.writeable
    with pytest.raises(ValueError):
        proprio[0, 0] = 1.0


def test_decoded_arrays_are_views_into_the_buffer_not_copies() -> None:
    buf = bytearray(wire.encode({"x": np.zeros(16, np.uint8)}))
    decoded = wire.decode(buf)
    buf[-16:] = bytes(range(16))  # the last 16 bytes of the message are x's data
    assert decoded["x"].tolist() == list(range(16))


def test_encode_parts_hand_out_the_arrays_own_memory() -> None:
    arr = np.arange(1000, dtype=np.float64)
    parts = wire.encode_parts({"a": arr})
    assert any(isinstance(p, memoryview) and np.shares_memory(np.frombuffer(p, np.uint8), arr) for p in parts)


def test_array_data_starts_on_64_byte_boundaries() -> None:
    buf = wire.encode({"a": np.ones(3, np.uint8), "b": np.ones(5, np.float64), "c": np.ones((2, 3), np.int16)})
    (header_len,) = struct.unpack_from("<I", buf, 4)
    header = json.loads(buf[8 : 8 + header_len])
    assert all(spec["offset"] % 64 == 0 for spec in header["arrays"])
    assert header["arrays"][0]["dtype"] == "<u1"


def test_header_lists_every_array_and_keeps_leaves_under_values() -> None:
    buf = wire.encode(step_payload(2))
    (header_len,) = struct.unpack_from("<I", buf, 4)
    header = json.loads(buf[8 : 8 + header_len])
    paths = {tuple(spec["path"]) for spec in header["arrays"]}
    assert ("obs", "images", "agentview") in paths and ("env_indices",) in paths
    assert header["values"]["info"] == {"task_id": ["tiny/lift", "tiny/lift"]}


def test_non_contiguous_arrays_travel_as_their_contiguous_values() -> None:
    base = np.arange(60, dtype=np.int32).reshape(6, 10)
    view = base[::2, 1::3].T
    decoded = wire.decode(wire.encode({"v": view}))["v"]
    assert decoded.shape == view.shape and np.array_equal(decoded, view)


def test_zero_dimensional_and_zero_size_arrays_keep_their_shapes() -> None:
    decoded = wire.decode(wire.encode({"s": np.array(3.5), "e": np.zeros((0, 7), np.float32)}))
    assert decoded["s"].shape == () and decoded["s"] == 3.5
    assert decoded["e"].shape == (0, 7) and decoded["e"].dtype == np.float32


def test_big_endian_arrays_arrive_with_the_same_values() -> None:
    arr = np.arange(5, dtype=">i4")
    assert wire.decode(wire.encode({"a": arr}))["a"].tolist() == [0, 1, 2, 3, 4]


def test_numpy_scalars_travel_as_plain_values() -> None:
    decoded = wire.decode(wire.encode({"r": np.float32(0.5), "n": np.int64(3), "b": np.bool_(True)}))
    assert decoded == {"r": 0.5, "n": 3, "b": True}


def test_empty_message_is_a_valid_message() -> None:
    assert wire.decode(wire.encode({})) == {}


def test_content_type_is_the_documented_one() -> None:
    assert wire.CONTENT_TYPE == "application/x-vecsim"


# ---------------------------------------------------------------------------- encode refuses


@pytest.mark.parametrize(
    ("value", "dtype_name"),
    [
        (np.array(["a", "b"]), "<U1"),
        (np.array([object(), None], dtype=object), "object"),
        (np.zeros(2, dtype="V4"), r"\|V4"),
        (np.zeros(2, dtype=np.complex64), "complex64"),
        (np.array(["2020-01-01"], dtype="datetime64[D]"), "datetime64"),
    ],
)
def test_encode_rejects_disallowed_dtypes_naming_the_key_path(value: np.ndarray, dtype_name: str) -> None:
    with pytest.raises(WireError, match=rf"obs/names: dtype {dtype_name}"):
        wire.encode({"obs": {"names": value}})


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_encode_rejects_non_finite_floats_outside_arrays_naming_the_key_path(bad: float) -> None:
    with pytest.raises(WireError, match="info/score: non-finite float"):
        wire.encode({"info": {"score": bad}})


def test_encode_carries_non_finite_floats_inside_arrays() -> None:
    decoded = wire.decode(wire.encode({"x": np.array([np.nan, np.inf, -np.inf])}))["x"]
    assert np.isnan(decoded[0]) and decoded[1] == np.inf and decoded[2] == -np.inf


@pytest.mark.parametrize("value", [{1, 2}, b"bytes", object(), 1 + 2j])
def test_encode_rejects_unknown_leaf_types_naming_the_key_path(value: Any) -> None:
    with pytest.raises(WireError, match="a/b: cannot encode"):
        wire.encode({"a": {"b": value}})


def test_encode_rejects_arrays_inside_lists() -> None:
    with pytest.raises(WireError, match=r"obs\[1\]: lists may hold only"):
        wire.encode({"obs": [1, np.zeros(2)]})


def test_encode_rejects_non_str_keys() -> None:
    with pytest.raises(WireError, match="keys must be str"):
        wire.encode({"a": {3: np.zeros(1)}})


@pytest.mark.parametrize("top", [[1, 2], np.zeros(3), "text", None])
def test_encode_rejects_a_top_level_that_is_not_a_mapping(top: Any) -> None:
    with pytest.raises(WireError, match="top level must be a mapping"):
        wire.encode(top)


def test_encode_rejects_nesting_deeper_than_the_cap() -> None:
    obj: dict[str, Any] = {}
    node = obj
    for _ in range(wire.MAX_DEPTH + 1):
        node["k"] = {}
        node = node["k"]
    with pytest.raises(WireError, match="nested deeper"):
        wire.encode(obj)


def test_encode_rejects_more_arrays_than_the_cap() -> None:
    obj = {str(i): np.zeros(0) for i in range(wire.MAX_ARRAYS + 1)}
    with pytest.raises(WireError, match="more than the cap"):
        wire.encode(obj)


# ------------------------------------------------------------------- decode refuses hostile bytes


@pytest.mark.parametrize(
    ("buf", "problem"),
    [
        (b"", "truncated message"),
        (b"VSW1\x00\x00", "truncated message"),
        (b"XXXX\x00\x00\x00\x00" + bytes(56), "bad magic"),
        (b"VSW1\xff\xff\xff\x7f" + bytes(56), "over the cap"),
        (b"VSW1\x00\x01\x00\x00" + bytes(56), "runs past the end"),
        (hostile({}, header_bytes=b"{not json")[:-10], "truncated message|header padding"),
        (hostile(None, header_bytes=b"{not json"), "header is not JSON"),
        (hostile(None, header_bytes=b"\xff\xfe{}"), "not UTF-8"),
        (hostile(None, header_bytes=b"[" * 5000 + b"]" * 5000), "deeper|expected an object"),
        (hostile(None, header_bytes=b'{"v":1,"arrays":[],"values":{"a":NaN}}'), "NaN is not valid JSON"),
        (hostile(None, header_bytes=b'{"v":1,"arrays":[],"values":{"a":1e999}}'), "out of range"),
        (hostile([1, 2]), "expected an object with keys"),
        (hostile({"v": 2, "arrays": [], "values": {}}), "unsupported version"),
        (hostile({"v": True, "arrays": [], "values": {}}), "unsupported version"),
        (hostile({"v": 1, "arrays": [], "values": {}, "extra": 1}), "expected an object with keys"),
        (hostile({"v": 1, "arrays": {}, "values": {}}), "'arrays' must be a list"),
        (hostile({"v": 1, "arrays": [], "values": []}), "'values' must be an object"),
        (hostile({"v": 1, "arrays": [], "values": {"a": [{"b": 1}]}}), "a list holds an object"),
        (hostile(array_header(), bytes(4)), "outside the 4-byte payload"),
        (hostile(array_header(offset=64), bytes(64)), "outside the 64-byte payload"),
        (hostile(array_header(offset=8), bytes(64)), "not 64-byte aligned"),
        (hostile(array_header(offset=-64), bytes(64)), "non-negative"),
        (hostile(array_header(nbytes=12), bytes(64)), r"shape \[2\] x itemsize 4 != nbytes 12"),
        (hostile(array_header(shape=[2**40], nbytes=8), bytes(64)), "!= nbytes 8"),
        (hostile(array_header(shape=[-2, -1], nbytes=8), bytes(64)), "negative dimension"),
        (hostile(array_header(shape=[1] * 40, nbytes=4), bytes(64)), "at most 32 ints"),
        (hostile(array_header(shape=[2.0]), bytes(64)), "list of at most"),
        (hostile(array_header(dtype="|O"), bytes(64)), "dtype '|O' is not allowed"),
        (hostile(array_header(dtype="<c8", nbytes=16), bytes(64)), "dtype '<c8' is not allowed"),
        (hostile(array_header(dtype=">f4"), bytes(64)), "dtype '>f4' is not allowed"),
        (hostile(array_header(path=[]), bytes(64)), r"arrays\[0\].path"),
        (hostile(array_header(path=["a", 3]), bytes(64)), r"arrays\[0\].path"),
        (hostile(array_header(path=["k"] * 40), bytes(64)), r"arrays\[0\].path"),
        (hostile({**array_header(), "arrays": ["x"]}, bytes(64)), r"arrays\[0\]: expected an object"),
    ],
)
def test_decode_rejects_malformed_messages_naming_the_problem(buf: bytes, problem: str) -> None:
    with pytest.raises(WireError, match=problem):
        wire.decode(buf)


def test_decode_rejects_more_arrays_than_the_cap() -> None:
    spec = {"path": ["x"], "dtype": "<u1", "shape": [0], "offset": 0, "nbytes": 0}
    with pytest.raises(WireError, match="more than the cap"):
        wire.decode(hostile({"v": 1, "arrays": [spec] * (wire.MAX_ARRAYS + 1), "values": {}}))


def test_decode_rejects_values_nested_deeper_than_the_cap() -> None:
    values: dict[str, Any] = {}
    node = values
    for _ in range(wire.MAX_DEPTH + 2):
        node["k"] = {}
        node = node["k"]
    with pytest.raises(WireError, match="deeper than"):
        wire.decode(hostile({"v": 1, "arrays": [], "values": values}))


def test_decode_rejects_two_arrays_at_one_path() -> None:
    header = array_header()
    header["arrays"].append(dict(header["arrays"][0]))
    with pytest.raises(WireError, match="array x collides"):
        wire.decode(hostile(header, bytes(64)))


def test_decode_rejects_an_array_where_a_value_sits() -> None:
    header = array_header(path=["info", "n"])
    header["values"] = {"info": {"n": 3}}
    with pytest.raises(WireError, match="array info/n collides"):
        wire.decode(hostile(header, bytes(64)))


def test_decode_rejects_an_array_below_a_value() -> None:
    header = array_header(path=["info", "n", "deeper"])
    header["values"] = {"info": {"n": 3}}
    with pytest.raises(WireError, match="collides with the value at info/n"):
        wire.decode(hostile(header, bytes(64)))


def test_decode_rejects_what_is_not_bytes_like() -> None:
    with pytest.raises(WireError, match="expected a bytes-like object, got str"):
        wire.decode("VSW1")  # type: ignore[arg-type]


def test_decode_accepts_bytes_bytearray_and_memoryview_alike() -> None:
    buf = wire.encode(step_payload(2))
    for form in (buf, bytearray(buf), memoryview(buf)):
        assert_same(step_payload(2), wire.decode(form))


def test_every_truncation_of_a_message_is_rejected() -> None:
    buf = wire.encode({"a": np.arange(5, dtype=np.int16), "b": {"c": np.ones((2, 2))}, "n": [1, "x"]})
    for cut in range(len(buf)):
        with pytest.raises(WireError):
            wire.decode(buf[:cut])


def _decode_or_wire_error(buf: bytes) -> None:
    """Decode must answer a dict or raise WireError, and allocate nothing near the claimed sizes."""
    tracemalloc.start()
    try:
        try:
            assert isinstance(wire.decode(buf), dict)
        except WireError:
            pass
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 64 * len(buf) + (1 << 20)


@FUZZ
@given(messages, st.data())
def test_mutated_messages_raise_wire_error_or_decode(obj: dict[str, Any], data: st.DataObject) -> None:
    buf = bytearray(wire.encode(obj))
    for _ in range(data.draw(st.integers(1, 4))):
        index = data.draw(st.integers(0, len(buf) - 1))
        buf[index] = data.draw(st.integers(0, 255))
    _decode_or_wire_error(bytes(buf))


@FUZZ
@given(st.binary(max_size=512))
def test_random_bytes_raise_wire_error(raw: bytes) -> None:
    _decode_or_wire_error(raw)
    _decode_or_wire_error(wire.MAGIC + raw)


json_values = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(-(2**64), 2**64), st.floats(allow_nan=False), st.text(max_size=6)),
    lambda children: st.one_of(
        st.lists(children, max_size=4), st.dictionaries(st.text(max_size=6), children, max_size=4)
    ),
    max_leaves=20,
)
array_specs = st.fixed_dictionaries(
    {
        "path": st.one_of(st.lists(st.sampled_from(["a", "b", "c"]), max_size=3), json_values),
        "dtype": st.one_of(st.sampled_from(["<f4", "<u1", "|b1", "<i8", "<f2", "<O", "f4"]), json_values),
        "shape": st.one_of(st.lists(st.integers(-2, 2**33), max_size=3), json_values),
        "offset": st.one_of(st.sampled_from([0, 64, 128, 7, -64, 2**40]), json_values),
        "nbytes": st.one_of(st.integers(-8, 300), json_values),
    }
)


@FUZZ
@given(
    st.fixed_dictionaries(
        {
            "v": st.one_of(st.just(1), json_values),
            "arrays": st.one_of(st.lists(array_specs, max_size=4), json_values),
            "values": st.one_of(
                st.dictionaries(st.sampled_from(["a", "b", "c"]), json_values, max_size=3), json_values
            ),
        }
    ),
    st.binary(max_size=256),
)
def test_hostile_headers_raise_wire_error_or_decode(header: dict[str, Any], payload: bytes) -> None:
    _decode_or_wire_error(hostile(header, payload))


# ----------------------------------------------------------------------------- JSON helpers


def test_to_jsonable_output_is_strict_json() -> None:
    obj = {"x": np.array([1.0, np.nan, np.inf, -np.inf], np.float32), "s": float("inf"), "n": np.int8(3)}
    text = json.dumps(wire.to_jsonable(obj), allow_nan=False)
    assert json.loads(text) == {"x": [1.0, "NaN", "Infinity", "-Infinity"], "s": "Infinity", "n": 3}


@FUZZ
@given(messages)
def test_json_round_trip_with_like_restores_arrays_exactly(obj: dict[str, Any]) -> None:
    text = json.dumps(wire.to_jsonable(obj), allow_nan=False)
    back = wire.from_jsonable(json.loads(text), like=obj)
    _assert_json_trip(obj, back)


def _assert_json_trip(original: Any, back: Any) -> None:
    if isinstance(original, dict):
        for key in original:
            _assert_json_trip(original[key], back[key])
    elif isinstance(original, np.ndarray):
        restored = back.reshape(original.shape)
        assert restored.dtype == original.dtype.newbyteorder("=")
        assert np.array_equal(restored, original, equal_nan=original.dtype.kind == "f")


def test_from_jsonable_takes_dtypes_from_a_gymnasium_space() -> None:
    from gymnasium import spaces

    space = spaces.Dict(
        {
            "images": spaces.Dict({"a": spaces.Box(0, 255, (1, 2, 3), np.uint8)}),
            "proprio": spaces.Box(-np.inf, np.inf, (2,), np.float32),
        }
    )
    obs = wire.from_jsonable({"images": {"a": [[[[1, 2, 3], [4, 5, 6]]]]}, "proprio": [[0.5, "-Infinity"]]}, like=space)
    assert obs["images"]["a"].dtype == np.uint8 and obs["images"]["a"].shape == (1, 1, 2, 3)
    assert obs["proprio"].dtype == np.float32 and obs["proprio"][0, 1] == -np.inf


def test_from_jsonable_without_like_turns_number_lists_into_arrays_and_leaves_the_rest() -> None:
    out = wire.from_jsonable(
        {"ids": [1, 2], "x": [[0.5], [1.5]], "names": ["a"], "empty": [], "ragged": [[1], [1, 2]], "inf": ["Infinity"]}
    )
    assert out["ids"].dtype == np.int64 and out["x"].shape == (2, 1)
    assert out["names"] == ["a"] and out["empty"] == [] and out["ragged"] == [[1], [1, 2]]
    assert out["inf"] == ["Infinity"]


@pytest.mark.parametrize(
    ("value", "dtype", "problem"),
    [
        ([1.5], np.int64, "expected int64 values, got floats"),
        ([True], np.int64, "expected int64 values, got bools"),
        ([300], np.uint8, "values 300..300 do not fit in uint8"),
        ([-1], np.uint8, "values -1..-1 do not fit in uint8"),
        (["x"], np.float32, "expected a number, got the string 'x'"),
        (["1"], np.int64, "expected int64 values, got strings"),
        ([[1], [1, 2]], np.float32, "not a rectangular array"),
        ([None], np.float32, "expected float32 values, got mixed or non-numeric"),
        ([1], np.bool_, "expected bool values, got ints"),
    ],
)
def test_from_jsonable_rejects_values_that_do_not_fit_naming_the_key(value: Any, dtype: type, problem: str) -> None:
    with pytest.raises(WireError, match=f"actions: {problem}"):
        wire.from_jsonable({"actions": value}, like={"actions": dtype})


def test_from_jsonable_wants_an_object_where_like_has_a_mapping() -> None:
    with pytest.raises(WireError, match="obs: expected an object, got list"):
        wire.from_jsonable({"obs": [1]}, like={"obs": {"proprio": np.float32}})


def test_to_jsonable_rejects_what_the_wire_rejects() -> None:
    with pytest.raises(WireError, match="a: cannot turn a value of type set"):
        wire.to_jsonable({"a": {1}})
