"""The order the ray tracer draws pixels in, and the unpacking of its words, on warp's CPU.

MuJoCo Warp's render context holds one precomputed ray a pixel and writes each ray's colour at
that ray's position. :func:`frames.order_rays` reorders the rays into tiles; :func:`frames.unpack`
must then put every word back at its own pixel, in every orientation, so that a tiled context
serves the images a row-order one would. A stand-in context holds what MuJoCo Warp's would
(rays, packed words): the words written are each ray's pixel, so any misplacement shows. That
the real ray tracer draws the same images bit for bit in both orders runs on the GPU
(``test_mjwarp_gpu.py``).
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import warp as wp

from vecsim.engine.mjwarp import frames

CPU = "cpu"


def _context(height: int, width: int, cameras: int) -> SimpleNamespace:
    """What ``order_rays`` reads of a render context: a ray a pixel, row by row, each camera's
    rays one after the other (a ray is its camera and pixel, to be recognised after a shuffle)."""
    count = height * width
    rays = np.zeros((cameras * count, 3), dtype=np.float32)
    rays[:, 0] = np.repeat(np.arange(cameras), count)
    rays[:, 1] = np.tile(np.arange(count), cameras)
    return SimpleNamespace(
        total_rays=cameras * count,
        nrender=cameras,
        use_precomputed_rays=True,
        ray=wp.array(rays, dtype=wp.vec3, device=CPU),
        ray_offset=wp.array(rays * 2, dtype=wp.vec3, device=CPU),
    )


def _draw(rc: SimpleNamespace, worlds: int) -> wp.array:
    """Packed words as the ray tracer leaves them: at each ray's position, a colour naming the
    world and the ray's pixel (``0x00RRGGBB``: R the world, G and B the pixel)."""
    rays = rc.ray.numpy()
    pixel = rays[:, 1].astype(np.uint32)
    words = np.stack([(np.uint32(w) << 16) | (pixel & 0xFFFF) for w in range(worlds)])
    return wp.array(words, dtype=wp.uint32, device=CPU)


@pytest.mark.parametrize("tile", [None, (8, 4), (8, 8), (5, 3), (64, 64)])
def test_ray_order_visits_every_pixel_once_tile_by_tile(tile):
    height, width = 12, 20
    order = frames.ray_order(height, width, tile)
    assert sorted(order.tolist()) == list(range(height * width))
    if tile is None:
        np.testing.assert_array_equal(order, np.arange(height * width))
        return
    rows, cols = tile
    # The first tile is the top-left corner, cut to the image, row by row.
    first = [y * width + x for y in range(min(rows, height)) for x in range(min(cols, width))]
    assert order[: len(first)].tolist() == first


@pytest.mark.parametrize(("height", "width", "tile"), [(0, 4, None), (4, 4, (0, 2)), (4, 4, (2, -1))])
def test_ray_order_refuses_empty_sizes(height, width, tile):
    with pytest.raises(ValueError, match="must be >= 1"):
        frames.ray_order(height, width, tile)


@pytest.mark.parametrize("orientation", sorted(frames.FLIPS))
@pytest.mark.parametrize("tile", [None, (8, 4), (3, 5)])
def test_tiled_rays_unpack_to_the_pixels_of_row_order(tile, orientation):
    height, width, cameras, worlds = 12, 10, 2, 3
    rows = _context(height, width, cameras)
    want_order = frames.order_rays(rows, height, width, None)
    tiled = _context(height, width, cameras)
    order = frames.order_rays(tiled, height, width, tile)
    # The rays moved as a whole: each camera's block holds that camera's rays, in the new order.
    moved = tiled.ray.numpy().reshape(cameras, height * width, 3)
    np.testing.assert_array_equal(moved[:, :, 0], np.repeat(np.arange(cameras)[:, None], height * width, 1))
    np.testing.assert_array_equal(moved[:, :, 1], np.tile(order.numpy(), (cameras, 1)))
    np.testing.assert_array_equal(tiled.ray_offset.numpy(), tiled.ray.numpy() * 2)

    for camera in range(cameras):
        first = camera * height * width
        want = wp.zeros((worlds, height, width, 3), dtype=wp.uint8, device=CPU)
        got = wp.zeros((worlds, height, width, 3), dtype=wp.uint8, device=CPU)
        frames.unpack(_draw(rows, worlds), first, want_order, height, width, orientation, want)
        frames.unpack(_draw(tiled, worlds), first, order, height, width, orientation, got)
        np.testing.assert_array_equal(got.numpy(), want.numpy())
    # Row order, upright: world w's pixel (y, x) holds w and its own index.
    if orientation == "upright":
        pixels = want.numpy().astype(np.int64)
        index = (pixels[..., 1] << 8) | pixels[..., 2]
        np.testing.assert_array_equal(pixels[..., 0], np.broadcast_to(np.arange(worlds)[:, None, None], index.shape))
        np.testing.assert_array_equal(index[0], np.arange(height * width).reshape(height, width))


def test_order_rays_refuses_a_context_without_a_ray_a_pixel():
    rc = _context(6, 6, 2)
    with pytest.raises(ValueError, match="want one a pixel"):
        frames.order_rays(rc, 6, 7, (2, 2))
    rc.use_precomputed_rays = False
    with pytest.raises(ValueError, match="want one a pixel"):
        frames.order_rays(rc, 6, 6, (2, 2))
    # Nothing was reordered by the refused calls.
    np.testing.assert_array_equal(rc.ray.numpy()[:, 1], np.tile(np.arange(36), 2))
