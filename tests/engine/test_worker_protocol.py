"""The messages between a pod and its worker processes (``vecsim.engine.protocol``): messages on a real pipe,
and run orders in binary. The behaviour they carry (steps, resets, errors, dead and hung workers)
is specified in test_sim*.py and test_faults*.py on real workers."""

from __future__ import annotations

import multiprocessing
import os
import threading

import gymnasium
import numpy as np
import pytest

from vecsim.engine.protocol import Order, decode_run, encode_run, receive, send

BOX = gymnasium.spaces.Box(-1.0, 1.0, (2, 3), np.float32)


def test_a_message_larger_than_the_pipe_arrives_whole_and_writable() -> None:
    parent, child = multiprocessing.Pipe()
    message = os.urandom(3 * 65536 + 7)
    # The writer blocks until the reader drains the pipe, so it writes from another thread.
    writer = threading.Thread(target=send, args=(child, message[:10], message[10:]))
    writer.start()
    received = receive(parent)
    writer.join()
    assert bytes(received) == message
    received[0] ^= 1  # writable: arrays decoded from a message are writable too
    parent.close()
    child.close()


def test_reading_a_pipe_whose_other_end_closed_is_eof() -> None:
    parent, child = multiprocessing.Pipe()
    child.close()
    with pytest.raises(EOFError):
        receive(parent)
    parent.close()


def test_a_chunk_step_order_round_trips_with_its_dtype_shape_and_recorded_envs() -> None:
    actions = np.arange(2 * 4 * 6, dtype=np.float32).reshape(2, 4, 2, 3) / 10
    order = Order(np.array([3, 1]), actions=actions, record=np.array([False, True]))
    decoded = decode_run(bytearray(encode_run(order)), BOX)
    assert decoded.local_indices.tolist() == [3, 1]
    assert decoded.actions.dtype == np.float32 and decoded.actions.shape == (2, 4, 2, 3)
    np.testing.assert_array_equal(decoded.actions, actions)
    assert decoded.record.tolist() == [False, True]
    assert decoded.actions.flags.writeable
    assert (decoded.state_ids, decoded.seeds, decoded.options) == (None, None, None)


def test_a_step_order_of_discrete_actions_keeps_the_spaces_integer_dtype() -> None:
    space = gymnasium.spaces.Discrete(5)
    order = Order(np.array([0]), actions=np.array([[4]], dtype=space.dtype))
    decoded = decode_run(bytearray(encode_run(order)), space)
    assert decoded.actions.dtype == space.dtype and decoded.actions.tolist() == [[4]]
    assert decoded.record is None


@pytest.mark.parametrize("dtype", ["float64", "float16", ">f8", "int8", "uint64", "bool"])
def test_a_step_order_carries_the_dtype_its_actions_were_sent_in(dtype: str) -> None:
    # A float32 Box space: float64 actions (as a user sends them) reach the worker as float64.
    actions = (np.arange(12).reshape(2, 1, 2, 3) % 2).astype(dtype)
    decoded = decode_run(bytearray(encode_run(Order(np.array([0, 1]), actions=actions))), BOX)
    assert decoded.actions.dtype == np.dtype(dtype).newbyteorder("=")
    np.testing.assert_array_equal(decoded.actions, actions)


def test_reset_orders_round_trip_state_ids_and_seeds_with_none_as_minus_one() -> None:
    states = decode_run(bytearray(encode_run(Order(np.array([0, 2]), state_ids=np.array([7, 0])))), BOX)
    assert (states.local_indices.tolist(), states.state_ids.tolist(), states.seeds, states.actions) == (
        [0, 2],
        [7, 0],
        None,
        None,
    )
    seeds = decode_run(bytearray(encode_run(Order(np.array([1]), seeds=np.array([-1])))), BOX)
    assert (seeds.seeds.tolist(), seeds.state_ids, seeds.options) == ([-1], None, None)


def test_a_seeded_reset_with_options_is_not_binary() -> None:
    assert encode_run(Order(np.array([0]), seeds=np.array([3]), options={"x_init": 0.5})) is None
