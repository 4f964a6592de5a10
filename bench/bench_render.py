"""Rendering benchmark: the batched render path against MuJoCo's default one, per node.

For each scene (robosuite Lift, a LIBERO-10 scene, gymnasium's Pusher) and two cameras per env,
every process of the node builds ``--envs`` envs and then, in lockstep with the others (a
barrier before each measurement), runs each configuration for ``--seconds``:

- ``render``: frames/s of rendering every camera of every env once per round, through the
  default path (robosuite's or gymnasium's own renderer: one GL context and one readback per
  camera, MuJoCo's default passes) and through vecsim's batched path under each preset (all the
  process's cameras in one batch, one readback; ``lowpoly`` with simplified meshes), with 1
  process and with ``--procs``;
- ``passes``: frames/s of the batched path (1 process) with one pass at a time switched off,
  to tell which pass costs what;
- ``step``: env-steps/s of ``--procs`` processes stepping their envs with physics only, and
  with physics plus rendering through each path: the node is physics-bound when a preset's
  env-steps/s is near the physics-only figure.

It also renders one state of each scene under each preset (a side-by-side image) and checks
that the batched images equal the default path's under the same preset and the same images
rendered one view at a time, bit for bit, on this machine's GL.

    python bench/bench_render.py --gpu            # 256x256, 16 processes of 8 envs
    python bench/bench_render.py --cpu-small      # 64x64, 2 processes of 2 envs (Mesa)

Writes out/bench/render_<gpu|cpu>.json, plots and the frames image to docs/img/ (and copies of
all of them to ``--copy-to``), and prints ``RESULT {json}``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import multiprocessing
import os
import queue
import shutil
import subprocess
import sys
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from lib.records import img_dir, write_result

log = logging.getLogger("bench_render")

SCENES = {"lift": "robosuite/Lift", "libero": "libero_10/0", "pusher": "gym/Pusher-v5"}
PRESETS = ("full", "fast", "lean", "lowpoly")
# Pass variants: the full preset with one thing taken away at a time.
PASSES: dict[str, dict[str, Any]] = {
    "full": {},
    "no reflection": {"reflections": False},
    "no shadow": {"shadows": False, "shadow_size": 0},
    "no skybox": {"skybox": False},
    "shadow map 1024": {"shadow_size": 1024},
    "no multisampling": {"multisamples": 0},
    "lean": {"shadows": False, "shadow_size": 0, "reflections": False, "skybox": False},
    "lean, no multisampling": {
        "shadows": False,
        "shadow_size": 0,
        "reflections": False,
        "skybox": False,
        "multisamples": 0,
    },
}


@dataclasses.dataclass(frozen=True)
class Plan:
    """What one run measures: sizes, counts and how long each measurement lasts."""

    height: int
    width: int
    envs: int
    procs: int
    seconds: float
    scenes: tuple[str, ...]


@dataclasses.dataclass(frozen=True)
class Config:
    """One measurement: ``kind`` render|passes|step, ``path`` default|physics|preset|pass name."""

    kind: str
    path: str
    active: int

    @property
    def label(self) -> str:
        return f"{self.kind}/{self.path}/{self.active}p"


def configs(plan: Plan) -> list[Config]:
    """Return every measurement of one scene, in the order they run."""
    counts = sorted({1, plan.procs})
    out = [Config("render", path, n) for n in counts for path in ("default", *PRESETS)]
    out += [Config("passes", name, 1) for name in PASSES]
    out += [Config("step", path, plan.procs) for path in ("physics", "default", *PRESETS)]
    return out


class Scene:
    """One process's envs of one scene, with every render path over them."""

    def __init__(self, task_id: str, plan: Plan) -> None:
        from vecsim.config import CameraConfig, LiberoProtocol
        from vecsim.engine.tasks import make_env

        self.task_id = task_id
        self.gym = task_id.startswith("gym/")
        names = ("render",) if self.gym else ("agentview", "robot0_eye_in_hand")
        self.camera = CameraConfig(names=names, height=plan.height, width=plan.width)
        # LIBERO scenes drawn as robosuite's own renderer draws them: upright, at the state set.
        protocol = LiberoProtocol(image_orientation="upright", settle_steps=0)
        self.envs = [make_env(task_id, self.camera, "lean", libero=protocol) for _ in range(plan.envs)]
        for index, env in enumerate(self.envs):
            env.defer_images = True
            env.reset(options={"state_id": index})
        self.views = [view for env in self.envs for view in env.camera_views]
        self.renderers: dict[str, Any] = {}
        self._default: list[Callable[[], Any]] | None = None
        self._default_contexts: list[Any] = []
        self.references: list[Any] = []
        self.rng = np.random.default_rng(0)

    def renderer(self, path: str) -> Any:
        """Return (made once) the batch renderer of a preset or pass variant, models attached."""
        from vecsim.engine import render
        from vecsim.engine.batch_render import BatchRenderer

        if path not in self.renderers:
            preset = path if path in PRESETS else dataclasses.replace(render.settings("full"), **PASSES[path])
            renderer = BatchRenderer(self.camera.height, self.camera.width, preset)
            for env in self.envs:
                renderer.attach(env.camera_views[0].model, len(env.camera_views))
            self.renderers[path] = renderer
        return self.renderers[path]

    def release(self, path: str) -> None:
        """Free the batch renderer of ``path`` (LIBERO's textures alone are ~200 MB a context)."""
        renderer = self.renderers.pop(path, None)
        if renderer is not None:
            for env in self.envs:
                renderer.detach(env.camera_views[0].model, len(env.camera_views))
            renderer.close()

    def release_default(self) -> None:
        """Free the default path's GL and render contexts (one per env)."""
        for context in self._default_contexts:
            context.gl_ctx.make_current()
            context.con.free()
            context.gl_ctx.free()
        for env in self.envs:
            if not self.gym:
                env.inner.sim._render_context_offscreen = None
        self._default_contexts, self._default = [], None

    def close(self) -> None:
        """Free every renderer and context, then the envs."""
        for path in list(self.renderers):
            self.release(path)
        self.release_default()
        for env in [*self.references, *self.envs]:
            env.close()

    def default_path(self) -> list[Callable[[], Any]]:
        """Return one callable per camera of every env: the default path's render of it."""
        if self._default is None:
            self._default = [call for env in self.envs for call in self._default_calls(env)]
        return self._default

    def _default_calls(self, env: Any) -> list[Callable[[], Any]]:
        if self.gym:
            viewer = env.inner.unwrapped.mujoco_renderer._get_viewer("rgb_array")

            def gym_render() -> Any:
                # gymnasium renders into whichever GL context is current.
                viewer.make_context_current()
                return env.inner.render()

            return [gym_render]
        from robosuite.utils.binding_utils import MjRenderContextOffscreen

        sim = env.inner.sim
        context = MjRenderContextOffscreen(sim, device_id=-1)
        self._default_contexts.append(context)
        # As robosuite's reset sets them: visual meshes shown, collision meshes hidden.
        context.vopt.geomgroup[0] = 0
        context.vopt.geomgroup[1] = 1
        calls = []
        for name in self.camera.names:

            def robosuite_render(name: str = name) -> Any:
                context.gl_ctx.make_current()
                return sim.render(camera_name=name, width=self.camera.width, height=self.camera.height)

            calls.append(robosuite_render)
        return calls

    def render_round(self, path: str) -> int:
        """Render every camera of every env once through ``path``; return the frames made."""
        if path == "default":
            for call in self.default_path():
                call()
        else:
            self.renderer(path).render(self.views)
        return len(self.views)

    def step_round(self, path: str) -> int:
        """Step every env once (small random actions), then render through ``path``; return steps."""
        for env in self.envs:
            env.step(self.rng.uniform(-0.3, 0.3, env.action_space.shape).astype(np.float32))
        if path != "physics":
            self.render_round(path)
        return len(self.envs)


def _measure(scene: Scene, config: Config, seconds: float) -> tuple[int, float]:
    run = scene.step_round if config.kind == "step" else scene.render_round
    path = config.path
    run(path)  # warm-up: contexts made, caches filled
    count, started = 0, time.perf_counter()
    while time.perf_counter() - started < seconds:
        count += run(path)
    return count, time.perf_counter() - started


def worker(index: int, plan: Plan, barrier: Any, results: Any) -> None:
    """One process of the node: build each scene, measure each config in lockstep, report."""
    logging.basicConfig(level=logging.WARNING)
    from vecsim.engine.batch_render import gl_info

    try:
        results.put(("gl", index, gl_info()))
        for name in plan.scenes:
            scene = Scene(SCENES[name], plan)
            results.put(("built", index, name))
            for config in configs(plan):
                active = index < config.active
                if active:
                    _measure(scene, config, 0.0)
                barrier.wait(timeout=600)
                if active:
                    count, elapsed = _measure(scene, config, plan.seconds)
                    results.put(("rate", index, (name, config.label, count / elapsed)))
                if config.kind == "passes":
                    scene.release(config.path)
                if config.kind == "step" and config.path == "default":
                    scene.release_default()
                barrier.wait(timeout=600)
            scene.close()
    except Exception:
        results.put(("error", index, traceback.format_exc()))
        barrier.abort()


def run_node(plan: Plan, deadline_s: float) -> tuple[dict[str, Any], dict[str, str]]:
    """Run ``plan.procs`` worker processes; return ``{scene: {config label: rate}}`` and GL info."""
    context = multiprocessing.get_context("spawn")
    barrier = context.Barrier(plan.procs)
    results = context.Queue()
    processes = [context.Process(target=worker, args=(i, plan, barrier, results)) for i in range(plan.procs)]
    for process in processes:
        process.start()
    rates: dict[str, dict[str, float]] = {}
    gl: dict[str, str] = {}
    expected = len(plan.scenes) * sum(c.active for c in configs(plan))
    received, stop_at = 0, time.monotonic() + deadline_s
    try:
        while received < expected:
            try:
                kind, index, payload = results.get(timeout=max(1.0, stop_at - time.monotonic()))
            except queue.Empty:
                log.error("deadline of %.0f s reached with %d of %d rates", deadline_s, received, expected)
                break
            if kind == "error":
                log.error("worker %d failed:\n%s", index, payload)
                break
            if kind == "gl":
                gl = payload
                log.info("worker %d renders with %s", index, payload)
            elif kind == "built":
                log.info("worker %d built %s", index, payload)
            else:
                scene, label, rate = payload
                rates.setdefault(scene, {}).setdefault(label, 0.0)
                rates[scene][label] += rate
                received += 1
    finally:
        for process in processes:
            process.join(timeout=5)
            if process.is_alive():
                process.terminate()
                process.join(timeout=5)
    return rates, gl


def check_pixels(plan: Plan) -> tuple[dict[str, Any], dict[str, dict[str, np.ndarray]]]:
    """Render one state of each scene under each preset three ways; return the checks and frames.

    The checks: batched == one view at a time, batched == the default path with the preset
    applied, and the same state rendered twice gives the same pixels.
    """
    checks: dict[str, Any] = {}
    frames: dict[str, dict[str, np.ndarray]] = {}
    for name in plan.scenes:
        try:
            checks[name], frames[name] = _check_scene(name, plan)
        except Exception:
            log.exception("pixel checks of %s failed", name)
            checks[name] = {"error": traceback.format_exc(limit=3)}
    return checks, frames


def _check_scene(name: str, plan: Plan) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    scene = Scene(SCENES[name], dataclasses.replace(plan, envs=2))
    checks: dict[str, Any] = {}
    frames: dict[str, np.ndarray] = {}
    try:
        for preset in PRESETS:
            defaults = [_preset_default(scene, env, preset) for env in scene.envs]
            reference = np.stack([call() for calls in defaults for call in calls])
            batched = scene.renderer(preset).render(scene.views)
            alone = np.concatenate([scene.renderer(preset).render([view]) for view in scene.views])
            again = scene.renderer(preset).render(scene.views)
            checks[preset] = {
                "batched_equals_default_path": bool(np.array_equal(batched, reference)),
                "batched_equals_one_at_a_time": bool(np.array_equal(batched, alone)),
                "deterministic": bool(np.array_equal(batched, again)),
                "pixels_differing_from_default_path": int((batched != reference).any(-1).sum()),
            }
            frames[preset] = batched[: len(scene.camera.names)]
    finally:
        scene.close()
    return checks, frames


def _preset_default(scene: Scene, env: Any, preset: str) -> list[Callable[[], np.ndarray]]:
    """The default path's renderer of ``env`` with ``preset`` applied: upright images."""
    from vecsim.engine import render

    if scene.gym:
        import gymnasium

        from vecsim.engine.tasks import derive_seed

        # gymnasium aims its camera when it makes its viewer; vecsim aims its own when it makes
        # the env: make the viewer at once, then bring the env to the same state.
        reference = gymnasium.make(
            env.inner.spec.id, render_mode="rgb_array", width=scene.camera.width, height=scene.camera.height
        )
        viewer = render.apply_to_gymnasium(reference, preset)
        scene.references.append(reference)
        reference.reset(seed=derive_seed(scene.task_id, scene.envs.index(env)))

        def gym_render() -> np.ndarray:
            viewer.make_context_current()
            return reference.render()

        return [gym_render]
    from robosuite.utils.binding_utils import MjRenderContextOffscreen

    sim = env.inner.sim
    context = sim._render_context_offscreen
    if context is None:
        context = MjRenderContextOffscreen(sim, device_id=-1)
        scene._default_contexts.append(context)
    context.vopt.geomgroup[0] = 0
    context.vopt.geomgroup[1] = 1
    render.apply_to_robosuite(sim, preset)

    def robosuite_render(name: str) -> np.ndarray:
        context.gl_ctx.make_current()
        return sim.render(camera_name=name, width=scene.camera.width, height=scene.camera.height)[::-1]

    return [lambda name=name: robosuite_render(name) for name in scene.camera.names]


def summarise(rates: dict[str, dict[str, float]], plan: Plan) -> dict[str, Any]:
    """Return per scene: frames/s per path and process count, speed-ups over the default path,
    env-steps/s per path, and frames/s per pass variant."""
    summary: dict[str, Any] = {}
    for scene, by_label in rates.items():
        render = {
            f"{n}p": {path: by_label.get(f"render/{path}/{n}p") for path in ("default", *PRESETS)}
            for n in sorted({1, plan.procs})
        }
        speedup = {
            procs: {
                path: round(row[path] / row["default"], 2) if row.get(path) and row.get("default") else None
                for path in PRESETS
            }
            for procs, row in render.items()
        }
        steps = {path: by_label.get(f"step/{path}/{plan.procs}p") for path in ("physics", "default", *PRESETS)}
        physics = steps.get("physics")
        summary[scene] = {
            "frames_per_s": render,
            "speedup_over_default": speedup,
            "env_steps_per_s": steps,
            "fraction_of_physics_only": {
                path: round(value / physics, 3) if value and physics else None
                for path, value in steps.items()
                if path != "physics"
            },
            "passes_frames_per_s_1p": {name: by_label.get(f"passes/{name}/1p") for name in PASSES},
        }
    return summary


def plot(summary: dict[str, Any], plan: Plan, tag: str) -> list[Path]:
    """Draw the frames/s, env-steps/s and pass-cost charts; return the PNG paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    scenes = list(summary)
    size = f"{plan.height}x{plan.width}, 2 cameras"
    fig, axes = plt.subplots(1, len(scenes), figsize=(4.2 * len(scenes), 3.6), squeeze=False)
    for ax, scene in zip(axes[0], scenes):
        rows = summary[scene]["frames_per_s"]
        paths_ = ("default", *PRESETS)
        for offset, (procs, row) in enumerate(rows.items()):
            values = [row.get(p) or 0 for p in paths_]
            ax.bar(np.arange(len(paths_)) + 0.4 * offset, values, 0.4, label=f"{procs[:-1]} process(es)")
        ax.set_xticks(np.arange(len(paths_)) + 0.2, paths_)
        ax.set_yscale("log")
        ax.set_title(f"{scene}: frames/s")
        ax.legend(fontsize=7)
    fig.suptitle(f"rendering per node ({tag}, {size})")
    fig.tight_layout()
    paths.append(img_dir() / f"render_{tag}_frames.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    fig, axes = plt.subplots(1, len(scenes), figsize=(4.2 * len(scenes), 3.6), squeeze=False)
    for ax, scene in zip(axes[0], scenes):
        steps = summary[scene]["env_steps_per_s"]
        colors = ["grey", "tab:red", "tab:blue", "tab:cyan", "tab:green", "tab:purple"]
        ax.bar(list(steps), [v or 0 for v in steps.values()], color=colors)
        ax.set_title(f"{scene}: env-steps/s, {plan.procs} processes")
    fig.suptitle(f"physics only vs physics + rendering ({tag}, {size})")
    fig.tight_layout()
    paths.append(img_dir() / f"render_{tag}_steps.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    fig, axes = plt.subplots(1, len(scenes), figsize=(4.2 * len(scenes), 3.8), squeeze=False)
    for ax, scene in zip(axes[0], scenes):
        passes = summary[scene]["passes_frames_per_s_1p"]
        ms = [1000.0 / v if v else 0 for v in passes.values()]
        ax.barh(list(passes), ms)
        ax.invert_yaxis()
        ax.set_xlabel("ms per frame (1 process)")
        ax.set_title(scene)
    fig.suptitle(f"what each pass costs ({tag}, {size})")
    fig.tight_layout()
    paths.append(img_dir() / f"render_{tag}_passes.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)
    return paths


def frames_image(frames: dict[str, dict[str, np.ndarray]], tag: str) -> Path:
    """Save one image: a row per preset, the scenes' cameras side by side; return its path."""
    from PIL import Image, ImageDraw

    rows = []
    for preset in PRESETS:
        tiles = [image for scene in frames for image in frames[scene][preset]]
        rows.append(np.concatenate(tiles, axis=1))
    grid = np.concatenate(rows, axis=0)
    picture = Image.fromarray(grid)
    draw = ImageDraw.Draw(picture)
    tile_height = grid.shape[0] // len(PRESETS)
    for index, preset in enumerate(PRESETS):
        draw.text((4, index * tile_height + 2), preset, fill=(255, 0, 0))
    path = img_dir() / f"render_{tag}_presets.png"
    picture.save(path)
    return path


def gpu_name() -> str | None:
    """Return nvidia-smi's name of the GPU, or None without one."""
    try:
        done = subprocess.run(
            ["nvidia-smi", "--query-gpu=name,driver_version", "--format=csv,noheader"],
            capture_output=True,
            text=True,
            timeout=20,
        )
    except (OSError, subprocess.TimeoutExpired):
        return None
    return done.stdout.strip() or None


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    mode = parser.add_mutually_exclusive_group(required=True)
    mode.add_argument("--gpu", action="store_true", help="256x256, 16 processes of 8 envs; GL must be NVIDIA's")
    mode.add_argument("--cpu-small", action="store_true", help="64x64, 2 processes of 2 envs (Mesa)")
    parser.add_argument("--procs", type=int, help="processes of the node")
    parser.add_argument("--envs", type=int, help="envs per process")
    parser.add_argument("--seconds", type=float, help="length of each measurement")
    parser.add_argument("--scenes", default="lift,libero,pusher", help="comma-separated: lift, libero, pusher")
    parser.add_argument("--deadline", type=float, default=420.0, help="stop measuring after this many seconds")
    parser.add_argument("--copy-to", type=Path, help="also copy the JSON and images into this folder")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
    os.environ.setdefault("MUJOCO_GL", "egl")
    tag = "gpu" if args.gpu else "cpu"
    size = 256 if args.gpu else 64
    plan = Plan(
        height=size,
        width=size,
        envs=args.envs or (8 if args.gpu else 2),
        procs=args.procs or (16 if args.gpu else 2),
        seconds=args.seconds or (2.0 if args.gpu else 1.5),
        scenes=tuple(s for s in args.scenes.split(",") if s),
    )
    unknown = set(plan.scenes) - set(SCENES)
    if unknown:
        parser.error(f"--scenes: unknown {sorted(unknown)}; choose from {sorted(SCENES)}")
    started = time.monotonic()

    from vecsim.engine.batch_render import gl_info

    # The parent's GL context is only for this check; workers are spawned, not forked.
    gl = gl_info()
    log.info("GL: %s", gl)
    if args.gpu and "NVIDIA" not in gl["renderer"].upper():
        log.error("GL_RENDERER is %r, not NVIDIA's: not measuring", gl["renderer"])
        return 2
    checks, frames = check_pixels(plan)
    log.info("pixel checks: %s", json.dumps(checks))
    image = frames_image(frames, tag)
    rates, worker_gl = run_node(plan, max(30.0, args.deadline - (time.monotonic() - started)))
    summary = summarise(rates, plan)
    plots = plot(summary, plan, tag)
    record = {
        "plan": dataclasses.asdict(plan),
        "gl": worker_gl or gl,
        "gpu": gpu_name(),
        "pixel_checks": checks,
        "scenes": summary,
        "seconds_total": round(time.monotonic() - started, 1),
    }
    path = write_result(f"render_{tag}", record, {"rates": rates})
    if args.copy_to:
        args.copy_to.mkdir(parents=True, exist_ok=True)
        for item in (path, image, *plots):
            shutil.copy(item, args.copy_to / item.name)
    return 0


if __name__ == "__main__":
    sys.exit(main())
