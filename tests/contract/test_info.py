"""vecsim.info.batch_infos batches envs' own infos as gymnasium's vector envs do: the real
``VectorEnv._add_info`` of a ``SyncVectorEnv`` is the reference, on infos of real envs and on
batches that leave the column-by-column path (mixed types, missing keys, another key order)."""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np
import pytest
from gymnasium.vector import SyncVectorEnv

from vecsim.info import batch_infos


def gymnasium_batch(infos: list[dict[str, Any]]) -> dict[str, Any]:
    """What gymnasium's own vector env builds of ``infos``, one env's info after the other."""
    vec = SyncVectorEnv([lambda: gymnasium.make("CartPole-v1")] * len(infos))
    try:
        out: dict[str, Any] = {}
        for row, info in enumerate(infos):
            out = vec._add_info(out, info, row)
        return out
    finally:
        vec.close()


def half_cheetah_infos(n: int) -> list[dict[str, Any]]:
    """The info of each of ``n`` HalfCheetah-v5 envs after a random step (numbers of two dtypes)."""
    infos = []
    for i in range(n):
        env = gymnasium.make("HalfCheetah-v5")
        env.reset(seed=i)
        env.action_space.seed(i)
        infos.append(env.step(env.action_space.sample())[4])
        env.close()
    return infos


def assert_same_batch(ours: dict[str, Any], theirs: dict[str, Any]) -> None:
    assert list(ours) == list(theirs)
    for key, value in theirs.items():
        assert ours[key].dtype == value.dtype, key
        np.testing.assert_array_equal(ours[key], value, err_msg=key)


def test_the_infos_of_real_envs_batch_as_gymnasium_batches_them():
    infos = half_cheetah_infos(5)
    assert {type(v) for v in infos[0].values()} == {np.float64, np.float32}
    assert_same_batch(batch_infos(infos), gymnasium_batch(infos))


@pytest.mark.parametrize(
    "infos",
    [
        [{"a": 1}, {"a": 2.5}, {"a": 3}],  # a float into gymnasium's int array (the first env's type)
        [{"a": np.float32(1.5)}, {}, {"a": np.float32(2.5)}],  # one env gave nothing
        [{"a": 1, "b": True}, {"b": False, "a": 3}],  # another key order
        [{"a": 1}, {"a": 2, "c": np.int8(3)}],  # a key only the second env gave
        [{"a": np.int64(7)}, {"a": 8}],  # a numpy number, then a Python one
    ],
    ids=["mixed-types", "empty-info", "key-order", "extra-key", "numpy-then-python"],
)
def test_batches_beside_the_common_case_batch_as_gymnasium_batches_them(infos):
    assert_same_batch(batch_infos(infos), gymnasium_batch(infos))
