"""The figures ``bench/bench_mjwarp.py`` reports beyond plain differences, checked here: SSIM
(against Wang et al.'s index computed window by window) and the rotation between two
quaternions (against scipy's rotations); and its layouts' syntax."""

from __future__ import annotations

import argparse


import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from support.bench_scripts import bench_import


@pytest.fixture(scope="module")
def bench():
    with bench_import("bench_mjwarp") as module:
        yield module


def windowed_ssim(x: np.ndarray, y: np.ndarray, window: int = 7) -> float:
    """SSIM of two single-channel images, one 7x7 window at a time, averaged."""
    c1, c2 = (0.01 * 255) ** 2, (0.03 * 255) ** 2
    values = []
    for i in range(x.shape[0] - window + 1):
        for j in range(x.shape[1] - window + 1):
            a, b = x[i : i + window, j : j + window], y[i : i + window, j : j + window]
            cov = ((a - a.mean()) * (b - b.mean())).sum() / (a.size - 1)
            values.append(
                (2 * a.mean() * b.mean() + c1)
                * (2 * cov + c2)
                / ((a.mean() ** 2 + b.mean() ** 2 + c1) * (a.var(ddof=1) + b.var(ddof=1) + c2))
            )
    return float(np.mean(values))


def test_ssim_is_the_windowed_index_averaged_over_channels(bench):
    rng = np.random.default_rng(0)
    first = rng.integers(0, 256, (2, 12, 10, 3), dtype=np.uint8)
    second = np.clip(first.astype(int) + rng.integers(-40, 40, first.shape), 0, 255).astype(np.uint8)
    want = [
        np.mean([windowed_ssim(first[k, ..., c].astype(float), second[k, ..., c].astype(float)) for c in range(3)])
        for k in range(2)
    ]
    np.testing.assert_allclose(bench.ssim(first, second), want, rtol=1e-10)
    np.testing.assert_allclose(bench.ssim(first, first), [1.0, 1.0])


def test_rotation_between_is_scipys_relative_rotation(bench):
    first, second = Rotation.random(20, random_state=1), Rotation.random(20, random_state=2)
    # MuJoCo orders quaternions (w, x, y, z); scipy (x, y, z, w).
    wxyz = [np.roll(r.as_quat(), 1, axis=-1) for r in (first, second)]
    np.testing.assert_allclose(bench.rotation_between(*wxyz), (first.inv() * second).magnitude(), atol=1e-12)
    # q and -q are the same rotation.
    np.testing.assert_allclose(bench.rotation_between(wxyz[0], -wxyz[0]), 0.0, atol=1e-12)


def test_layouts_name_pods_envs_an_optional_size_and_turns(bench):
    assert bench.layout_spec("2x512") == (2, 512, None, False)
    assert bench.layout_spec("1x1024@0") == (1, 1024, 0, False)
    assert bench.layout_spec("2x2048/turns") == (2, 2048, None, True)
    assert bench.layout_spec("2x1024@128/turns") == (2, 1024, 128, True)
    with pytest.raises(ValueError):
        bench.layout_spec("2x")
    with pytest.raises(argparse.ArgumentTypeError, match="the only option is /turns"):
        bench.layout_spec("2x512/fast")


def test_a_rounds_ratio_is_its_best_mjwarp_over_its_best_cpu_at_the_size(bench):
    layouts = [
        {"engine": "cpu", "size": 256, "env_steps_per_s": 1200.0, "round": 0},
        {"engine": "cpu", "size": 256, "env_steps_per_s": 1500.0, "round": 0},
        {"engine": "mjwarp", "size": 256, "env_steps_per_s": 13800.0, "round": 0},
        # Another size, a failed layout and another round's figures are not this round's ratio.
        {"engine": "mjwarp", "size": 128, "env_steps_per_s": 26000.0, "round": 0},
        {"engine": "mjwarp", "size": 256, "error": "pod 1 never ready", "round": 0},
        {"engine": "cpu", "size": 256, "env_steps_per_s": 1000.0, "round": 1},
        {"engine": "mjwarp", "size": 256, "env_steps_per_s": 12000.0, "round": 1},
    ]
    assert bench.round_ratio(layouts, 0, 256) == pytest.approx(13800.0 / 1500.0)
    assert bench.round_ratio(layouts, 1, 256) == pytest.approx(12.0)
    # A round with one engine measured has no ratio.
    assert bench.round_ratio(layouts[:2], 0, 256) is None
    assert bench.round_ratio(layouts, 2, 256) is None


def test_rounds_are_a_whole_number_of_at_least_one(bench):
    assert bench.rounds_spec("3") == 3
    for bad in ("0", "-1", "1.5", "two", ""):
        with pytest.raises(argparse.ArgumentTypeError, match="at least 1"):
            bench.rounds_spec(bad)
