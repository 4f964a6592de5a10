"""Where a camera frame's time goes in one scene: a profile of vecsim's batched render path.

For one task (default LIBERO-10 task 0) at one size, this renders the env's cameras in batches
(``--views`` views a batch, the env's cameras repeated, as a worker hosting several envs would)
through :class:`vecsim.engine.batch_render.BatchRenderer` and measures frames/s with one thing changed
at a time:

- ``lean``: the preset as shipped (the baseline of every ratio);
- ``no_textures``: the same with MuJoCo's texture flag off;
- ``no_multisampling``: the offscreen buffer without its 4 samples a pixel;
- ``no_visual_meshes``: geom group 1 hidden (robosuite's visual meshes), what the rest costs;
- ``lowpoly``: the ``lowpoly`` preset as shipped (lean's passes, meshes simplified on a grid of
  ``vecsim.engine.render.LOWPOLY_CELL``), and ``cell=X``: the same on a grid of X metres (``--cells``);
  each also with its picture's quality against ``lean`` (PSNR and mean absolute difference per
  camera, one state) and the triangles its meshes keep;
- ``faces/K``: the visual meshes keep every K-th triangle (a timing proxy for lighter meshes:
  the pictures are not meant to be looked at);
- ``scene_update``: ``mjv_updateScene`` alone (the CPU side of a frame).

It also reports the scene's geometry (meshes, triangles per geom group, textures), the GL
strings, the process's memory at each stage, and the machine's CPU topology.

    python bench/profile_render.py --size 256                 # on the GPU machine (after .device/setup.sh)
    python bench/profile_render.py --size 64 --seconds 0.5    # here (Mesa)

Prints ``RESULT {json}`` and writes out/bench/profile_render[_<tag>].json.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import platform
import subprocess
import time
from collections import Counter
from pathlib import Path
from typing import Any

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco
import numpy as np
import psutil
from lib.images import quality
from lib.records import write_result

from vecsim.engine import mesh_lod
from vecsim.engine.batch_render import BatchRenderer, CameraView, gl_info
from vecsim.config import CameraConfig, LiberoProtocol
from vecsim.engine.render import LOWPOLY_CELL, PRESETS
from vecsim.engine.tasks import make_env

# LIBERO scenes drawn upright at the state a reset sets, as the other scenes are (no settle steps).
AS_SET = LiberoProtocol(image_orientation="upright", settle_steps=0)

log = logging.getLogger("bench.profile_render")

CAMERAS = ("agentview", "robot0_eye_in_hand")
VISUAL_GROUP = 1


def rss_mib() -> float:
    return psutil.Process().memory_info().rss / 2**20


def cpu_topology() -> dict[str, Any]:
    """Threads per core and physical cores, from sysfs (lscpu's text as well when present)."""
    siblings = set()
    for path in Path("/sys/devices/system/cpu").glob("cpu[0-9]*/topology/thread_siblings_list"):
        siblings.add(path.read_text().strip())
    logical = os.cpu_count() or 0
    out: dict[str, Any] = {"logical_cpus": logical, "physical_cores": len(siblings) or None}
    if siblings:
        out["threads_per_core"] = round(logical / len(siblings), 2)
    try:
        out["lscpu"] = subprocess.run(["lscpu"], capture_output=True, text=True, timeout=10).stdout
    except (OSError, subprocess.TimeoutExpired) as exc:
        out["lscpu"] = f"unavailable: {exc}"
    return out


def geometry(model: mujoco.MjModel) -> dict[str, Any]:
    """Meshes, triangles per geom group and the biggest meshes and textures of ``model``."""
    faces_by_group: Counter[int] = Counter()
    meshes = []
    for geom in range(model.ngeom):
        if model.geom_type[geom] == mujoco.mjtGeom.mjGEOM_MESH:
            mesh = model.geom_dataid[geom]
            faces_by_group[int(model.geom_group[geom])] += int(model.mesh_facenum[mesh])
            meshes.append((int(model.mesh_facenum[mesh]), mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_MESH, mesh)))
    textures = sorted(((int(model.tex_width[t]), int(model.tex_height[t])) for t in range(model.ntex)), reverse=True)
    return {
        "geoms": int(model.ngeom),
        "meshes": int(model.nmesh),
        "mesh_vertices": int(model.nmeshvert),
        "mesh_faces": int(model.nmeshface),
        "faces_by_geom_group": {str(k): v for k, v in sorted(faces_by_group.items())},
        "largest_meshes": sorted(meshes, reverse=True)[:8],
        "textures": len(textures),
        "texture_bytes": int(model.tex_data.size),
        "largest_textures": textures[:6],
        "lights": int(model.nlight),
        "lights_casting_shadows": int(np.sum(model.light_castshadow)),
    }


def thin_visual_meshes(model: mujoco.MjModel, keep_every: int) -> int:
    """Keep every ``keep_every``-th triangle of meshes only non-colliding geoms use; return faces left.

    A timing proxy: the faces kept are packed at the start of each mesh's range and its face count
    lowered, so a render context made afterwards uploads fewer triangles.
    """
    colliding = {
        int(model.geom_dataid[g])
        for g in range(model.ngeom)
        if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH and (model.geom_contype[g] or model.geom_conaffinity[g])
    }
    visual = {
        int(model.geom_dataid[g])
        for g in range(model.ngeom)
        if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH and model.geom_group[g] == VISUAL_GROUP
    }
    for mesh in sorted(visual - colliding):
        start, count = int(model.mesh_faceadr[mesh]), int(model.mesh_facenum[mesh])
        kept = model.mesh_face[start : start + count : keep_every].copy()
        model.mesh_face[start : start + len(kept)] = kept
        model.mesh_facenum[mesh] = len(kept)
    return int(
        sum(
            model.mesh_facenum[int(model.geom_dataid[g])]
            for g in range(model.ngeom)
            if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH and model.geom_group[g] == VISUAL_GROUP
        )
    )


def frames_per_s(renderer: BatchRenderer, views: list[CameraView], seconds: float) -> dict[str, float]:
    renderer.render(views)  # makes the context and uploads the assets
    batches, started = 0, time.perf_counter()
    cpu_started = time.process_time()
    while time.perf_counter() - started < seconds:
        renderer.render(views)
        batches += 1
    wall = time.perf_counter() - started
    cpu = time.process_time() - cpu_started
    frames = batches * len(views)
    return {"frames_per_s": frames / wall, "ms_per_frame": 1e3 * wall / frames, "cpu_ms_per_frame": 1e3 * cpu / frames}


def scene_update_ms(views: list[CameraView], seconds: float) -> float:
    scene = mujoco.MjvScene(views[0].model, maxgeom=10_000)
    perturb = mujoco.MjvPerturb()
    count, started = 0, time.perf_counter()
    while time.perf_counter() - started < seconds:
        for view in views:
            mujoco.mjv_updateScene(
                view.model, view.data, view.option, perturb, view.camera, mujoco.mjtCatBit.mjCAT_ALL, scene
            )
        count += len(views)
    return 1e3 * (time.perf_counter() - started) / count


def measure(
    task: str, size: int, views_per_batch: int, seconds: float, keep_every: list[int], cells: list[float]
) -> dict[str, Any]:
    memory = {"start": rss_mib()}
    camera = CameraConfig(names=CAMERAS, height=size, width=size)
    env = make_env(task, camera, "lean", libero=AS_SET)
    env.reset(options={"state_id": 0})
    memory["env_built_and_reset"] = rss_mib()
    model = env.camera_views[0].model
    out: dict[str, Any] = {"gl": gl_info(), "geometry": geometry(model)}
    base_views = env.camera_views
    views = [base_views[i % len(base_views)] for i in range(views_per_batch)]

    def variant(name: str, preset: Any, chosen: list[CameraView]) -> None:
        renderer = BatchRenderer(size, size, preset)
        renderer.attach(model, len(chosen))
        try:
            out[name] = frames_per_s(renderer, chosen, seconds)
        finally:
            renderer.detach(model, len(chosen))
        memory[f"after_{name}"] = rss_mib()
        log.info("%s: %.0f frames/s", name, out[name]["frames_per_s"])

    variant("lean", "lean", views)
    textureless = [dataclasses.replace(v, option=_copy_option(v.option, textures=False)) for v in views]
    variant("no_textures", "lean", textureless)
    variant("no_multisampling", dataclasses.replace(PRESETS["lean"], multisamples=0), views)
    no_visual = [dataclasses.replace(v, option=_copy_option(v.option, hide_group=VISUAL_GROUP)) for v in views]
    variant("no_visual_meshes", "lean", no_visual)
    out["scene_update_ms"] = scene_update_ms(views, seconds)
    reference = _picture(size, "lean", model, base_views)
    for name, cell in [("lowpoly", LOWPOLY_CELL), *((f"cell={c:g}", c) for c in cells)]:
        preset = "lowpoly" if name == "lowpoly" else dataclasses.replace(PRESETS["lowpoly"], mesh_cell=cell)
        started = time.perf_counter()
        simplified = mesh_lod.simplify_meshes(model, cell)
        simplify_s = time.perf_counter() - started
        variant(name, preset, views)
        out[name].update(quality(reference, _picture(size, preset, model, base_views)))
        out[name].update(
            {
                "cell_m": cell,
                "faces_kept": simplified.faces_after,
                "faces_all": simplified.faces_before,
                "simplify_s": round(simplify_s, 3),
            }
        )
    faces_before = geometry(model)["faces_by_geom_group"].get(str(VISUAL_GROUP), 0)
    done = 1
    for k in sorted(keep_every):
        # Thinning is cumulative: keep every (k / done)-th face of what is left.
        left = thin_visual_meshes(model, max(1, k // done))
        done = k
        variant(f"faces/{k}", "lean", views)
        out[f"faces/{k}"]["visual_faces"] = left
    out["visual_faces_full"] = faces_before
    out["memory_mib"] = memory
    env.close()
    return out


def _picture(size: int, preset: Any, model: mujoco.MjModel, views: list[CameraView]) -> np.ndarray:
    renderer = BatchRenderer(size, size, preset)
    renderer.attach(model, len(views))
    try:
        return renderer.render(views)
    finally:
        renderer.detach(model, len(views))


def _copy_option(option: mujoco.MjvOption, textures: bool = True, hide_group: int | None = None) -> mujoco.MjvOption:
    copy = mujoco.MjvOption()
    copy.geomgroup[:] = option.geomgroup
    copy.flags[:] = option.flags
    copy.flags[mujoco.mjtVisFlag.mjVIS_TEXTURE] = int(textures)
    if hide_group is not None:
        copy.geomgroup[hide_group] = 0
    return copy


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--task", default="libero_10/0")
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--views", type=int, default=16, help="views per batch")
    parser.add_argument("--seconds", type=float, default=1.5, help="per variant")
    parser.add_argument("--keep-every", default="4,16", help="thinning factors of the faces/K variants")
    parser.add_argument("--cells", default="0.002,0.004,0.006", help="grids (metres) of the cell=X variants")
    parser.add_argument("--tag", default="", help="suffix of the JSON's name")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    keep = [int(k) for k in args.keep_every.split(",") if k]
    cells = [float(c) for c in args.cells.split(",") if c]
    result = measure(args.task, args.size, args.views, args.seconds, keep, cells)
    base = result["lean"]["frames_per_s"]
    summary = {
        "task": args.task,
        "size": args.size,
        "gl_renderer": result["gl"]["renderer"],
        "lean_frames_per_s": round(base, 1),
        "ratio_to_lean": {
            name: round(result[name]["frames_per_s"] / base, 3)
            for name in result
            if isinstance(result[name], dict) and "frames_per_s" in result[name]
        },
        "scene_update_ms": round(result["scene_update_ms"], 4),
        "lowpoly_quality": {
            name: {key: result[name][key] for key in ("cell_m", "faces_kept", "psnr_db", "mean_abs_diff")}
            for name in result
            if isinstance(result[name], dict) and "psnr_db" in result[name]
        },
    }
    details = {"result": result, "cpu": cpu_topology(), "python": platform.python_version(), "args": vars(args)}
    write_result("profile_render" + (f"_{args.tag}" if args.tag else ""), summary, details)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
