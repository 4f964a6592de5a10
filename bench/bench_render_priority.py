"""Does a low GL priority for the pods' renders give the policy its GPU back?

On one GPU, the pods' camera renders (EGL contexts, one a pod process) share the GPU with the
trainer's policy (a CUDA context). In the slow-policy pipeline runs (docs/benchmarks.md,
"Stage layouts and refill") a 40-row ViT call took 425 ms in the loop against 363 ms alone, and
that alone caps two stages at about 1.7x one. This measures that contention without pods or
HTTP, and what the renders' GL context priority (``VECSIM_RENDER_PRIORITY``,
EGL_IMG_context_priority) does to it:

- the policy: the pipeline bench's ViT (``--vit-depth`` blocks 768 wide, two 256x256 cameras)
  replayed from a CUDA graph on ``--batch`` rows, call after call, timed with a sync each call;
- the renders: ``--renderers`` processes, each pinned to a core of its own and holding one
  LIBERO-10 scene, render ``--views`` camera views (a pod's envs' two cameras) through
  vecsim's batched renderer once every ``--period-ms``, as a pod does once per K-action call.
  One set of processes per priority is built up front; one set renders at a time.

Contenders, in turn within each of ``--rounds`` interleaved rounds (the order rotates):
``alone`` (no renders), then ``renders/<priority>`` for each of ``--priorities``. Per contender:
the policy's median ms a call, and the renders' median ms a batch (what the pods would pay). The
ratios are per round, against ``alone`` and against ``renders/medium``, in this one process.

    source .device/setup.sh && python bench/bench_render_priority.py --copy-to "$OUT"   # GPU node
    python bench/bench_render_priority.py --quick    # here: Mesa renders, a CPU policy (plumbing only)

Prints ``RESULT {json}`` and writes out/bench/bench_render_priority[_<tag>].json.
"""

from __future__ import annotations

import argparse
import logging
import multiprocessing as mp
import os
import shutil
import statistics
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np
import torch
from lib.records import spread, write_result
from gymnasium import spaces

from vecsim.config import CameraConfig
from vecsim.engine.batch_render import RENDER_PRIORITIES, RENDER_PRIORITY_ENV, BatchRenderer, gl_info

log = logging.getLogger("bench.render_priority")

CAMERAS = ("agentview", "robot0_eye_in_hand")


def renderer_main(
    index: int,
    core: int | None,
    priority: str,
    task: str,
    size: int,
    views: int,
    period_s: float,
    go: Any,
    stop: Any,
    ready: Any,
    results: Any,
) -> None:
    """A render process: one scene, ``views`` views a batch every ``period_s`` while ``go`` is set.

    Puts ``("ready", index, gl_info)`` once it has rendered a first batch, then ``("times",
    index, [ms, ...])`` each time ``go`` is cleared after batches were drawn.
    """
    os.environ[RENDER_PRIORITY_ENV] = priority
    if core is not None:
        os.sched_setaffinity(0, {core})
    from vecsim.engine.tasks import make_env

    env = make_env(task, CameraConfig(names=CAMERAS, height=size, width=size), "lean")
    env.reset(options={"state_id": index % 10})
    model = env.camera_views[0].model
    batch = [env.camera_views[i % len(env.camera_views)] for i in range(views)]
    renderer = BatchRenderer(size, size, "lean")
    renderer.attach(model, len(batch))
    renderer.render(batch)
    results.put(("ready", index, gl_info()))
    ready.wait()
    times: list[float] = []
    # Spread the processes' batches over the period, as pods' calls are not in phase.
    next_at = time.perf_counter() + period_s * (index % 8) / 8
    while not stop.is_set():
        if not go.is_set():
            if times:
                results.put(("times", index, times))
                times = []
            go.wait(0.05)
            next_at = time.perf_counter() + period_s * (index % 8) / 8
            continue
        pause = next_at - time.perf_counter()
        if pause > 0:
            time.sleep(pause)
        started = time.perf_counter()
        renderer.render(batch)
        times.append(1000 * (time.perf_counter() - started))
        next_at = started + period_s
    if times:
        results.put(("times", index, times))
    env.close()


class RenderSet:
    """``count`` render processes at one priority, started paused."""

    def __init__(
        self, ctx: Any, priority: str, count: int, cores: list[int | None], args: argparse.Namespace, first_index: int
    ) -> None:
        self.priority = priority
        self.go = ctx.Event()
        self.stop = ctx.Event()
        self.ready = ctx.Event()
        self.results = ctx.Queue()
        tasks = [f"libero_10/{i % 5}" for i in range(count)]
        self.processes = [
            ctx.Process(
                target=renderer_main,
                name=f"render-{priority}-{i}",
                args=(
                    first_index + i,
                    cores[i % len(cores)],
                    priority,
                    tasks[i],
                    args.size,
                    args.views,
                    args.period_ms / 1000,
                    self.go,
                    self.stop,
                    self.ready,
                    self.results,
                ),
                daemon=True,
            )
            for i in range(count)
        ]
        for process in self.processes:
            process.start()
        self.gl: list[dict[str, str]] = []

    def wait_ready(self, timeout_s: float) -> None:
        """Wait until every process has rendered once; raise TimeoutError naming how many did."""
        deadline = time.monotonic() + timeout_s
        while len(self.gl) < len(self.processes):
            left = deadline - time.monotonic()
            if left <= 0 or any(p.exitcode not in (None, 0) for p in self.processes):
                raise TimeoutError(f"{len(self.gl)} of {len(self.processes)} {self.priority} renderers ready")
            try:
                kind, _, info = self.results.get(timeout=min(left, 5.0))
            except Exception:
                continue
            if kind == "ready":
                self.gl.append(info)
        self.ready.set()

    def collect(self, timeout_s: float = 30.0) -> list[float]:
        """Every batch time (ms) the processes report after a pause."""
        times: list[float] = []
        reported = 0
        deadline = time.monotonic() + timeout_s
        while reported < len(self.processes) and time.monotonic() < deadline:
            try:
                kind, _, values = self.results.get(timeout=1.0)
            except Exception:
                continue
            if kind == "times":
                times.extend(values)
                reported += 1
        return times

    def close(self) -> None:
        self.stop.set()
        self.ready.set()
        self.go.set()
        for process in self.processes:
            process.join(timeout=20)
            if process.is_alive():
                process.kill()


def build_policy(args: argparse.Namespace, device: str) -> Any:
    """The pipeline bench's ViT policy, graphed for ``args.batch`` rows on CUDA."""
    from lib.policies import GraphedPolicy, VisionPolicy, dummy_obs

    box = spaces.Box(0, 255, (args.size, args.size, 3), np.uint8)
    space = spaces.Dict(
        {"images": spaces.Dict({c: box for c in CAMERAS}), "proprio": spaces.Box(-np.inf, np.inf, (9,), np.float32)}
    )
    action = spaces.Box(-1.0, 1.0, (7,), np.float32)
    dtype = torch.bfloat16 if device.startswith("cuda") else torch.float32
    policy = VisionPolicy(space, action, encoder="vit", vit_depth=args.vit_depth, device=device, dtype=dtype)
    graphed = GraphedPolicy(policy, space, device, [args.batch])
    obs = dummy_obs(space, args.batch, device)
    names = [""] * args.batch

    def call() -> float:
        started = time.perf_counter()
        with torch.no_grad():
            graphed(obs, names, names)
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        return 1000 * (time.perf_counter() - started)

    for _ in range(3):
        call()
    return call


def run(args: argparse.Namespace) -> dict[str, Any]:
    device = "cuda" if torch.cuda.is_available() and not args.quick else "cpu"
    call = build_policy(args, device)
    cores = sorted(os.sched_getaffinity(0))
    policy_core, render_cores = cores[0], cores[1:] or [None]
    os.sched_setaffinity(0, {policy_core})
    ctx = mp.get_context("spawn")
    sets = {
        p: RenderSet(ctx, p, args.renderers, render_cores, args, i * args.renderers)
        for i, p in enumerate(args.priorities)
    }
    try:
        for render_set in sets.values():
            render_set.wait_ready(args.build_timeout_s)
            log.info(
                "%d renderers at %s priority ready; granted: %s",
                args.renderers,
                render_set.priority,
                sorted({g.get("priority", "?") for g in render_set.gl}),
            )
        contenders = ["alone", *(f"renders/{p}" for p in args.priorities)]
        policy_ms: dict[str, list[float]] = {c: [] for c in contenders}
        render_ms: dict[str, list[float]] = {c: [] for c in contenders[1:]}
        for round_index in range(args.rounds):
            order = contenders[round_index % len(contenders) :] + contenders[: round_index % len(contenders)]
            for name in order:
                render_set = sets.get(name.split("/", 1)[1]) if "/" in name else None
                if render_set is not None:
                    render_set.go.set()
                    time.sleep(args.period_ms / 1000)  # every renderer under way
                calls: list[float] = []
                started = time.perf_counter()
                while time.perf_counter() - started < args.seconds or len(calls) < 3:
                    calls.append(call())
                if render_set is not None:
                    render_set.go.clear()
                    render_ms[name].append(statistics.median(render_set.collect()))
                policy_ms[name].append(statistics.median(calls))
                log.info(
                    "round %d %s: policy %.1f ms a call (%d calls)%s",
                    round_index + 1,
                    name,
                    policy_ms[name][-1],
                    len(calls),
                    f", renders {render_ms[name][-1]:.1f} ms a batch" if name in render_ms else "",
                )
    finally:
        for render_set in sets.values():
            render_set.close()
    alone = policy_ms["alone"]
    summary: dict[str, Any] = {
        "policy_ms": {c: spread(v) for c, v in policy_ms.items()},
        "render_ms": {c: spread(v) for c, v in render_ms.items()},
        "policy_slowdown_over_alone": {
            c: spread([m / a for m, a in zip(v, alone)]) for c, v in policy_ms.items() if c != "alone"
        },
        "gl": {p: s.gl[0] if s.gl else None for p, s in sets.items()},
        "granted": {p: sorted({g.get("priority", "?") for g in s.gl}) for p, s in sets.items()},
    }
    if "medium" in args.priorities:
        medium = policy_ms["renders/medium"]
        summary["policy_speedup_over_medium"] = {
            c: spread([m / v for m, v in zip(medium, values)])
            for c, values in policy_ms.items()
            if c.startswith("renders/") and c != "renders/medium"
        }
    summary["setup"] = {
        "device": device,
        "batch": args.batch,
        "vit_depth": args.vit_depth,
        "size": args.size,
        "renderers": args.renderers,
        "views": args.views,
        "period_ms": args.period_ms,
        "seconds": args.seconds,
        "rounds": args.rounds,
        "policy_core": policy_core,
        "render_cores": render_cores,
        "torch": torch.__version__,
    }
    return summary


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--renderers", type=int, default=15, help="render processes a priority (a core each)")
    parser.add_argument("--views", type=int, default=10, help="camera views a batch (a pod's envs' cameras)")
    parser.add_argument("--period-ms", type=float, default=330.0, help="a renderer's batch every this many ms")
    parser.add_argument("--size", type=int, default=256, help="camera side, pixels")
    parser.add_argument("--batch", type=int, default=40, help="the policy's rows a call")
    parser.add_argument(
        "--vit-depth", type=int, default=448, help="the ViT's blocks (448: about 360 ms a 40-row call on an H200)"
    )
    parser.add_argument("--priorities", default="medium,low", help="comma-separated: low, medium, high")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--seconds", type=float, default=8.0, help="the policy's calls per contender, in seconds")
    parser.add_argument("--build-timeout-s", type=float, default=300.0)
    parser.add_argument("--quick", action="store_true", help="tiny sizes on the CPU: checks the plumbing only")
    parser.add_argument("--tag", default="")
    parser.add_argument("--copy-to", type=Path, default=None, help="also copy the record here (the device's $OUT)")
    args = parser.parse_args(argv)
    args.priorities = tuple(p.strip().lower() for p in args.priorities.split(",") if p.strip())
    unknown = [p for p in args.priorities if p not in RENDER_PRIORITIES]
    if unknown or not args.priorities:
        parser.error(f"--priorities: expected some of {', '.join(RENDER_PRIORITIES)}, got {unknown or 'none'}")
    if args.renderers < 1 or args.views < 1 or args.batch < 1 or args.rounds < 1:
        parser.error("--renderers, --views, --batch and --rounds must be at least 1")
    if args.quick:
        args.renderers, args.views, args.size, args.batch, args.vit_depth = 1, 2, 64, 2, 1
        args.seconds, args.rounds, args.period_ms = min(args.seconds, 0.5), min(args.rounds, 2), 50.0
    return args


def main(argv: list[str] | None = None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    args = parse_args(argv)
    summary = run(args)
    name = "bench_render_priority" + (f"_{args.tag}" if args.tag else "")
    path = write_result(name, summary)
    if args.copy_to:
        args.copy_to.mkdir(parents=True, exist_ok=True)
        shutil.copy(path, args.copy_to / path.name)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
