"""The parts of ``bench/bench_mjwarp_render.py`` that need no GPU: its variants turn off what
they name and nothing else, and its image scores are those of ``bench_mjwarp``."""

from __future__ import annotations


import numpy as np
import pytest
from support.bench_scripts import bench_import


@pytest.fixture(scope="module")
def bench():
    with bench_import("bench_mjwarp_render") as module:
        yield module


def test_each_shading_variant_turns_off_only_its_term(bench):
    variants = bench.variants()
    assert variants["default"] == {}
    assert variants["rows"] == {"enable_backface_culling": False, "enable_specular": False}
    assert variants["engine"] == variants["rows"] | {"ray_tile": (8, 8), "mesh_bvh": ("cubql", 4)}
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


def test_order_variants_change_only_the_order_of_the_work(bench):
    variants = bench.variants()
    engine = variants["rows"]
    for rows, cols in bench.TILES:
        assert variants[f"tile{rows}x{cols}"] == engine | {"ray_tile": (rows, cols)}
    for threads in bench.BLOCK_DIMS:
        assert variants[f"block{threads}"] == engine | {"block_dim": threads}
    assert variants["mesh_cubql_leaf1"] == engine | {"mesh_bvh": ("cubql", 1)}
    # Every variant that only reorders the work is checked against the engine's images.
    reordering = [
        name
        for name, options in variants.items()
        if name != "engine" and {"ray_tile", "block_dim", "mesh_bvh"} & set(options)
    ]
    assert reordering and all(name.startswith(bench.SAME_IMAGES) for name in reordering)


def test_same_images_names_the_largest_difference(bench):
    rng = np.random.default_rng(3)
    want = {"a": rng.integers(0, 256, size=(2, 8, 8, 3), dtype=np.uint8)}
    assert bench.same_images({"a": want["a"].copy()}, want) == {
        "a": {"equal": True, "max_levels": 0, "pixels_differ": 0},
        "equal": True,
    }
    got = {"a": want["a"].copy()}
    got["a"][1, 2, 3] = want["a"][1, 2, 3] ^ 5  # one pixel, every channel moved
    report = bench.same_images(got, want)
    assert not report["equal"] and report["a"]["pixels_differ"] == 1 and 1 <= report["a"]["max_levels"] <= 5


def test_variants_joined_by_plus_take_every_parts_options(bench):
    known = bench.variants()
    both = bench.combined(known, "tile8x8+block32+mesh_cubql_leaf4")
    assert both == known["rows"] | {"ray_tile": (8, 8), "block_dim": 32, "mesh_bvh": ("cubql", 4)}
    with pytest.raises(ValueError, match="unknown \\['tile3x3'\\]"):
        bench.combined(known, "tile8x8+tile3x3")
