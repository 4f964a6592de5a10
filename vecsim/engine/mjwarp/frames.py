"""MuJoCo Warp's rendered pixels as the pod's camera images, laid out on the GPU.

MuJoCo Warp's ray tracer leaves each world's pixels packed (one ``uint32`` ``0xAABBGGRR``-like
word per pixel) in its render context, in the order of the context's precomputed rays: row by
row from the top as MuJoCo Warp builds them, or in tiles once :func:`order_rays` has reordered
them (:func:`ray_order`). :func:`unpack` writes one camera's pixels of every world as
``uint8 [nworld, H, W, 3]`` RGB in the layout the job asks for (``image_orientation``:
``upright``, ``raw`` rows reversed, ``rotate180`` columns reversed), so that one contiguous copy
brings them to the host.

Why tiles: the ray tracer runs one thread a ray, and the 32 threads of a GPU warp walk the
scene's trees together. In row order they are 32 pixels of one row; in 8x4 tiles their rays are
closer together, so they visit more of the same nodes. Every pixel is drawn from the same ray
either way: the images are the same bit for bit, only the order of the work changes.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import warp as wp

from vecsim.config import CameraConfig

FLIPS = {"upright": (0, 0), "raw": (1, 0), "rotate180": (0, 1)}
# The geom groups the CPU engine draws for LIBERO (robosuite's render_visual_mesh on,
# render_collision_mesh off): group 0 holds the collision meshes, group 1 the visual ones.
GEOM_GROUPS = [1, 2]
# Measured on LIBERO-10/0 (bench/bench_mjwarp_render.py, docs/mjwarp.md): without back-face
# culling the ray tracer draws 1.33x faster and the images are the same to 0.01 levels (no camera
# sits inside a geom); without specular highlights the wrist camera is closer to the CPU engine's
# images (mean difference 9.9 levels against 16.3, SSIM 0.89 against 0.85), which have none to
# speak of, and agentview moves by 0.7 levels.
RENDER_SETTINGS = {"enable_backface_culling": False, "enable_specular": False}
# The order the ray tracer draws each camera's pixels in (:func:`ray_order`): tiles of (rows,
# cols), or None for MuJoCo Warp's row order. The images are the same bit for bit either way; 8x8
# tiles drew 4,096 worlds of LIBERO-10/0 at 2x256x256 1.37x faster than rows on an H200 (4x4
# 1.33x, 8x4 1.34x, 16x16 1.30x; bench/bench_mjwarp_render.py, docs/mjwarp.md).
RAY_TILE: tuple[int, int] | None = (8, 8)
# The BVH of each mesh the ray tracer walks: warp's constructor and triangles a leaf (build_mesh_trees), or None for MuJoCo Warp's own (cubql, 2). The same hits, other trees: cubql
# with 4 a leaf drew 1.065x faster than 2 with 8x8 tiles (in row order: 1.04x; 1 a leaf: 0.88x;
# bench/bench_mjwarp_render.py).
MESH_TREES: tuple[str, int] | None = ("cubql", 4)


def ray_order(height: int, width: int, tile: tuple[int, int] | None) -> np.ndarray:
    """``order[j]``: the row-major pixel (``y * width + x``) whose ray is drawn ``j``-th, with
    ``tile = (rows, cols)`` tiles taken row by row over the image and each tile's pixels row by
    row (tiles at the right and bottom edges are cut to the image); ``None``: row order.

    Raises:
        ValueError: a size or tile below 1.
    """
    if height < 1 or width < 1:
        raise ValueError(f"ray_order: image {height}x{width}: both sides must be >= 1")
    pixels = np.arange(height * width, dtype=np.int32).reshape(height, width)
    if tile is None:
        return pixels.reshape(-1)
    rows, cols = tile
    if rows < 1 or cols < 1:
        raise ValueError(f"ray_order: tile {rows}x{cols}: both sides must be >= 1")
    parts = [
        pixels[top : top + rows, left : left + cols].reshape(-1)
        for top in range(0, height, rows)
        for left in range(0, width, cols)
    ]
    return np.concatenate(parts)


def order_rays(rc: Any, height: int, width: int, tile: tuple[int, int] | None) -> wp.array:
    """Reorder the precomputed rays of ``rc`` (every camera ``height`` x ``width``, drawn once a
    pixel) into :func:`ray_order`'s order; return that order on ``rc``'s device, for
    :func:`unpack`. Call once, on a context fresh from ``create_render_context``.

    Raises:
        ValueError: ``rc`` does not hold one precomputed ray per pixel of its cameras (MuJoCo
            Warp's ``use_precomputed_rays`` off, or supersampling on).
    """
    order = ray_order(height, width, tile)
    count = height * width
    total = int(rc.total_rays)
    if total != count * int(rc.nrender) or rc.ray.shape[0] != total or not rc.use_precomputed_rays:
        raise ValueError(
            f"order_rays: the context holds {rc.ray.shape[0]} precomputed rays for {rc.nrender} "
            f"cameras of {height}x{width}; want one a pixel"
        )
    if tile is not None:
        index = np.concatenate([order + camera * count for camera in range(int(rc.nrender))])
        for name in ("ray", "ray_offset"):
            rays = getattr(rc, name)
            rays.assign(rays.numpy()[index])
    return wp.array(order, dtype=wp.int32, device=rc.ray.device)


def render_context(
    mjm: Any,
    nworld: int,
    camera: CameraConfig,
    tile: tuple[int, int] | None = RAY_TILE,
    mesh_trees: tuple[str, int] | None = MESH_TREES,
) -> tuple[Any, Any]:
    """MuJoCo Warp's render context for ``nworld`` worlds of ``mjm`` drawn by ``camera``, as the
    engine draws (``GEOM_GROUPS``, ``RENDER_SETTINGS``, rays in ``tile`` order, ``mesh_trees``),
    and the order its rays draw each camera's pixels in (for :func:`unpack`)."""
    import mujoco_warp as mjw

    rc = mjw.create_render_context(
        mjm,
        nworld=nworld,
        cam_res=(camera.width, camera.height),
        render_rgb=True,
        render_depth=False,
        cam_active=list(camera.names),
        enabled_geom_groups=GEOM_GROUPS,
        **RENDER_SETTINGS,
    )
    if mesh_trees is not None:
        build_mesh_trees(mjm, rc, *mesh_trees)
    return rc, order_rays(rc, camera.height, camera.width, tile)


def build_mesh_trees(mjm: Any, rc: Any, constructor: str, leaf_size: int) -> None:
    """Give every mesh of ``rc`` a BVH built by warp's ``constructor`` with ``leaf_size``
    triangles a leaf, in place of the ones ``create_render_context`` built (MuJoCo Warp 4.0.0:
    ``cubql``, 2 a leaf). The same triangles in other trees: the ray tracer finds the same hits
    (the render kernels read ``rc.mesh_bvh_id`` at each launch)."""
    from mujoco_warp._src import bvh

    registry, ids = {}, []
    for mesh_id in range(mjm.nmesh):
        mesh, _ = bvh.build_mesh_bvh(mjm, mesh_id, constructor=constructor, leaf_size=leaf_size)
        registry[mesh.id] = mesh  # the context keeps each mesh alive while its id is in use
        ids.append(mesh.id)
    rc.mesh_registry = registry
    rc.mesh_bvh_id = wp.array(ids, dtype=wp.uint64, device=rc.mesh_bvh_id.device)


@wp.kernel
def _unpack_rgb(
    packed: wp.array2d(dtype=wp.uint32),
    first: int,
    order: wp.array(dtype=wp.int32),
    height: int,
    width: int,
    flip_rows: int,
    flip_cols: int,
    out: wp.array4d(dtype=wp.uint8),
):
    world, ray = wp.tid()
    pixel = order[ray]
    x = pixel % width
    y = pixel // width
    if flip_rows != 0:
        y = height - 1 - y
    if flip_cols != 0:
        x = width - 1 - x
    word = packed[world, first + ray]
    out[world, y, x, 0] = wp.uint8((word >> wp.uint32(16)) & wp.uint32(0xFF))
    out[world, y, x, 1] = wp.uint8((word >> wp.uint32(8)) & wp.uint32(0xFF))
    out[world, y, x, 2] = wp.uint8(word & wp.uint32(0xFF))


def unpack(
    packed: wp.array, first: int, order: wp.array, height: int, width: int, orientation: str, out: wp.array
) -> None:
    """Write the camera whose pixels start at ``first`` in ``packed``, drawn in ``order``
    (:func:`order_rays`), into ``out``."""
    flip_rows, flip_cols = FLIPS[orientation]
    wp.launch(
        _unpack_rgb,
        dim=(packed.shape[0], height * width),
        device=packed.device,
        inputs=[packed, int(first), order, height, width, flip_rows, flip_cols],
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
        unpack(rc.rgb_data, first[index], batch.ray_order, height, width, orientation, batch.pixels)
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
