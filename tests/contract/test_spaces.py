"""vecsim.spaces: gymnasium spaces survive a trip through JSON text; bad descriptions name the field."""

from __future__ import annotations

import json
from typing import Any

import numpy as np
import pytest
from gymnasium import spaces
from hypothesis import given, settings
from hypothesis import strategies as st

from vecsim.spaces import space_from_json, space_to_json


def trip(space: spaces.Space) -> spaces.Space:
    """Through strict JSON text and back, as /v1/info carries it."""
    return space_from_json(json.loads(json.dumps(space_to_json(space), allow_nan=False)))


def robot_observation_space(height: int = 32, width: int = 32) -> spaces.Dict:
    """The observation layout of docs/api.md."""
    image = spaces.Box(0, 255, (height, width, 3), np.uint8)
    return spaces.Dict(
        [
            ("images", spaces.Dict([("agentview", image), ("robot0_eye_in_hand", image)])),
            ("proprio", spaces.Box(-np.inf, np.inf, (23,), np.float32)),
        ]
    )


@pytest.mark.parametrize(
    "space",
    [
        spaces.Box(-1, 1, (7,), np.float32),
        spaces.Box(0, 255, (4, 5, 3), np.uint8),
        spaces.Box(-np.inf, np.inf, (3,), np.float64),
        spaces.Box(np.array([0.0, -1.5, -np.inf], np.float32), np.array([1.0, np.inf, 2.25], np.float32)),
        spaces.Box(np.iinfo(np.int64).min, np.iinfo(np.int64).max, (2,), np.int64),
        spaces.Box(-2, 2, (), np.float16),
        spaces.Discrete(5),
        spaces.Discrete(3, start=-1),
        spaces.MultiBinary(6),
        spaces.MultiBinary([2, 3]),
        spaces.MultiDiscrete([3, 4, 5]),
        spaces.MultiDiscrete(np.array([[2, 3], [4, 5]]), start=np.array([[0, 1], [-2, 3]])),
        robot_observation_space(),
        spaces.Tuple([spaces.Discrete(2), spaces.Box(-1, 1, (), np.float64)]),
        spaces.Dict({"a": spaces.Tuple([spaces.MultiBinary(3), spaces.Dict({"b": spaces.Discrete(4)})])}),
    ],
    ids=repr,
)
def test_space_equals_itself_after_a_trip_through_json_text(space: spaces.Space) -> None:
    assert trip(space) == space


def test_box_keeps_its_dtype_and_exact_bounds() -> None:
    low = np.array([0.1, -3.3], np.float32)
    back = trip(spaces.Box(low, np.array([0.2, 7.7], np.float32)))
    assert back.dtype == np.float32
    assert back.low.tobytes() == low.tobytes()


def test_infinite_bounds_are_strict_json_strings() -> None:
    described = space_to_json(spaces.Box(-np.inf, np.inf, (23,), np.float32))
    assert described["low"] == "-Infinity" and described["high"] == "Infinity"
    json.dumps(described, allow_nan=False)


def test_uniform_bounds_are_written_once_not_per_element() -> None:
    described = space_to_json(spaces.Box(0, 255, (128, 128, 3), np.uint8))
    assert described == {"type": "Box", "dtype": "uint8", "shape": [128, 128, 3], "low": 0, "high": 255}


def test_dict_keys_keep_their_order_at_every_level() -> None:
    space = spaces.Dict(
        [
            ("proprio", spaces.Box(-1, 1, (2,))),
            ("images", spaces.Dict([("z", spaces.Discrete(2)), ("a", spaces.Discrete(3))])),
        ]
    )
    back = trip(space)
    assert list(back.spaces) == ["proprio", "images"]
    assert list(back["images"].spaces) == ["z", "a"]


box_specs = st.fixed_dictionaries(
    {
        "dtype": st.sampled_from([np.float16, np.float32, np.float64, np.int8, np.int32, np.uint8, np.int64]),
        "shape": st.lists(st.integers(1, 4), max_size=3).map(tuple),
        "seed": st.integers(0, 2**32 - 1),
        "uniform": st.booleans(),
    }
)


@settings(max_examples=60, deadline=None)
@given(box_specs)
def test_random_boxes_round_trip(spec: dict[str, Any]) -> None:
    rng = np.random.default_rng(spec["seed"])
    dtype, shape = np.dtype(spec["dtype"]), spec["shape"]
    if spec["uniform"]:
        low, high = (-np.inf, np.inf) if dtype.kind == "f" else (0, 10)
    else:
        spread = rng.standard_normal(shape) * 10 if dtype.kind == "f" else rng.integers(0, 50, shape)
        low = spread.astype(dtype)
        high = (low.astype(np.float64) + rng.integers(0, 50, shape)).astype(dtype)
    space = spaces.Box(low, high, shape, dtype)
    back = trip(space)
    assert back == space
    assert back.low.tobytes() == space.low.tobytes() and back.high.tobytes() == space.high.tobytes()


@pytest.mark.parametrize(
    "space",
    [spaces.Sequence(spaces.Discrete(2)), spaces.Text(5)],
    ids=["Sequence", "Text"],
)
def test_unsupported_spaces_are_refused_naming_the_type(space: spaces.Space) -> None:
    with pytest.raises(ValueError, match=f"space: {type(space).__name__} is not supported"):
        space_to_json(space)


def test_unsupported_space_inside_a_dict_is_named_by_its_path() -> None:
    space = spaces.Dict({"obs": spaces.Dict({"text": spaces.Text(4)})})
    with pytest.raises(ValueError, match=r"space\.spaces\.obs\.spaces\.text: Text is not supported"):
        space_to_json(space)


BOX = {"type": "Box", "dtype": "float32", "shape": [2], "low": -1, "high": 1}


@pytest.mark.parametrize(
    ("description", "problem"),
    [
        ([1, 2], "space: expected an object, got list"),
        ({"type": "Text"}, r"space\.type: 'Text' is not one of"),
        ({"type": "Tuple", "spaces": {"a": BOX}}, r"space\.spaces: expected a list, got dict"),
        ({"shape": [2]}, r"space\.type: None is not one of"),
        ({"type": "Box", "dtype": "float32"}, r"space: a Box needs exactly the fields .* missing \['high', 'low'"),
        ({**BOX, "seed": 3}, r"unknown \['seed'\]"),
        ({**BOX, "dtype": "object"}, r"space\.dtype: 'object' is not a usable dtype"),
        ({**BOX, "dtype": 5}, r"space\.dtype: 5 is not a usable dtype"),
        ({**BOX, "shape": 2}, r"space\.shape: expected a list of ints"),
        ({**BOX, "shape": [2.5]}, r"space\.shape: expected int64 values, got floats"),
        ({**BOX, "shape": [-1]}, r"space: not a valid Box"),
        ({**BOX, "low": "low"}, r"space\.low: expected a number, got the string 'low'"),
        ({**BOX, "high": "NaN"}, r"space\.high: NaN is not a bound"),
        ({**BOX, "low": 2}, r"space: not a valid Box: .*low values must be less than or equal to high"),
        ({**BOX, "low": [0, 0, 0]}, r"space: not a valid Box: .*shape"),
        ({"type": "Discrete", "n": 0, "start": 0, "dtype": "int64"}, r"space: not a valid Discrete"),
        ({"type": "Discrete", "n": "3", "start": 0, "dtype": "int64"}, r"space\.n: expected int64 values, got strings"),
        ({"type": "Discrete", "n": [3], "start": 0, "dtype": "int64"}, r"space\.n: expected an int"),
        ({"type": "Discrete", "n": 3, "start": 0, "dtype": "float32"}, r"space\.dtype: 'float32' is not a usable"),
        ({"type": "MultiBinary", "n": -1}, r"space: not a valid MultiBinary"),
        ({"type": "MultiDiscrete", "nvec": [0], "start": [0], "dtype": "int64"}, r"space: not a valid MultiDiscrete"),
        ({"type": "Dict", "spaces": [BOX]}, r"space\.spaces: expected an object, got list"),
        (
            {"type": "Dict", "spaces": {"images": {"type": "Dict", "spaces": {"agentview": {**BOX, "low": "x"}}}}},
            r"space\.spaces\.images\.spaces\.agentview\.low: expected a number",
        ),
    ],
)
def test_bad_descriptions_raise_value_error_naming_the_field(description: Any, problem: str) -> None:
    with pytest.raises(ValueError, match=problem):
        space_from_json(description)
