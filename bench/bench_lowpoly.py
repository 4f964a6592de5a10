"""The ``lowpoly`` preset's trade: picture quality against triangles and render cost, per grid cell.

For each scene (LIBERO-10 tasks, robosuite Lift) at one state, renders both cameras with the
model's meshes (``lean``) and with meshes simplified on grids of ``--cells`` metres (``lean``'s
passes, :mod:`vecsim.engine.mesh_lod`), and reports per cell: the triangles kept, the time to simplify,
the quality against the full meshes (PSNR and mean absolute difference, per camera), and the
render cost. On Mesa the cost is CPU seconds per frame of this process (llvmpipe's threads are
its own), which the other load of a shared machine hardly moves; with ``--wall`` it is
wall-clock frames/s (on a GPU).

    python bench/bench_lowpoly.py                                   # here, 256x256, Mesa
    python bench/bench_lowpoly.py --wall --tasks libero_10/0        # on the GPU machine

Writes out/bench/lowpoly_<tag>.json and docs/img/render_lowpoly.png (full meshes against the
``lowpoly`` preset's, the LIBERO scenes' two cameras), and prints ``RESULT {json}``.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import time
from typing import Any

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np
from lib.images import quality
from lib.records import img_dir, write_result

from vecsim.engine import mesh_lod
from vecsim.engine.batch_render import BatchRenderer, CameraView
from vecsim.config import CameraConfig, LiberoProtocol
from vecsim.engine.render import LOWPOLY_CELL, PRESETS
from vecsim.engine.tasks import make_env

# LIBERO scenes drawn upright at the state a reset sets, as the other scenes are (no settle steps).
AS_SET = LiberoProtocol(image_orientation="upright", settle_steps=0)

log = logging.getLogger("bench.lowpoly")

CAMERAS = ("agentview", "robot0_eye_in_hand")


def render_rate(renderer: BatchRenderer, views: list[CameraView], seconds: float, wall: bool) -> float:
    """Return frames per second of ``renderer`` on ``views``: per wall second, or per CPU second."""
    renderer.render(views)
    frames, started, cpu = 0, time.perf_counter(), time.process_time()
    while time.perf_counter() - started < seconds or frames < 3 * len(views):
        renderer.render(views)
        frames += len(views)
    spent = time.perf_counter() - started if wall else time.process_time() - cpu
    return frames / spent


def measure(task: str, size: int, cells: list[float], seconds: float, wall: bool) -> tuple[dict[str, Any], dict]:
    """Return one scene's rows (full meshes first, then one per cell) and its pictures by cell."""
    env = make_env(task, CameraConfig(names=CAMERAS, height=size, width=size), "lean", libero=AS_SET)
    try:
        env.reset(options={"state_id": 0})
        views = env.camera_views
        model = views[0].model

        def run(preset: Any) -> tuple[np.ndarray, float]:
            renderer = BatchRenderer(size, size, preset)
            renderer.attach(model, len(views))
            try:
                return renderer.render(views).copy(), render_rate(renderer, views, seconds, wall)
            finally:
                renderer.close()

        reference, base = run("lean")
        rows: list[dict[str, Any]] = [{"cell_m": None, "faces": int(model.mesh_facenum.sum()), "frames_per_s": base}]
        pictures = {None: reference}
        for cell in cells:
            started = time.perf_counter()
            simplified = mesh_lod.simplify_meshes(model, cell)
            simplify_s = time.perf_counter() - started
            images, rate = run(dataclasses.replace(PRESETS["lowpoly"], mesh_cell=cell))
            pictures[cell] = images
            rows.append(
                {
                    "cell_m": cell,
                    "faces": simplified.faces_after,
                    "simplify_s": round(simplify_s, 3),
                    "frames_per_s": rate,
                    "speedup": round(rate / base, 2),
                    **quality(reference, images),
                }
            )
            log.info("%s cell %g: %s", task, cell, rows[-1])
        return {"rows": rows}, pictures
    finally:
        env.close()


def side_by_side(pictures: dict[str, dict], cell: float) -> str:
    """Save full meshes against ``cell``'s, a row per LIBERO scene; return the image's path."""
    from PIL import Image, ImageDraw

    rows = [
        np.concatenate([*shots[None], *shots[cell]], axis=1) for task, shots in pictures.items() if "libero" in task
    ]
    grid = Image.fromarray(np.concatenate(rows, axis=0))
    draw = ImageDraw.Draw(grid)
    width = rows[0].shape[1] // 4
    for index, task in enumerate(t for t in pictures if "libero" in t):
        top = index * rows[0].shape[0]
        draw.text((4, top + 2), f"{task}: full meshes", fill=(255, 0, 0))
        draw.text((2 * width + 4, top + 2), f"lowpoly ({cell * 1000:g} mm grid)", fill=(255, 0, 0))
    path = img_dir() / "render_lowpoly.png"
    grid.save(path)
    return str(path)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--tasks", default="libero_10/0,libero_10/5,libero_10/2,robosuite/Lift")
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--cells", default="0.002,0.003,0.004,0.005,0.006,0.008,0.01", help="grids, metres")
    parser.add_argument("--seconds", type=float, default=2.0, help="per measurement")
    parser.add_argument("--wall", action="store_true", help="wall-clock frames/s (a GPU), not CPU-time ones")
    parser.add_argument("--tag", default="cpu", help="suffix of the JSON's name")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    cells = sorted({float(c) for c in args.cells.split(",") if c} | {LOWPOLY_CELL})
    scenes, pictures = {}, {}
    for task in (t for t in args.tasks.split(",") if t):
        scenes[task], pictures[task] = measure(task, args.size, cells, args.seconds, args.wall)
    image = side_by_side(pictures, LOWPOLY_CELL) if any("libero" in t for t in pictures) else None
    summary = {
        "size": args.size,
        "rate": "wall-clock frames/s" if args.wall else "frames per CPU second of the process",
        "lowpoly_cell_m": LOWPOLY_CELL,
        "scenes": scenes,
        "image": image,
    }
    write_result(f"lowpoly_{args.tag}", summary, {"args": vars(args)})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
