"""The parts of ``bench/bench_mjwarp_render.py`` that need no GPU: its variants turn off what
they name and nothing else, and its image scores are those of ``bench_mjwarp``."""

from __future__ import annotations

import sys

import numpy as np
import pytest
from support import ROOT

BENCH = ROOT / "bench"


@pytest.fixture(scope="module")
def bench():
    sys.path.insert(0, str(BENCH))
    try:
        import bench_mjwarp_render

        yield bench_mjwarp_render
    finally:
        sys.path.remove(str(BENCH))


def test_each_shading_variant_turns_off_only_its_term(bench):
    variants = bench.variants()
    assert variants["default"] == {}
    assert variants["engine"] == {"enable_backface_culling": False, "enable_specular": False}
    for term in bench.SHADING:
        assert variants["no_" + term.removeprefix("enable_")] == {term: False}
    assert variants["plain"] == {term: False for term in bench.SHADING} | {"enable_backface_culling": False}
    assert variants["lowpoly"] == {"lowpoly": bench.LOWPOLY_CELL_M}


def test_image_scores_of_equal_and_of_shifted_images(bench):
    rng = np.random.default_rng(7)
    images = rng.integers(0, 256, size=(3, 16, 16, 3), dtype=np.uint8)
    same = bench.image_scores(images, images)
    assert same["mad"] == 0.0 and same["ssim"] == pytest.approx(1.0)
    brighter = np.clip(images.astype(np.int16) + 10, 0, 255).astype(np.uint8)
    moved = bench.image_scores(brighter, images)
    assert moved["mad"] == pytest.approx(np.abs(brighter.astype(np.int16) - images).mean())
    assert moved["ssim"] < 1.0
