"""``bench/bench_mjwarp_refill.py``'s bookkeeping: which envs a refill resets call by call, and
how its calls add up to rates and ratios. (The engine calls it times are the pod's, tested in
tests/engine/mjwarp/; the bench ran on warp's CPU device by hand and on the GPU, docs/mjwarp.md.)"""

from __future__ import annotations

import numpy as np
import pytest
from support.bench_scripts import bench_import


@pytest.fixture(scope="module")
def bench():
    with bench_import("bench_mjwarp_refill") as module:
        yield module


def test_the_reset_envs_move_on_by_a_window_and_reach_every_env(bench):
    windows = [bench.reset_window(10, 0.3, call) for call in range(4)]
    assert [w.tolist() for w in windows] == [[0, 1, 2], [3, 4, 5], [6, 7, 8], [9, 0, 1]]
    assert set(np.concatenate(windows).tolist()) == set(range(10))


@pytest.mark.parametrize(
    ("envs", "share", "count"),
    [(8, 0.01, 1), (8, 0.125, 1), (8, 0.5, 4), (8, 0.99, 7), (2, 0.9, 1)],
)
def test_a_refill_resets_at_least_one_env_and_never_all(bench, envs, share, count):
    assert len(bench.reset_window(envs, share, 0)) == count


@pytest.mark.parametrize("share", [0.0, 1.0, -0.5, 2.0])
def test_a_share_outside_zero_to_one_is_refused_by_name(bench, share):
    with pytest.raises(ValueError, match="share"):
        bench.reset_window(8, share, 0)


def test_a_kinds_rate_is_its_steps_over_its_seconds_and_the_ratios_compare_rates(bench):
    def call(seconds, steps, renders):
        return {
            "seconds": seconds,
            "env_steps": steps,
            "physics_s": seconds / 2,
            "render_s": seconds / 4,
            "renders": renders,
        }

    kinds = {
        "step": bench.summary([call(1.0, 80, 8), call(3.0, 80, 8)]),  # 160 steps in 4 s: 40/s
        "refill": bench.summary([call(2.0, 70, 8)]),  # 35/s
        "reset_then_step": bench.summary([call(3.5, 70, 16)]),  # 20/s
    }
    assert kinds["step"] == {
        "calls": 2,
        "env_steps_per_s": 40.0,
        "s_per_call": 2.0,
        "physics_s_per_call": 1.0,
        "render_s_per_call": 0.5,
        "renders_per_call": 8.0,
    }
    assert bench.ratios(kinds) == {"refill_over_reset_then_step": 1.75, "refill_over_step": 0.875}
