"""A call's answer read from the rows its workers left (vecsim/engine/answers.py), alone: no
workers, the same arrays a pool's shared memory holds. The pool's own tests (test_sim*.py) run
these through real workers; here each rule is shown on rows built to exercise it."""

from __future__ import annotations

import numpy as np

from vecsim.engine.answers import EnvRows, chunk_result, reset_answer
from vecsim.engine.errors import EnvError
from vecsim.engine.worker import REWARD, SUCCESS, TERMINATED, TRUNCATED


def _rows(n: int, k: int) -> np.ndarray:
    rows = np.zeros((n, k, 4))
    rows[:, :, REWARD] = np.arange(n * k).reshape(n, k)
    return rows


def test_an_env_stops_at_its_first_termination_or_truncation_and_one_that_never_did_applied_all_k():
    rows = _rows(3, 4)
    rows[0, 1, TERMINATED] = 1
    rows[1, 2, TRUNCATED] = 1
    rows[1, 3, TERMINATED] = 1
    result = chunk_result(EnvRows({"state": np.zeros((3, 2))}, rows, [{}] * 3, []), np.zeros(0, np.int64), False, None)
    assert result.num_steps.tolist() == [2, 3, 4]
    assert result.reward.tolist() == rows[:, :, REWARD].tolist()
    assert result.terminated[0].tolist() == [False, True, False, False]


def test_stepping_past_the_end_counts_every_action_applied():
    rows = _rows(2, 3)
    rows[:, 0, TERMINATED] = 1
    result = chunk_result(EnvRows({"state": np.zeros((2, 2))}, rows, [{}] * 2, []), np.zeros(0, np.int64), True, None)
    assert result.num_steps.tolist() == [3, 3]
    assert result.terminated[:, 0].all()


def test_the_rows_of_a_refill_split_into_the_stepped_and_the_reset_envs_each_numbered_from_zero():
    rows = _rows(5, 2)
    rows[3, 0, SUCCESS] = 1
    obs = {"state": np.arange(10.0).reshape(5, 2)}
    errors = [EnvError(1, "ValueError", "stepped"), EnvError(4, "RuntimeError", "reset")]
    info = [{"row": i} for i in range(5)]
    stepped, reset = EnvRows(obs, rows, info, errors).split(3)
    assert stepped.obs["state"].tolist() == obs["state"][:3].tolist()
    assert stepped.errors == [errors[0]] and stepped.env_info == info[:3]
    assert reset.obs["state"].tolist() == obs["state"][3:].tolist()
    assert reset.errors == [EnvError(1, "RuntimeError", "reset")] and reset.env_info == info[3:]
    reset_obs, reset_info = reset_answer(reset, ["tiny/lift", "tiny/lift"])
    assert reset_obs is reset.obs
    assert reset_info["success"].tolist() == [True, False]
    assert reset_info["task_id"] == ["tiny/lift", "tiny/lift"]
