"""GPU against software rendering on the same pod setup (``bench_gpu_scale.py --render-compare``):
the same open-loop rollouts on the machine's EGL and on Mesa's, their physics and images compared.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import shutil
import statistics
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from .pods import rate_spread
from .records import img_dir, write_result

from vecsim.client import StageClient, fetch_routing
from vecsim.rollout import EnvLoop
from .policies import ScriptedPolicy
from .machine import gpu_name, cpu_topology, cores_first, split_cores, render_probe, gpu_egl_env, software_egl_env
from .jobs import Plan, job_config, running_job, wait_for_job, requests_for
from .jobs import camera as camera_setup
from .measure import POD_COUNTERS, scrape, Measured, Deadline
from .stats import breakdown

log = logging.getLogger("bench.gpu_scale")


def render_rollouts(
    plan: Plan, pins: Sequence[str], name: str, env: dict[str, str], rounds: int, deadline: Deadline
) -> tuple[list[Measured], dict[str, Any]]:
    """Start a one-pod job of ``plan.tasks[0]`` with ``env`` on core ``pins[0]``; run a warm-up
    and then ``rounds`` rollouts of ``plan.horizon`` steps (fewer once the deadline nears; at
    least one); return them and the first one's observations, ``{traj_key: observations}``."""
    config = job_config(plan, pins, f"render-{name}", 1)
    with running_job(config, env=env) as job:
        table = wait_for_job(job, max(60.0, min(600.0, deadline.left())))
        table = fetch_routing(job.controller_url, wait_ready_s=30)
        requests = requests_for(table)
        with StageClient(table, token=job.token, timeout_s=600) as client:
            space = client.action_space

            def one(horizon: int, keep: tuple[str, ...]) -> tuple[Measured, Any]:
                urls = [p.url for stage in table.stages for p in stage.pods]
                before = scrape(urls)
                loop = EnvLoop(client, ScriptedPolicy(space), horizon=horizon, keep_obs=keep, log_every_s=60)
                result = loop.run(requests, [f"env-{i}" for i in range(len(requests))])
                after = scrape(urls)
                if result.lost:
                    raise RuntimeError(f"{name}: {len(result.lost)} trajectories lost")
                return Measured(result.stats, {k: after[k] - before[k] for k in POD_COUNTERS}), result.trajectories

            one(min(2, plan.horizon), ())  # warm-up: shaders compiled, caches filled
            started = time.monotonic()
            first, trajectories = one(plan.horizon, ("images", "proprio"))
            measured = [first]
            for _ in range(rounds - 1):
                if deadline.left() < 2 * (time.monotonic() - started) + 60:
                    log.warning("%s: deadline near, %d of %d rounds run", name, len(measured), rounds)
                    break
                measured.append(one(plan.horizon, ())[0])
            log.info("%s: %s env-steps/s", name, [round(m.env_steps_per_s, 1) for m in measured])
    return measured, {key: t.observations for key, t in trajectories.items()}


def compare_images(first: dict[str, Any], second: dict[str, Any]) -> dict[str, Any]:
    """Pixel differences between two rollouts' images of the same states (every trajectory and
    step both have), per camera: mean and max absolute difference (0-255), PSNR, the share of
    pixels off by more than 8 and 32 levels in some channel; and the largest proprio difference
    (0 when both ran through the same physics states)."""
    keys = sorted(set(first) & set(second))
    steps = min(min(len(first[k]["proprio"]), len(second[k]["proprio"])) for k in keys)
    proprio = max(
        float((first[k]["proprio"][:steps].double() - second[k]["proprio"][:steps].double()).abs().max()) for k in keys
    )
    cameras = {}
    for camera in first[keys[0]]["images"]:
        a = np.stack([first[k]["images"][camera][:steps].numpy() for k in keys]).astype(np.int16)
        b = np.stack([second[k]["images"][camera][:steps].numpy() for k in keys]).astype(np.int16)
        diff = np.abs(a - b)
        mse = float(np.mean(diff.astype(np.float64) ** 2))
        per_frame = np.mean(diff.reshape(-1, *diff.shape[2:]).astype(np.float64) ** 2, axis=(1, 2, 3))
        worst = float(per_frame.max())
        cameras[camera] = {
            "frames": int(per_frame.size),
            "mean_abs_diff": round(float(diff.mean()), 3),
            "max_abs_diff": int(diff.max()),
            "psnr_db": round(10 * math.log10(255**2 / mse), 2) if mse > 0 else None,
            "worst_frame_psnr_db": round(10 * math.log10(255**2 / worst), 2) if worst > 0 else None,
            "pixels_off_by_more_than_8": round(float((diff.max(axis=-1) > 8).mean()), 4),
            "pixels_off_by_more_than_32": round(float((diff.max(axis=-1) > 32).mean()), 4),
            "identical": bool(diff.max() == 0),
        }
    return {
        "trajectories": len(keys),
        "steps_compared": steps,
        "proprio_max_abs_diff": proprio,
        "same_states": proprio == 0.0,
        "cameras": cameras,
    }


def render_figures(summary: dict[str, Any], observations: dict[str, dict[str, Any]], tag: str) -> list[Path]:
    """Draw the bar chart (env-steps/s; ms per env-step split) and the frames figure (the last
    compared step of the first env, each camera: GPU, software, difference x4); return the PNGs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = {name: run for name, run in summary["renderers"].items() if "env_steps_per_s" in run}
    labels = [f"{name} EGL\n{run['gl']['renderer'].split('/')[0].split(' (')[0]}" for name, run in runs.items()]
    fig, (left, right) = plt.subplots(1, 2, figsize=(9.5, 4.0))
    rates = [run["env_steps_per_s"]["median"] for run in runs.values()]
    bars = left.bar(labels, rates, color=["tab:green", "tab:orange"][: len(rates)])
    left.bar_label(bars, fmt="%.1f", fontsize=8)
    left.set_ylabel("env-steps/s")
    left.set_title("one pod, one core", fontsize=9)
    bottom = np.zeros(len(runs))
    parts = (("physics", "physics_ms_per_env_step"), ("render", "render_ms_per_env_step"))
    for label, key in parts:
        values = np.array([run["time_split_ms"][key] for run in runs.values()])
        right.bar(labels, values, bottom=bottom, label=label)
        bottom += values
    rest = np.array(
        [
            max(
                run["wall_ms_per_env_step"]
                - run["time_split_ms"]["physics_ms_per_env_step"]
                - run["time_split_ms"]["render_ms_per_env_step"],
                0,
            )
            for run in runs.values()
        ]
    )
    bars = right.bar(labels, rest, bottom=bottom, label="rest (resets, IPC, serving)")
    right.bar_label(bars, labels=[f"{v:.1f} ms" for v in bottom + rest], fontsize=8)
    right.set_ylabel("ms per env-step")
    right.set_title("where an env-step's time goes", fontsize=9)
    right.legend(fontsize=7)
    setup = summary["setup"]
    fig.suptitle(
        f"{setup['task']}, {setup['size']}x{setup['size']} x {len(setup['cameras'])} cameras, "
        f"{setup['envs']} envs: GPU against software EGL",
        fontsize=10,
    )
    fig.tight_layout()
    paths = [img_dir() / f"gpu_render_compare{tag}.png"]
    fig.savefig(paths[0], dpi=110)
    plt.close(fig)

    if len(observations) == 2:
        gpu, software = observations.values()
        key = sorted(set(gpu) & set(software))[0]
        step = summary["images"]["steps_compared"] - 1
        cameras = list(gpu[key]["images"])
        fig, axes = plt.subplots(len(cameras), 3, figsize=(9, 3.1 * len(cameras)), squeeze=False)
        for row, camera in enumerate(cameras):
            a = gpu[key]["images"][camera][step].numpy()
            b = software[key]["images"][camera][step].numpy()
            diff = np.clip(np.abs(a.astype(np.int16) - b.astype(np.int16)) * 4, 0, 255).astype(np.uint8)
            for col, (image, title) in enumerate(
                ((a, f"GPU: {camera}"), (b, f"software: {camera}"), (diff, "|difference| x 4"))
            ):
                axes[row][col].imshow(image)
                axes[row][col].set_title(title, fontsize=8)
                axes[row][col].axis("off")
        fig.suptitle(f"{key}, step {step}", fontsize=9)
        fig.tight_layout()
        paths.append(img_dir() / f"gpu_render_compare{tag}_frames.png")
        fig.savefig(paths[-1], dpi=100)
        plt.close(fig)
    return paths


def render_compare(args: argparse.Namespace) -> int:
    """``--render-compare``: one pinned pod of one scene, the machine's EGL then Mesa's."""
    deadline = Deadline(args.deadline)
    task = args.tasks.split(",")[0] if args.tasks else "libero_10/0"
    plan = Plan(
        mode="render",
        tasks=(task,),
        size=args.size or 256,
        envs_per_task=args.envs_per_task or 4,
        pods=1,
        pod_counts=(1,),
        pipeline_cores=0,
        horizon=args.horizon or 10,
        service_steps=0,
        rounds=args.rounds or 3,
        device="cpu",
        dtype="float32",
        vit_width=768,
        vit_max_depth=0,
        max_memory_gib=args.max_memory_gib,
        deadline_s=args.deadline,
    )
    pins, trainer = split_cores(cores_first(cpu_topology()), 1)
    os.sched_setaffinity(0, set(trainer))
    soft_env, soft_source = software_egl_env()
    contenders: dict[str, tuple[dict[str, str] | None, str, int]] = {
        "gpu": (gpu_egl_env(), "the machine's default EGL (NVIDIA's vendor file where there is one)", plan.rounds),
        "software": (soft_env, soft_source, args.soft_rounds),
    }
    renderers: dict[str, Any] = {}
    observations: dict[str, dict[str, Any]] = {}
    for name, (env, source, rounds) in contenders.items():
        if env is None:
            renderers[name] = {"skipped": source}
            continue
        gl = render_probe(env)
        log.info("%s EGL (%s): %s", name, source, gl)
        shown = {k: v for k, v in env.items() if k != "LD_LIBRARY_PATH"}
        if "error" in gl:
            renderers[name] = {"skipped": f"no GL context: {gl['error']}", "source": source, "env": shown, "gl": gl}
            continue
        measured, observations[name] = render_rollouts(plan, pins, name, env, rounds, deadline)
        rates = [m.env_steps_per_s for m in measured]
        renderers[name] = {
            "source": source,
            "env": shown,
            "gl": gl,
            "env_steps_per_s": rate_spread(rates),
            "wall_ms_per_env_step": round(1000 / statistics.median(rates), 2),
            "time_split_ms": breakdown(measured),
            "per_round": [round(rate, 2) for rate in rates],
        }
    gpu_renderer = renderers["gpu"].get("gl", {}).get("renderer", "")
    nvidia = "NVIDIA" in gpu_renderer.upper()
    if not nvidia:
        log.warning("the default EGL renders with %r, not NVIDIA's: recording under the _cpu name", gpu_renderer)
    both = all("env_steps_per_s" in run for run in renderers.values())
    summary: dict[str, Any] = {
        "baseline": "the same pod with the machine's default EGL (the GPU's)",
        "ratio": None,
        "setup": {
            "task": task,
            "size": plan.size,
            "cameras": camera_setup(plan)["names"],
            "envs": plan.envs_per_task,
            "horizon": plan.horizon,
            "preset": "lean",
            "pod_pinned_to": pins[0],
            "trainer_cores": trainer,
            "policy": "open-loop sine actions (the same each run, so the states are the same)",
            "rollout": "one EnvLoop.run: reset, then `horizon` steps of every env; a warm-up first",
        },
        "gpu_is_nvidia": nvidia,
        "gpu": gpu_name(),
        "renderers": renderers,
    }
    if both:
        gpu_run, soft_run = renderers["gpu"], renderers["software"]
        summary["ratio"] = round(gpu_run["env_steps_per_s"]["median"] / soft_run["env_steps_per_s"]["median"], 2)
        summary["render_ms_per_env_step_software_over_gpu"] = round(
            soft_run["time_split_ms"]["render_ms_per_env_step"]
            / max(gpu_run["time_split_ms"]["render_ms_per_env_step"], 1e-6),
            1,
        )
        summary["images"] = compare_images(observations["gpu"], observations["software"])
    tag = "" if nvidia else "_cpu"
    plots = render_figures(summary, observations, tag) if both else []
    summary["plots"] = [str(p.relative_to(img_dir().parent.parent)) for p in plots]
    path = write_result(f"bench_gpu_render_compare{tag}", summary)
    if args.copy_to:
        args.copy_to.mkdir(parents=True, exist_ok=True)
        for item in (path, *plots):
            shutil.copy(item, args.copy_to / item.name)
    return 0 if both else 2
