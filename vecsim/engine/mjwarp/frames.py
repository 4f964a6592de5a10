"""MuJoCo Warp's rendered pixels as the pod's camera images, laid out on the GPU.

MuJoCo Warp's ray tracer leaves each world's pixels packed (one ``uint32`` ``0xAABBGGRR``-like
word per pixel, row 0 at the top) in its render context. :func:`unpack` writes one camera's
pixels of every world as ``uint8 [nworld, H, W, 3]`` RGB in the layout the job asks for
(``image_orientation``: ``upright``, ``raw`` rows reversed, ``rotate180`` columns reversed), so
that one contiguous copy brings them to the host.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import warp as wp

FLIPS = {"upright": (0, 0), "raw": (1, 0), "rotate180": (0, 1)}


@wp.kernel
def _unpack_rgb(
    packed: wp.array2d(dtype=wp.uint32),
    first: int,
    height: int,
    width: int,
    flip_rows: int,
    flip_cols: int,
    out: wp.array4d(dtype=wp.uint8),
):
    world, pixel = wp.tid()
    x = pixel % width
    y = pixel // width
    if flip_rows != 0:
        y = height - 1 - y
    if flip_cols != 0:
        x = width - 1 - x
    word = packed[world, first + pixel]
    out[world, y, x, 0] = wp.uint8((word >> wp.uint32(16)) & wp.uint32(0xFF))
    out[world, y, x, 1] = wp.uint8((word >> wp.uint32(8)) & wp.uint32(0xFF))
    out[world, y, x, 2] = wp.uint8(word & wp.uint32(0xFF))


def unpack(packed: wp.array, first: int, height: int, width: int, orientation: str, out: wp.array) -> None:
    """Write the camera whose pixels start at ``first`` in ``packed`` into ``out``."""
    flip_rows, flip_cols = FLIPS[orientation]
    wp.launch(
        _unpack_rgb,
        dim=(packed.shape[0], height * width),
        device=packed.device,
        inputs=[packed, int(first), height, width, flip_rows, flip_cols],
        outputs=[out],
    )


def writers(images: dict[str, np.ndarray], start: int, count: int, worlds: np.ndarray) -> tuple[Callable, Callable]:
    """``(take, into)`` for :func:`draw` that put the named ``worlds`` of a batch (envs ``start``
    to ``start + count`` of ``images``, each camera's ``uint8 [num_envs, H, W, 3]``) into
    ``images``: straight from the GPU when every world is named; else only the named worlds, from
    the batch's buffer (the others were put back, their pixels are stale)."""
    every = worlds.size == count

    def into(name: str) -> np.ndarray | None:
        return images[name][start : start + count] if every else None

    def take(name: str, pixels: np.ndarray) -> None:
        if not every:
            images[name][worlds + start] = pixels[worlds]

    return take, into


def draw(
    batch: Any,
    cameras: Sequence[str],
    height: int,
    width: int,
    orientation: str,
    take: Callable,
    into: Callable | None = None,
) -> None:
    """Draw every world of ``batch`` (MuJoCo Warp has no world mask) from the kinematics its
    cameras see (``batch.view``, copied where LIBERO samples), and bring each camera's images of
    every world, ``uint8 [nworld, H, W, 3]``, to the host: into ``into(camera)`` where that gives
    a C-contiguous array of that shape (page-locked host memory makes it one copy from the GPU),
    else into the batch's pinned buffer, which the next camera overwrites. Then
    ``take(camera, images)`` is called with the array they landed in."""
    import mujoco_warp as mjw

    # The data's own kinematics are recomputed by the next step1 or reset: they may be overwritten.
    for name, view in batch.view.items():
        wp.copy(getattr(batch.data, name), view)
    rc = batch.render
    mjw.refit_bvh(batch.model, batch.data, rc)
    mjw.render(batch.model, batch.data, rc)
    first = rc.rgb_adr.numpy()
    for index, camera in enumerate(cameras):
        unpack(rc.rgb_data, first[index], height, width, orientation, batch.pixels)
        target = into(camera) if into is not None else None
        if target is None:
            wp.copy(batch.host, batch.pixels)
        else:
            if target.shape != tuple(batch.pixels.shape) or target.dtype != np.uint8 or not target.flags.c_contiguous:
                raise ValueError(
                    f"into({camera!r}): want a C-contiguous uint8 {tuple(batch.pixels.shape)}, got {target.shape}"
                )
            wp.copy(wp.array(target, dtype=wp.uint8, device="cpu", copy=False), batch.pixels)
        wp.synchronize_device(batch.pixels.device)
        take(camera, batch.host.numpy() if target is None else target)
