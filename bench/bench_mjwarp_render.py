"""MuJoCo Warp's ray tracer on a LIBERO scene: what a render costs, what its settings buy, and
whether physics overlaps it on the GPU.

The ``mjwarp`` engine draws both LIBERO cameras of every world once per chunk; at 2x256x256 that
render, not physics, bounds the engine (docs/mjwarp.md). This bench takes one exported scene
(``vecsim.engine.mjwarp.scene``), puts ``--worlds`` worlds at its recorded init states, and times
``refit_bvh`` + ``render`` of both cameras, all worlds, for each variant:

- ``default``: MuJoCo Warp's own settings (textures, vertex normals, specular, emission,
  per-light ambient, back-face culling; no shadows);
- ``engine``: the ``mjwarp`` engine's (``vecsim.engine.mjwarp.frames.RENDER_SETTINGS``, its rays
  in ``RAY_TILE`` tiles, its meshes' trees ``MESH_TREES``); ``rows``: the same settings, rays in
  MuJoCo Warp's row order and its trees (the engine before tiles);
- one of those shading terms off at a time, and ``plain`` with all of them off;
- ``lowpoly``: MuJoCo Warp's settings, drawn from meshes simplified on a 5 mm grid
  (``vecsim.engine.mesh_lod``, the CPU engine's ``lowpoly`` preset), physics untouched;
- ``mesh_sah``, ``mesh_sah_leaf1``, ``mesh_sah_leaf4``, ``mesh_lbvh``: the engine's settings, each
  mesh's BVH built again by warp's SAH (leaf sizes 2, 1, 4) or LBVH constructor in place of the
  one MuJoCo Warp 4.0.0 builds (``cubql``, leaf size 2): the same triangles, other trees;
  ``mesh_cubql_leaf1``, ``mesh_cubql_leaf4``: ``cubql`` trees of other leaf sizes;
- ``tile4x4``, ``tile8x4``, ``tile8x8``, ``tile16x16``: the engine's settings with each camera's
  rays drawn in tiles of that many rows x columns (``vecsim.engine.mjwarp.frames.ray_order``)
  in place of row order; ``block32``, ``block128``, ``block256``: the engine's settings with the
  ray tracer launched in blocks of that many threads (MuJoCo Warp's ``block_dim.render``, 64).
  These change the order of the work only: each also reports whether its images of the first
  ``--compare`` worlds are bit for bit the ``engine`` variant's (``same_as_engine``);
- several of the above joined by ``+`` (``tile8x8+block32``): their options together.

With ``--reference`` (the CPU engine's trajectories and images from ``bench_mjwarp.py
reference``), each variant also draws the reference's recorded poses at its image marks, at the
reference's size, and reports per camera the mean absolute difference and SSIM against the CPU
engine's images (the poses differ by one physics substep from where the CPU sampled them, the
same for every variant).

``overlap``: one action's physics (25 steps of a second set of worlds, captured as a CUDA graph,
launched 8 times on a second stream) against one render on the first stream, each alone and
both launched together. ``both_s`` near ``max`` would mean the GPU runs them side by side; near
``sum``, that each fills it::

    python bench/bench_mjwarp_render.py --worlds 1024 --size 256 --reference ref.npz --out render.json

Runs in the ``mjwarp`` extra's environment on a GPU. The JSON record is written after every
variant, so a run cut short still leaves one.
"""

from __future__ import annotations

import argparse
import functools
import json
import logging
import platform
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from lib.images import ssim

from vecsim.config import LiberoProtocol

log = logging.getLogger("bench_mjwarp_render")

# The cameras the mjwarp engine serves for LIBERO (bench_mjwarp.py draws the same).
CAMERAS = ("agentview", "robot0_eye_in_hand")

# The shading terms MuJoCo Warp's render context can leave out at compile time (4.0.0).
SHADING = ("enable_vertex_normals", "enable_specular", "enable_emission", "enable_per_light_ambient")
LOWPOLY_CELL_M = 0.005
TILES = ((4, 4), (8, 4), (8, 8), (16, 16))
BLOCK_DIMS = (32, 128, 256)
# Variants that reorder the work only: their images must be the engine's bit for bit.
SAME_IMAGES = ("rows", "tile", "block", "mesh_")


def variants() -> dict[str, dict[str, Any]]:
    """Each variant's render-context keywords; ``lowpoly`` is marked by a key of its own."""
    from vecsim.engine.mjwarp.frames import MESH_TREES, RAY_TILE, RENDER_SETTINGS

    engine = dict(RENDER_SETTINGS) | {"ray_tile": RAY_TILE} | ({"mesh_bvh": MESH_TREES} if MESH_TREES else {})
    out: dict[str, dict[str, Any]] = {"default": {}, "engine": engine}
    out["rows"] = dict(RENDER_SETTINGS)
    for term in SHADING:
        out["no_" + term.removeprefix("enable_")] = {term: False}
    out["no_backface_culling"] = {"enable_backface_culling": False}
    out["plain"] = {term: False for term in SHADING} | {"enable_backface_culling": False}
    out["lowpoly"] = {"lowpoly": LOWPOLY_CELL_M}
    for name, constructor, leaf in (("mesh_sah", "sah", 2), ("mesh_sah_leaf1", "sah", 1), ("mesh_sah_leaf4", "sah", 4)):
        out[name] = dict(RENDER_SETTINGS) | {"mesh_bvh": (constructor, leaf)}
    out["mesh_lbvh"] = dict(RENDER_SETTINGS) | {"mesh_bvh": ("lbvh", 2)}
    for leaf in (1, 4):
        out[f"mesh_cubql_leaf{leaf}"] = dict(RENDER_SETTINGS) | {"mesh_bvh": ("cubql", leaf)}
    for rows, cols in TILES:
        out[f"tile{rows}x{cols}"] = dict(RENDER_SETTINGS) | {"ray_tile": (rows, cols)}
    for threads in BLOCK_DIMS:
        out[f"block{threads}"] = dict(RENDER_SETTINGS) | {"block_dim": threads}
    return out


def combined(known: dict[str, dict[str, Any]], name: str) -> dict[str, Any]:
    """The options of ``a+b+...``: those of each named variant, later ones over earlier ones.

    Raises:
        ValueError: a part that is not a known variant.
    """
    parts = name.split("+")
    unknown = [part for part in parts if part not in known]
    if unknown:
        raise ValueError(f"{name!r}: unknown {unknown}")
    out: dict[str, Any] = {}
    for part in parts:
        out |= known[part]
    return out


def mesh_stats(mjm: Any) -> dict[str, Any]:
    """Triangles of the scene's meshes drawn by the engine's geom groups."""
    from vecsim.engine.mjwarp.frames import GEOM_GROUPS

    drawn = {
        int(mjm.geom_dataid[g])
        for g in range(mjm.ngeom)
        if mjm.geom_type[g] == 7 and int(mjm.geom_group[g]) in GEOM_GROUPS and mjm.geom_rgba[g][3] > 0
    }
    faces = sorted((int(mjm.mesh_facenum[m]) for m in drawn), reverse=True)
    return {"meshes_drawn": len(faces), "faces_drawn": int(sum(faces)), "largest": faces[:8]}


def image_scores(got: np.ndarray, want: np.ndarray) -> dict[str, float]:
    """Mean absolute difference (levels) and mean SSIM of uint8 images ``[n, H, W, 3]``."""
    return {
        "mad": float(np.abs(got.astype(np.int16) - want.astype(np.int16)).mean()),
        "ssim": float(ssim(got, want).mean()),
    }


class Scene:
    """One exported scene on the GPU: the host model and device worlds at recorded states."""

    def __init__(self, task: str) -> None:
        import mujoco
        import mujoco_warp as mjw

        from vecsim.engine.mjwarp.scene import load_scene, scene_dir

        self.scene = load_scene(scene_dir(task, LiberoProtocol()))
        self.mjm = mujoco.MjModel.from_xml_path(str(self.scene.xml))
        states = self.scene.states
        self.mjm.body_pos[:], self.mjm.body_quat[:] = states["body_pos"][0], states["body_quat"][0]
        self.model = mjw.put_model(self.mjm)

    def worlds(self, qpos: np.ndarray) -> Any:
        """Device worlds at ``qpos`` (one row a world), kinematics computed."""
        import mujoco_warp as mjw
        import warp as wp

        from vecsim.engine.mjwarp.settings import MjwarpSettings

        settings = MjwarpSettings.from_env()  # the engine's contact and constraint rows
        data = mjw.make_data(self.mjm, nworld=len(qpos), nconmax=settings.nconmax, njmax=settings.njmax)
        data.qpos.assign(qpos.astype(np.float32))
        mjw.forward(self.model, data)
        wp.synchronize()
        return data

    def context(self, nworld: int, size: int, options: dict[str, Any]) -> tuple[Any, Any, Any]:
        """A render context for ``nworld`` worlds, the device model to draw with and the order
        its rays draw each camera's pixels in (``frames.order_rays``)."""
        import mujoco_warp as mjw

        from vecsim.engine import mesh_lod
        from vecsim.engine.mjwarp import frames
        from vecsim.engine.mjwarp.frames import GEOM_GROUPS

        options = dict(options)
        cell = options.pop("lowpoly", None)
        mesh_bvh = options.pop("mesh_bvh", None)
        tile = options.pop("ray_tile", None)
        threads = options.pop("block_dim", None)

        def make() -> Any:
            return mjw.create_render_context(
                self.mjm,
                nworld=nworld,
                cam_res=(size, size),
                render_rgb=True,
                render_depth=False,
                cam_active=list(CAMERAS),
                enabled_geom_groups=GEOM_GROUPS,
                **options,
            )

        if cell is None:
            rc = make()
            if mesh_bvh is not None:
                frames.build_mesh_trees(self.mjm, rc, *mesh_bvh)
            model = self.model
            if threads is not None:
                model = mjw.put_model(self.mjm)  # its own launch settings, the shared model's untouched
                model.block_dim.render = threads
            return rc, model, frames.order_rays(rc, size, size, tile)
        simplified = mesh_lod.simplify_meshes(self.mjm, cell)
        with mesh_lod.drawn_with(self.mjm, simplified):
            # The mesh arrays the render kernels read must be the simplified ones as well.
            rc = make()
            return rc, mjw.put_model(self.mjm), frames.order_rays(rc, size, size, None)


def draw(model: Any, data: Any, rc: Any) -> None:
    import mujoco_warp as mjw

    mjw.refit_bvh(model, data, rc)
    mjw.render(model, data, rc)


def seconds(launch: Callable[[], None], reps: int) -> float:
    """Mean seconds of ``launch`` on the GPU, after one untimed call (compiles, warms)."""
    import warp as wp

    launch()
    wp.synchronize()
    started = time.perf_counter()
    for _ in range(reps):
        launch()
    wp.synchronize()
    return (time.perf_counter() - started) / reps


def images(rc: Any, order: Any, size: int, worlds: int | None = None) -> dict[str, np.ndarray]:
    """Each camera's images of the first ``worlds`` worlds of ``rc`` (every world: ``None``), as
    the engine serves them."""
    import warp as wp

    from vecsim.engine.mjwarp import frames

    orientation = LiberoProtocol().image_orientation
    first = rc.rgb_adr.numpy()
    out = {}
    for index, name in enumerate(CAMERAS):
        pixels = wp.zeros((rc.rgb_data.shape[0], size, size, 3), dtype=wp.uint8, device=rc.rgb_data.device)
        frames.unpack(rc.rgb_data, first[index], order, size, size, orientation, pixels)
        out[name] = pixels[:worlds].numpy() if worlds is not None else pixels.numpy()
    return out


def same_images(got: dict[str, np.ndarray], want: dict[str, np.ndarray]) -> dict[str, Any]:
    """Whether each camera's images are ``want``'s bit for bit, and the largest difference."""
    out: dict[str, Any] = {}
    for name, image in want.items():
        diff = np.abs(got[name].astype(np.int16) - image.astype(np.int16))
        out[name] = {
            "equal": bool(not diff.any()),
            "max_levels": int(diff.max()),
            "pixels_differ": int((diff > 0).any(-1).sum()),
        }
    out["equal"] = all(entry["equal"] for entry in out.values())
    return out


def against_reference(scene: Scene, options: dict[str, Any], ref: Any) -> dict[str, Any]:
    """Draw the reference's recorded poses at its image marks; score against its CPU images."""
    marks = [int(t) for t in ref["image_marks"]]
    size = int(ref[f"image.{CAMERAS[0]}"].shape[2])
    qpos = ref["qpos"][:, marks].reshape(-1, ref["qpos"].shape[-1])
    data = scene.worlds(qpos)
    rc, model, order = scene.context(len(qpos), size, options)
    draw(model, data, rc)
    got = images(rc, order, size)
    return {name: image_scores(got[name], ref[f"image.{name}"].reshape(got[name].shape)) for name in CAMERAS}


def overlap(scene: Scene, data: Any, rc: Any, nworld: int, actions: int, reps: int) -> dict[str, float]:
    """One render against ``actions`` actions of physics on a second stream, alone and together."""
    import mujoco_warp as mjw
    import warp as wp

    other = scene.worlds(scene.scene.states["qpos"][np.arange(nworld) % scene.scene.num_states])
    stream = wp.Stream(wp.get_device())
    with wp.ScopedStream(stream):
        mjw.step(scene.model, other)  # loads the kernels before the capture
        wp.synchronize()
        wp.capture_begin()
        for _ in range(25):
            mjw.step(scene.model, other)
        graph = wp.capture_end()

    def physics() -> None:
        for _ in range(actions):
            wp.capture_launch(graph, stream=stream)

    def render() -> None:
        draw(scene.model, data, rc)

    def both() -> None:
        physics()
        render()

    alone_physics, alone_render, together = (seconds(f, reps) for f in (physics, render, both))
    return {
        "actions": actions,
        "physics_s": alone_physics,
        "render_s": alone_render,
        "both_s": together,
        "sum_s": alone_physics + alone_render,
        "max_s": max(alone_physics, alone_render),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--task", default="libero_10/0")
    parser.add_argument("--worlds", type=int, default=1024)
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--reps", type=int, default=4)
    parser.add_argument("--variants", default=",".join(variants()), help="comma-separated, of: " + ",".join(variants()))
    parser.add_argument("--reference", type=Path, help="the CPU engine's record (bench_mjwarp.py reference)")
    parser.add_argument("--no-overlap", action="store_true")
    parser.add_argument("--compare", type=int, default=64, help="worlds whose images are checked against engine's")
    parser.add_argument("--machine", default=platform.node())
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    known = variants()
    chosen = [name.strip() for name in args.variants.split(",") if name.strip()]
    try:
        known |= {name: combined(known, name) for name in chosen if "+" in name}
    except ValueError as exc:
        parser.error(f"--variants: {exc}")
    unknown = [name for name in chosen if name not in known]
    if unknown:
        parser.error(f"--variants: unknown {unknown}; known: {sorted(known)}, or several joined by '+'")

    import warp as wp

    wp.init()
    scene = Scene(args.task)
    ref = np.load(args.reference) if args.reference else None
    states = scene.scene.states["qpos"]
    data = scene.worlds(states[np.arange(args.worlds) % len(states)])
    record: dict[str, Any] = {
        "task": args.task,
        "machine": args.machine,
        "gpu": wp.get_device().name,
        "worlds": args.worlds,
        "size": args.size,
        "cameras": list(CAMERAS),
        "reps": args.reps,
        "reference": str(args.reference) if args.reference else None,
        "meshes": mesh_stats(scene.mjm),
        "variants": {},
    }
    engine_images = None
    for name in chosen:
        started = time.perf_counter()
        try:
            rc, model, order = scene.context(args.worlds, args.size, known[name])
            render_s = seconds(functools.partial(draw, model, data, rc), args.reps)
            entry: dict[str, Any] = {
                "options": known[name],
                "render_s": render_s,
                "world_renders_per_s": args.worlds / render_s,
            }
            compare = min(args.compare, args.worlds)
            if name == "engine":
                engine_images = images(rc, order, args.size, compare)
            elif all(part.startswith(SAME_IMAGES) for part in name.split("+")) and engine_images is not None:
                entry["same_as_engine"] = same_images(images(rc, order, args.size, compare), engine_images)
            if name == "engine":
                import mujoco_warp as mjw

                entry["refit_s"] = seconds(functools.partial(mjw.refit_bvh, model, data, rc), args.reps)
            if ref is not None:
                entry["vs_cpu_images"] = against_reference(scene, known[name], ref)
            if name == "default" and not args.no_overlap:
                record["overlap"] = overlap(scene, data, rc, args.worlds, actions=8, reps=args.reps)
        except Exception as exc:  # a variant this MuJoCo Warp cannot draw is recorded, not fatal
            entry = {"options": known[name], "error": f"{type(exc).__name__}: {exc}"}
        entry["wall_s"] = time.perf_counter() - started
        record["variants"][name] = entry
        for base in ("default", "engine"):
            if "render_s" in record["variants"].get(base, {}) and "render_s" in entry:
                entry[f"speedup_vs_{base}"] = record["variants"][base]["render_s"] / entry["render_s"]
        log.info("%s: %s", name, {k: v for k, v in entry.items() if k != "options"})
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(record, indent=1))
    print("RESULT", json.dumps(record))


if __name__ == "__main__":
    main()
