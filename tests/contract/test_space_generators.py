"""A seeded space keeps its generator through ``/v1/info``: the rebuilt space samples what the
original samples next, judged by gymnasium's own ``sample``."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest
from gymnasium import spaces

from vecsim.spaces import space_from_json, space_to_json, without_rng


def _nested() -> spaces.Dict:
    return spaces.Dict(
        {
            "box": spaces.Box(-1.0, 1.0, (3,), np.float32),
            "pair": spaces.Tuple((spaces.Discrete(5, start=-2), spaces.MultiBinary(4))),
            "counts": spaces.MultiDiscrete([3, 7]),
        }
    )


def _same_samples(a: spaces.Space, b: spaces.Space, n: int = 5) -> bool:
    return all(json.dumps(_plain(a.sample())) == json.dumps(_plain(b.sample())) for _ in range(n))


def _plain(value):
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, tuple):
        return [_plain(v) for v in value]
    return np.asarray(value).tolist()


@pytest.mark.parametrize("advance", [0, 3])
def test_a_seeded_space_samples_on_as_the_original_after_a_trip_through_json_text(advance):
    space = _nested()
    space.seed(11)
    for _ in range(advance):
        space.sample()
    rebuilt = space_from_json(json.loads(json.dumps(space_to_json(space), allow_nan=False)))
    assert rebuilt == space
    assert _same_samples(rebuilt, copy.deepcopy(space))


def test_an_unseeded_space_carries_no_generator():
    assert "rng" not in json.dumps(space_to_json(_nested()))


def test_without_rng_makes_spaces_seeded_apart_describe_alike():
    a, b = _nested(), _nested()
    a.seed(1)
    b.seed(2)
    assert space_to_json(a) != space_to_json(b)
    assert without_rng(space_to_json(a)) == without_rng(space_to_json(b)) == space_to_json(_nested())


def test_a_bad_generator_state_is_named():
    description = space_to_json(spaces.Discrete(3, seed=0))
    description["rng"]["inc"] = "not a number"
    with pytest.raises(ValueError, match=r"space\.rng: not a PCG64 state"):
        space_from_json(description)
