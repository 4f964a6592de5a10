"""Soak: several trainer clients stepping one job for a bounded time.

Starts a local job (``LocalJob``: the controller and its pods as processes, with a token made
for the run, every port picked free) and runs ``--clients`` trainers against it, each in its own
thread with its own ``StageClient``, on envs of its own (the job's envs are dealt out round robin,
so no two clients share one). Every client pipelines its stages: one call per stage in flight,
each call stepping the stage's live trajectories and resetting the ended ones to a new state id.

Reported: errors (the goal is none), env steps and calls, per window of ``--window-s`` seconds
the p50/p99 latency of a stage call (submitted to answered, as the client sees it), and the
resident memory of every pod (its process and its env workers) and of the controller at the
start (after every client's first reset) and at the end.

    python bench/soak.py                       # 30 s, 3 clients, the built-in HalfCheetah job
    python bench/soak.py --minutes 10          # the long run
    python bench/soak.py -c configs/tiny.yaml  # any job config (its ports are replaced)

Prints ``RESULT {json}``; writes out/bench/soak.json (or ``--json PATH``). Exit code 1 when any
client met an error.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import psutil
from lib.records import RESULT_PREFIX, command_line, machine_info, write_result

from service.runner import LocalJob
from service.runner.ports import free_port, free_port_block
from vecsim.client import RoutedEnv, StageClient, TrajRoute, routed_envs
from vecsim.config import JobConfig, load_job_config
from vecsim.engine.tasks import get_task

log = logging.getLogger("soak")

BUILT_IN_JOB = {
    "job_id": "soak",
    "tasks": ["gym/HalfCheetah-v5"],
    "group_size": 6,
    "num_stages": 2,
    "pods_per_stage": 1,
    "camera": {"names": []},
    "envs_per_worker": 3,
    "max_episode_steps": 100,
}
MIB = 1 << 20


def soak_config(path: str | None) -> JobConfig:
    """The job to soak on free loopback ports: ``path``'s, or the built-in one."""
    config = load_job_config(path) if path else JobConfig.model_validate({"job": BUILT_IN_JOB})
    job = config.job
    replicas = max(config.pods.replicas, job.pods_needed)
    port = free_port()
    base_port = free_port_block(replicas, avoid={port})
    pods = {**config.pods.model_dump(), "replicas": replicas, "host": "127.0.0.1", "base_port": base_port}
    controller = {**config.controller.model_dump(), "host": "127.0.0.1", "port": port}
    return JobConfig.model_validate({"job": job.model_dump(mode="json"), "pods": pods, "controller": controller})


def tree_rss(pid: int | None) -> int:
    """Resident bytes of a process and all its descendants (0 when it is gone)."""
    if pid is None:
        return 0
    try:
        root = psutil.Process(pid)
        total = root.memory_info().rss
        for child in root.children(recursive=True):
            try:
                total += child.memory_info().rss
            except psutil.NoSuchProcess:
                continue
        return total
    except psutil.NoSuchProcess:
        return 0


@dataclass
class ClientLog:
    """What one client saw: (finished at, seconds) per stage call, env steps, errors."""

    name: str
    calls: list[tuple[float, float]] = field(default_factory=list)
    env_steps: int = 0
    resets: int = 0
    errors: list[str] = field(default_factory=list)
    warm: threading.Event = field(default_factory=threading.Event)


def run_client(
    log_: ClientLog,
    controller_url: str,
    token: str,
    envs: Sequence[RoutedEnv],
    horizon: int,
    stop: threading.Event,
    seed: int,
) -> None:
    """Step ``envs`` (this client's share of the job's envs) stage by stage until ``stop``;
    record into ``log_``, errors included (a client that cannot go on records why and ends)."""
    try:
        _client_loop(log_, controller_url, token, envs, horizon, stop, seed)
    except Exception as exc:
        log_.errors.append(f"client ended: {type(exc).__name__}: {exc}")
        log_.warm.set()


def _client_loop(
    log_: ClientLog,
    controller_url: str,
    token: str,
    envs: Sequence[RoutedEnv],
    horizon: int,
    stop: threading.Event,
    seed: int,
) -> None:
    rng = np.random.default_rng(seed)
    states = {env.task_id: get_task(env.task_id).num_states for env in envs}
    with StageClient.from_controller(controller_url, timeout_s=60, wait_ready_s=60, token=token) as client:
        routes = {
            f"{log_.name}/{env.pod}/{env.env_index}": TrajRoute(
                env.pod, env.env_index, env.task_id, env.stage_id, int(rng.integers(states[env.task_id]))
            )
            for env in envs
        }
        client.set_routes(routes)
        space = client.action_space
        stages = sorted({route.stage_id for route in routes.values()})
        keys = {s: [k for k, r in routes.items() if r.stage_id == s] for s in stages}
        steps = {key: 0 for key in routes}
        pending = {s: client.call(reset=keys[s]) for s in stages}
        while not stop.is_set():
            for stage in stages:
                try:
                    reset_batch, step_batch = pending[stage].result(timeout=120)
                except Exception as exc:  # every kind of failure counts, and the client goes on
                    log_.errors.append(f"stage {stage}: {type(exc).__name__}: {exc}")
                    time.sleep(0.5)
                    pending[stage] = client.call(reset=keys[stage])
                    continue
                log_.calls.append((time.monotonic(), step_batch.finished_at - step_batch.submitted_at))
                log_.env_steps += step_batch.n
                log_.resets += reset_batch.n
                for key in reset_batch.traj_keys:
                    steps[key] = 0
                ended = {
                    key
                    for row, key in enumerate(step_batch.traj_keys)
                    if step_batch.terminated[row] or step_batch.truncated[row] or steps[key] >= horizon
                }
                if stage == stages[-1]:
                    log_.warm.set()
                step = {}
                for key in keys[stage]:
                    if key not in ended:
                        step[key] = rng.uniform(space.low, space.high).astype(np.float32)
                        steps[key] += 1
                again = {key: int(rng.integers(states[routes[key].task_id])) for key in ended}
                pending[stage] = client.call(reset=again, step=step)
        for call in pending.values():
            try:
                call.result(timeout=120)
            except Exception as exc:
                log_.errors.append(f"last call: {type(exc).__name__}: {exc}")


def windows(calls: list[tuple[float, float]], started: float, window_s: float, duration_s: float) -> list[dict]:
    """p50/p99 call latency (ms) per window of ``window_s`` from ``started``."""
    count = max(1, math.ceil(duration_s / window_s - 1e-9))
    out = []
    for i in range(count):
        begin, end = started + i * window_s, started + (i + 1) * window_s
        latencies = [s for at, s in calls if begin <= at < end]
        row: dict[str, Any] = {"window": i, "from_s": round(i * window_s, 1), "calls": len(latencies)}
        if latencies:
            row["p50_ms"] = round(float(np.percentile(latencies, 50)) * 1e3, 2)
            row["p99_ms"] = round(float(np.percentile(latencies, 99)) * 1e3, 2)
        out.append(row)
    return out


def memory(job: LocalJob) -> dict[str, float]:
    return {name: round(tree_rss(process.pid) / MIB, 1) for name, process in job.processes.items()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("-c", "--config", help="job config YAML (default: a built-in HalfCheetah job)")
    parser.add_argument("--clients", type=int, default=3, help="trainer clients (default 3)")
    duration = parser.add_mutually_exclusive_group()
    duration.add_argument("--seconds", type=float, default=30.0, help="how long to soak (default 30)")
    duration.add_argument("--minutes", type=float, help="how long to soak, in minutes (the long run: 10)")
    parser.add_argument("--window-s", type=float, help="latency window (default 60 s, or a third of a shorter run)")
    parser.add_argument("--horizon", type=int, default=50, help="steps before a trajectory is reset (default 50)")
    parser.add_argument("--json", type=Path, help="write the record here instead of out/bench/soak.json")
    parser.add_argument("--log-dir", type=Path, help="the job's process logs (default: a temporary directory)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    logging.getLogger("httpx").setLevel(logging.WARNING)
    duration_s = args.minutes * 60 if args.minutes is not None else args.seconds
    window_s = args.window_s or (60.0 if duration_s >= 120 else duration_s / 3)
    if args.clients < 1 or duration_s <= 0 or window_s <= 0:
        parser.error("--clients, the duration and --window-s must be positive")

    config = soak_config(args.config)
    with LocalJob(config, log_dir=args.log_dir, grace_s=10) as job:
        table = job.wait_ready(timeout=900)
        envs = routed_envs(table)
        if len(envs) < args.clients:
            raise SystemExit(f"the job has {len(envs)} envs, fewer than --clients {args.clients}")
        logs = [ClientLog(f"client{i}") for i in range(args.clients)]
        stop = threading.Event()
        threads = [
            threading.Thread(
                target=run_client,
                args=(logs[i], job.controller_url, job.token, envs[i :: args.clients], args.horizon, stop, i),
                name=f"soak-client{i}",
                daemon=True,
            )
            for i in range(args.clients)
        ]
        for thread in threads:
            thread.start()
        for entry in logs:
            if not entry.warm.wait(timeout=300):
                stop.set()
                raise SystemExit(f"{entry.name} made no full round of calls within 300 s: {entry.errors}")
        rss_start = memory(job)
        started = time.monotonic()
        log.info("soaking %s with %d clients for %.0f s", config.job.job_id, args.clients, duration_s)
        while not stop.wait(min(10.0, max(0.0, started + duration_s - time.monotonic()))):
            if time.monotonic() >= started + duration_s:
                break
            log.info(
                "%.0f s: %d env steps, %d errors",
                time.monotonic() - started,
                sum(e.env_steps for e in logs),
                sum(len(e.errors) for e in logs),
            )
        stop.set()
        elapsed = time.monotonic() - started
        for thread in threads:
            thread.join(timeout=180)
        rss_end = memory(job)

    calls = [c for entry in logs for c in entry.calls if c[0] >= started]
    per_window = windows(calls, started, window_s, duration_s)
    p99s = [w["p99_ms"] for w in per_window if "p99_ms" in w]
    errors = [f"{entry.name}: {e}" for entry in logs for e in entry.errors]
    summary = {
        "job": config.job.job_id,
        "clients": args.clients,
        "envs": len(envs),
        "duration_s": round(elapsed, 1),
        "window_s": window_s,
        "errors": len(errors),
        "calls": len(calls),
        "env_steps": sum(e.env_steps for e in logs),
        "env_steps_per_s": round(sum(e.env_steps for e in logs) / elapsed, 1),
        "windows": per_window,
        "p99_ms_max_over_min": round(max(p99s) / min(p99s), 2) if p99s else None,
        "rss_mib_start": rss_start,
        "rss_mib_end": rss_end,
    }
    details = {"errors": errors[:100]}
    if args.json is not None:
        record = {"name": "soak", "command": command_line(), "machine": machine_info(), **summary}
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({**record, "details": details}, indent=2) + "\n")
        print(RESULT_PREFIX + json.dumps(record, separators=(",", ":")), flush=True)
    else:
        write_result("soak", summary, details)
    for error in errors[:10]:
        log.error("%s", error)
    return 1 if errors else 0


if __name__ == "__main__":
    sys.exit(main())
