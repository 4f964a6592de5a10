"""``vecsim demo``: start a local job, run one pipelined rollout on it, show what happened.

Top to bottom: load a job config (default: the tiny job shipped inside the package), start the
controller and the pods (the local runner), wait until every pod is ready (its warm-up done,
its progress logged as it goes), draw a task-balanced batch of trajectory requests,
warm the policy up (its first forward pass, the trainer's own cost, timed and reported apart),
roll a small CNN policy out over the stages with :class:`vecsim.rollout.EnvLoop`, then print a
summary (with the first step's cost against the median step's) and write a timeline plot,
per-task success and videos under ``--out``. Everything started is stopped on
the way out, Ctrl-C included.

It is a program on the library and the local runner, so it lives in ``service`` (the library
never imports ``service``).
"""

from __future__ import annotations

import argparse
import itertools
import json
import logging
import contextlib
import importlib.resources
import statistics
import threading
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import httpx

import numpy as np
import torch
from gymnasium.vector.utils import create_empty_array

from service.runner import LocalJob, format_status
from service.runner.ports import free_port, free_port_block, port_free
from vecsim.client import StageClient
from vecsim.config import JobConfig, load_job_config
from vecsim.rollout import EnvLoop, ExampleCNNPolicy, RolloutResult
from vecsim.rollout.sampler import TaskBalancedSampler, TaskInstances
from vecsim.engine.tasks import episode_limit, get_task
from vecsim.trees import map_leaves

logger = logging.getLogger("service.demo")
# The default job, shipped inside the package (a copy of configs/tiny.yaml), so that the demo
# runs from any directory.
DEFAULT_CONFIG = importlib.resources.files("service") / "configs" / "tiny.yaml"
WARMUP_EVERY_S = 5.0  # how often the warm-up's progress is checked (a line when it changed)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="vecsim demo", description=__doc__.split("\n\n")[0])
    p.add_argument(
        "-c", "--config", default=None, help="job config (default: the tiny job shipped with vecsim, configs/tiny.yaml)"
    )
    p.add_argument("--out", default="out/demo", help="where plots, videos and summary.json go (default out/demo)")
    p.add_argument("--batch", type=int, default=0, help="trajectories in a sampler batch (default: one per env)")
    p.add_argument(
        "--waves",
        type=int,
        default=2,
        help="sampler batches rolled out at once (default 2): an env whose trajectory ends starts a waiting one (refill)",
    )
    p.add_argument("--horizon", type=int, default=0, help="steps per trajectory at most (default: the job's max)")
    p.add_argument("--videos", type=int, default=2, help="how many trajectories to record (default 2)")
    p.add_argument("--seed", type=int, default=0, help="sampler and policy seed (default 0)")
    p.add_argument("--ready-timeout", type=float, default=300.0, help="seconds to wait for the pods (default 300)")
    p.add_argument(
        "--timeout-s",
        type=float,
        default=300.0,
        help="seconds a pod may take to answer one call (default 300: a busy machine's first calls are slow)",
    )
    p.add_argument("--log-level", default="info", help="logging level (default info)")
    return p


def warmup_line(local: LocalJob) -> str:
    """Each pod's readiness in a few words: ``sim-0 building 6 envs for generation 1; sim-1 ready``."""
    parts = []
    for name in local.processes:
        if name == "controller":
            continue
        try:
            answer = httpx.get(f"{local.pod_url(name)}/readyz", timeout=2.0)
            said = "ready" if answer.status_code == 200 else str(answer.json().get("detail", answer.status_code))
        except (httpx.HTTPError, ValueError):
            said = "starting"
        parts.append(f"{name} {said}")
    return "; ".join(parts)


@contextlib.contextmanager
def showing_warmup(local: LocalJob, every_s: float = WARMUP_EVERY_S) -> Iterator[None]:
    """While the body runs (the wait for the pods), log each pod's progress every ``every_s``
    when it changed, so that a warm-up of minutes is not silent."""
    stop = threading.Event()
    started = time.perf_counter()

    def watch() -> None:
        last = ""
        while True:
            line = warmup_line(local)
            if line != last:
                logger.info("warming up, %.0f s: %s", time.perf_counter() - started, line)
                last = line
            if stop.wait(every_s):
                return

    thread = threading.Thread(target=watch, name="demo-warmup", daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()


def with_free_ports(config: JobConfig) -> JobConfig:
    """Return ``config`` moved to free ports when its own are taken (a demo should just run).

    Pods need ``replicas`` consecutive ports from ``base_port``; the first free block of
    ephemeral ports found is used.
    """

    host, pods = config.controller.host, config.pods
    taken = not port_free(host, config.controller.port) or not all(
        port_free(pods.host, pods.base_port + i) for i in range(pods.replicas)
    )
    if not taken:
        return config
    controller_port = free_port(host)
    base = free_port_block(pods.replicas, pods.host, avoid={controller_port})
    logger.info("default ports are taken: controller on %d, pods from %d", controller_port, base)
    return config.model_copy(
        update={
            "controller": config.controller.model_copy(update={"port": controller_port}),
            "pods": pods.model_copy(update={"base_port": base}),
        }
    )


def warm_policy(policy: Any, client: StageClient, tasks: Sequence[str], rows: int) -> float:
    """Run ``policy`` once on ``rows`` zero observations of the job's space, before the rollout's
    clock starts; return the seconds it took.

    A trainer's own first forward pass (torch's first convolution sets up its kernels) is not
    the pods' cost, and it is paid once per process: the demo pays it here, says how long it took,
    and keeps it out of the first step's timing (the first step is the pods' claim).
    """
    rows = max(rows, 1)
    obs = map_leaves(torch.from_numpy, create_empty_array(client.observation_space, rows, fn=np.zeros))
    task_ids = [tasks[i % len(tasks)] for i in range(rows)]
    begin = time.perf_counter()
    with torch.no_grad():
        policy(obs, [client.instructions.get(t, "") for t in task_ids], task_ids)
    return time.perf_counter() - begin


def step_costs(pod_calls: Sequence[tuple[int, str, float, float, int, int]]) -> dict[str, Any]:
    """The first step's cost against the median step's, from a rollout's ``pod_calls``.

    Per (stage, pod): the seconds in flight of its first call that stepped trajectories, the
    median of all its stepping calls, and their ratio. ``first_over_median`` is the worst ratio
    (None without a stepping pod); a pod with one stepping call has ratio 1.
    """
    durations: dict[tuple[int, str], list[tuple[float, float]]] = {}
    for stage, pod, begin, end, _resets, steps in pod_calls:
        if steps:
            durations.setdefault((stage, pod), []).append((begin, end - begin))
    per_pod = []
    for (stage, pod), calls in sorted(durations.items()):
        calls.sort()
        first, median = calls[0][1], statistics.median(d for _, d in calls)
        ratio = first / median if median > 0 else float("inf")
        per_pod.append(
            {"stage_id": stage, "pod": pod, "calls": len(calls), "first_s": first, "median_s": median, "ratio": ratio}
        )
    worst = max((p["ratio"] for p in per_pod), default=None)
    return {"first_over_median": worst, "per_pod": per_pod}


def summary_lines(result: RolloutResult, num_stages: int, policy_warmup_s: float | None = None) -> list[str]:
    """The summary table the demo prints: throughput, overlap, first step against the median
    step, per-task success."""
    s = result.stats
    costs = step_costs(s.pod_calls)
    lines = [
        f"{'trajectories':<28}{s.num_trajectories} (envs refill as trajectories end)",
        f"{'pipeline stages':<28}{num_stages}",
        f"{'env-steps':<28}{s.env_steps}",
        f"{'wall time':<28}{s.wall_s:.1f} s",
        f"{'env-steps/s':<28}{s.env_steps_per_s:.1f}",
        f"{'policy time':<28}{s.policy_s:.2f} s",
        f"{'simulation in flight':<28}{s.simulation_s:.2f} s",
        f"{'policy time overlapped':<28}{100 * s.overlap_fraction:.0f} % (simulation ran while the policy worked)",
    ]
    if costs["first_over_median"] is not None:
        lines.append(f"{'first step / median step':<28}{costs['first_over_median']:.2f}x (the worst pod's; per pod:)")
        for p in costs["per_pod"]:
            lines.append(
                f"{'':<28}stage {p['stage_id']} {p['pod']}: first {p['first_s']:.2f} s, "
                f"median {p['median_s']:.2f} s of {p['calls']} steps ({p['ratio']:.2f}x)"
            )
    if policy_warmup_s is not None:
        lines.append(f"{'policy warm-up':<28}{policy_warmup_s:.2f} s (its first forward pass, before the clock)")
    lines += [
        "",
        f"{'task':<28}{'trajectories':>12}{'success':>10}",
    ]
    counts: dict[str, int] = {}
    for trajectory in result.trajectories.values():
        counts[trajectory.route.task_id] = counts.get(trajectory.route.task_id, 0) + 1
    for task, rate in sorted(s.success_per_task.items()):
        lines.append(f"{task:<28}{counts.get(task, 0):>12}{100 * rate:>9.0f}%")
    return lines


def plot_timeline(result: RolloutResult, num_stages: int, path: Path, policy_warmup_s: float | None = None) -> Path:
    """Draw when the policy ran on each stage and when each pod simulated that stage's envs (a row
    per stage and pod: their calls start and end apart, as there is no lockstep), marking the
    calls that started refilled trajectories. The picture of pipelining."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = result.stats
    lanes = sorted({(stage, pod) for stage, pod, *_ in s.pod_calls})
    rows: list[str] = []
    where: dict[tuple[str, int, str], int] = {}
    for stage in range(num_stages):
        where[("policy", stage, "")] = len(rows)
        rows.append(f"stage {stage}: policy")
        for _, pod in (lane for lane in lanes if lane[0] == stage):
            where[("sim", stage, pod)] = len(rows)
            rows.append(f"stage {stage}: {pod}")
    colors = {"policy": "#DD8452", "sim": "#4C72B0", "refill": "#55A868", "reset": "#8C8C8C"}
    fig, ax = plt.subplots(figsize=(11, 1.4 + 0.38 * len(rows)))
    for what, stage, begin, end in s.timeline:
        if what == "policy":
            ax.barh(
                where[("policy", stage, "")], end - begin, left=begin, height=0.6, color=colors["policy"], linewidth=0
            )
    first: set[tuple[int, str]] = set()
    for stage, pod, begin, end, resets, steps in s.pod_calls:
        # A lane's first call resets the first wave; a later call with resets starts refilled trajectories.
        kind = "sim" if not resets else "reset" if (stage, pod) not in first else "refill"
        first.add((stage, pod))
        ax.barh(where[("sim", stage, pod)], end - begin, left=begin, height=0.6, color=colors[kind], linewidth=0)
    ax.set_yticks(range(len(rows)), rows, fontsize=8)
    ax.invert_yaxis()
    handles = [plt.Rectangle((0, 0), 1, 1, color=c) for c in colors.values()]
    labels = ["policy forward pass", "pod stepping", "pod starting refilled trajectories (and stepping)", "first reset"]
    ax.legend(
        handles, labels, loc="upper center", bbox_to_anchor=(0.5, -0.25 if len(rows) < 8 else -0.1), ncol=4, fontsize=8
    )
    worst = step_costs(s.pod_calls)["first_over_median"]
    first_step = "" if worst is None else f"; first step {worst:.1f}x the median"
    ax.set_title(
        f"{s.num_trajectories} trajectories, {s.env_steps} env-steps at {s.env_steps_per_s:.0f}/s; "
        f"{100 * s.overlap_fraction:.0f}% of policy time overlapped simulation{first_step}",
        fontsize=10,
    )
    ax.set_xlabel(
        "seconds since the rollout began"
        + ("" if policy_warmup_s is None else f" (before it, the policy's first forward pass: {policy_warmup_s:.2f} s)")
    )
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main(argv: list[str]) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    if args.waves < 1 or args.batch < 0:
        parser.error(f"--waves must be >= 1 and --batch >= 0, got {args.waves} and {args.batch}")
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    logging.getLogger("httpx").setLevel(logging.WARNING)  # one INFO line per request drowns the rest

    config = with_free_ports(load_job_config(args.config or DEFAULT_CONFIG))
    job = config.job
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(args.seed)

    with LocalJob(config, log_dir=out / "logs") as local:
        started = time.perf_counter()
        logger.info("starting %d pods and the controller (logs in %s)", config.pods.replicas, out / "logs")
        with showing_warmup(local):
            table = local.wait_ready(timeout=args.ready_timeout)
        logger.info(
            "job %r ready in %.0f s: generation %d", job.job_id, time.perf_counter() - started, table.generation
        )
        for line in format_status(local.status()).splitlines():
            logger.info("%s", line)

        client = StageClient.from_controller(local.controller_url, token=local.token, timeout_s=args.timeout_s)
        try:
            tasks = sorted({block.task_id for stage in table.stages for pod in stage.pods for block in pod.tasks})
            dataset = TaskInstances.from_tasks(tasks, num_states=10)
            batch_size = args.batch or table.num_envs
            sampler = TaskBalancedSampler.for_job(dataset, job, batch_size=batch_size, seed=args.seed)
            # Each batch holds a multiple of num_stages requests, so request i stays on stage i % S.
            requests = [dataset[i] for batch in itertools.islice(sampler, args.waves) for i in batch]
            policy = ExampleCNNPolicy(client.observation_space, client.action_space, noise_std=0.3)
            stage_rows = max(stage.num_envs for stage in table.stages) if table.stages else 1
            policy_warmup_s = warm_policy(policy, client, tasks, stage_rows)
            logger.info("policy warmed up (its first forward pass, %d rows) in %.2f s", stage_rows, policy_warmup_s)
            loop = EnvLoop(
                client,
                policy,
                horizon=args.horizon
                or max(
                    episode_limit(task, job.max_episode_steps) or get_task(task).max_episode_steps for task in tasks
                ),
                record=args.videos,
                video_dir=out / "videos",
                log_every_s=5.0,
            )
            logger.info(
                "rolling out %d trajectories over %d stages and %d envs", len(requests), job.num_stages, table.num_envs
            )
            result = loop.run(requests)
        finally:
            client.close()

    lines = summary_lines(result, job.num_stages, policy_warmup_s)
    timeline = plot_timeline(result, job.num_stages, out / "timeline.png", policy_warmup_s)
    summary = {
        "config": str(args.config or DEFAULT_CONFIG),
        "stats": {k: v for k, v in vars(result.stats).items() if k != "timeline"},
        "step_costs": step_costs(result.stats.pod_calls),
        "policy_warmup_s": policy_warmup_s,
        "routes": {key: vars(t.route) for key, t in result.trajectories.items()},
        "videos": {key: str(p) for key, p in result.videos.items()},
        "timeline_png": str(timeline),
        "lost": {key: {"route": vars(t.route), "steps": t.steps, "reason": t.reason} for key, t in result.lost.items()},
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
    print("\n".join(["", "vecsim demo: pipelined rollout", "-" * 60, *lines, "-" * 60]))
    print(f"timeline plot: {timeline}")
    for key, path in result.videos.items():
        print(f"video of {key}: {path}")
    print(f"summary: {out / 'summary.json'}")
    if result.lost:
        for key, lost in result.lost.items():
            logger.error(
                "lost %s (%s on %s after %d steps): %s",
                key,
                lost.route.task_id,
                lost.route.pod,
                lost.steps,
                lost.reason,
            )
        print(
            f"FAILED: {len(result.lost)} of {len(requests)} trajectories were lost (their pods or envs failed them; "
            f"see the errors above and the logs in {out / 'logs'})"
        )
        return 1
    return 0
