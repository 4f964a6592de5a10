"""Benchmark 6, control plane: the controller with 1,000 registered pods heartbeating.

A real controller process (``vecsim controller``, token on) and simulated pods on loopback: each
simulated pod registers, heartbeats every ``heartbeat_interval_s`` with the assignment it holds
(as ``service.pod.agent`` does), through an async httpx client; one small aiohttp server in this
process answers every pod's ``PUT /v1/assignment`` (pod ``sim-i`` is reached at
``http://127.0.0.1:<port>/p/sim-i``) and the pod reports that assignment, ready, from its next
heartbeat on, as a pod whose envs build at once would.

Measured, for a fleet of P pods (the baseline: the same with 10 pods, in the same run):

- heartbeat latency (request sent to answer read, at the simulated pod), p50 and p99, over a
  steady window once the job is ready;
- replan time after a pod loss: a slot holder stops heartbeating; from the moment its TTL ran
  out (its last heartbeat's send time + TTL) to the routing table showing a new generation
  without it (``replan_s``), and to the table being ready again with a spare in its slot
  (``recovered_s``, which includes the spare's next heartbeat).

The job has ~2% spare pods (at least one more than the pods lost) and slots of one or two tasks
(LIBERO's five suites' tasks; tiny and robosuite ones with ``--quick``); the controller runs with its default intervals
(heartbeat 1 s, TTL 5 s, reconcile 0.5 s), pinned to the last core, and the simulated pods (this
process) to the others: on a cluster the pods run elsewhere, and a load generator sharing the
controller's core would be measured as the controller's latency. Fleet sizes alternate round by
round.

    python bench/bench_control_plane.py [--quick] [--pods 1000] [--rounds 2] [--window-s 10]

Prints ``RESULT {json}`` and writes out/bench/bench_control_plane.json.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import logging
import math
import os
import secrets
import statistics
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
from lib.pods import (
    controller_server,
    free_port,
    running,
    setup_logging,
    wait_for_quiet,
)
from aiohttp import web
from lib.records import write_result

from vecsim.auth import bearer_headers
from vecsim.engine.tasks import suite_tasks
from vecsim.transport import HttpxTransport, make_async_client

log = logging.getLogger("bench.control_plane")

TARGET_P99_MS = 50.0
TARGET_REPLAN_S = 1.0
BASELINE_PODS = 10


@dataclass(frozen=True)
class ControllerTiming:
    """The controller's intervals: the defaults of ``ControllerConfig``, shorter under --quick."""

    heartbeat_interval_s: float = 1.0
    heartbeat_ttl_s: float = 5.0
    reconcile_interval_s: float = 0.5


def robot_tasks(with_libero: bool) -> list[str]:
    """Task ids that can make up one job (a job's tasks share one pair of spaces): LIBERO's five
    suites (130 tasks; their observation carries LIBERO's ``state``), or without LIBERO the tiny
    and robosuite tasks."""
    if with_libero:
        suites = ["libero_10", "libero_spatial", "libero_object", "libero_goal", "libero_90"]
    else:
        suites = ["tiny", "robosuite"]
    return [spec.task_id for suite in suites for spec in suite_tasks(suite)]


def job_for(pods: int, tasks: list[str], losses: int) -> dict[str, Any]:
    """A job that fills ~98% of ``pods`` with slots of one or two tasks; the rest are spares,
    at least one more than the pods to be lost, so that every lost slot finds a spare."""
    spares = max(losses + 1, pods // 50)
    stages = 2 if pods <= 20 else 8
    per_stage = (pods - spares) // stages
    count = min(len(tasks), math.ceil(1.2 * per_stage))
    return {
        "job_id": f"bench-{pods}",
        "tasks": tasks[:count],
        "group_size": 1,
        "num_stages": stages,
        "pods_per_stage": per_stage,
        "camera": {"names": ["agentview"], "height": 64, "width": 64},
    }


@contextlib.contextmanager
def controller_process(timing: ControllerTiming, token: str, workdir: Path, core: int) -> Iterator[str]:
    """Run ``vecsim controller`` on a free port, pinned to ``core``, until the block ends; yield its URL."""
    args = [
        "--heartbeat-interval",
        str(timing.heartbeat_interval_s),
        "--heartbeat-ttl",
        str(timing.heartbeat_ttl_s),
        "--reconcile-interval",
        str(timing.reconcile_interval_s),
        "--adopt-grace",
        "0",
        "--log-level",
        "warning",
    ]
    with running(controller_server(workdir, args=args, token=token, wrap=("taskset", "-c", str(core)))) as server:
        yield server.url


@dataclass
class SimulatedPod:
    """One pod's control-plane side: what it was assigned, and when its heartbeats went out."""

    name: str
    url: str
    assignment: dict[str, Any] | None = None
    alive: bool = True
    last_sent: float = 0.0
    samples: list[tuple[float, float]] = field(default_factory=list)  # (sent at, latency s)


class Fleet:
    """P simulated pods heartbeating one controller, and the server that takes their assignments."""

    def __init__(self, controller_url: str, token: str, pods: int, timing: ControllerTiming) -> None:
        self.controller_url = controller_url
        self.timing = timing
        self.headers = bearer_headers(token)
        self.port = free_port()
        self.pods = {
            f"sim-{i}": SimulatedPod(f"sim-{i}", f"http://127.0.0.1:{self.port}/p/sim-{i}") for i in range(pods)
        }
        self.errors: list[str] = []
        self._runner: web.AppRunner | None = None
        self._tasks: list[asyncio.Task[None]] = []
        self._client: httpx.AsyncClient | None = None

    async def _put_assignment(self, request: web.Request) -> web.Response:
        pod = self.pods.get(request.match_info["pod"])
        if pod is None:
            return web.json_response({"detail": "no such pod"}, status=404)
        pod.assignment = json.loads(await request.read())
        return web.json_response({"generation": pod.assignment["generation"], "rebuilt": True})

    async def start(self) -> None:
        """Serve the pods' assignment endpoint, register every pod, start their heartbeats."""
        app = web.Application()
        app.router.add_put("/p/{pod}/v1/assignment", self._put_assignment)
        self._runner = web.AppRunner(app, access_log=None)
        await self._runner.setup()
        await web.TCPSite(self._runner, "127.0.0.1", self.port).start()
        pods_transport = HttpxTransport(
            httpx.AsyncHTTPTransport(limits=httpx.Limits(max_connections=256), trust_env=False)
        )
        self._client = make_async_client(pods_transport, timeout=30.0, headers=self.headers)
        await asyncio.gather(*(self._register(pod) for pod in self.pods.values()))
        interval = self.timing.heartbeat_interval_s
        for i, pod in enumerate(self.pods.values()):
            # Spread over the interval, as independent pods would be.
            phase = interval * i / len(self.pods)
            self._tasks.append(asyncio.create_task(self._heartbeats(pod, phase)))

    async def _register(self, pod: SimulatedPod) -> None:
        assert self._client is not None
        body = {"pod": pod.name, "url": pod.url, "capacity": {"max_envs": 64, "gpu": False}}
        response = await self._client.post(f"{self.controller_url}/v1/pods", json=body)
        if response.status_code != 200:
            raise RuntimeError(f"registering {pod.name}: {response.status_code} {response.text[:200]}")

    async def _heartbeats(self, pod: SimulatedPod, phase: float) -> None:
        assert self._client is not None
        interval = self.timing.heartbeat_interval_s
        url = f"{self.controller_url}/v1/pods/{pod.name}/heartbeat"
        next_at = time.perf_counter() + phase
        while pod.alive:
            await asyncio.sleep(max(0.0, next_at - time.perf_counter()))
            next_at += interval
            if not pod.alive:
                return
            assignment = pod.assignment
            body = {
                "url": pod.url,
                "generation": assignment["generation"] if assignment else None,
                "assignment": assignment,
                "ready": assignment is not None,
            }
            sent = time.perf_counter()
            try:
                response = await self._client.post(url, json=body)
            except httpx.HTTPError as exc:
                self.errors.append(f"{pod.name}: {type(exc).__name__}: {exc}")
                continue
            if response.status_code == 404:
                await self._register(pod)
                continue
            if response.status_code != 200:
                self.errors.append(f"{pod.name}: heartbeat answered {response.status_code}: {response.text[:200]}")
                continue
            pod.last_sent = sent
            pod.samples.append((sent, time.perf_counter() - sent))

    async def routing(self) -> dict[str, Any] | None:
        """The controller's routing table (None before a plan)."""
        assert self._client is not None
        response = await self._client.get(f"{self.controller_url}/v1/routing")
        return response.json() if response.status_code == 200 else None

    async def wait_ready(self, timeout_s: float) -> dict[str, Any]:
        """Wait until the routing table is ready; return it.

        Raises:
            TimeoutError: not ready within ``timeout_s`` (the controller's reason included).
        """
        assert self._client is not None
        deadline = time.perf_counter() + timeout_s
        while time.perf_counter() < deadline:
            table = await self.routing()
            if table is not None and table["ready"]:
                return table
            await asyncio.sleep(0.25)
        detail = (await self._client.get(f"{self.controller_url}/readyz")).text[:500]
        raise TimeoutError(f"job with {len(self.pods)} pods not ready in {timeout_s} s: {detail}")

    async def lose_pod(self, name: str, poll_s: float = 0.05) -> dict[str, float]:
        """Stop pod ``name``'s heartbeats; return how long replanning and recovery took."""
        pod = self.pods[name]
        before = (await self.routing()) or {}
        pod.alive = False
        await asyncio.sleep(self.timing.heartbeat_interval_s * 0.5)  # a heartbeat in flight lands
        expired_at = pod.last_sent + self.timing.heartbeat_ttl_s
        replanned_at = recovered_at = None
        deadline = expired_at + 30
        while time.perf_counter() < deadline and recovered_at is None:
            await asyncio.sleep(poll_s)
            table = await self.routing()
            if table is None or table["generation"] == before.get("generation"):
                continue
            holders = {p["pod"] for stage in table["stages"] for p in stage["pods"]}
            if name in holders:
                continue
            now = time.perf_counter()
            replanned_at = replanned_at or now
            if table["ready"]:
                recovered_at = now
        if replanned_at is None or recovered_at is None:
            raise TimeoutError(f"no replan after losing {name} within 30 s of its TTL")
        return {"replan_s": replanned_at - expired_at, "recovered_s": recovered_at - expired_at}

    async def stop(self) -> None:
        """Stop every heartbeat, the assignment server and the client."""
        for pod in self.pods.values():
            pod.alive = False
        for task in self._tasks:
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        if self._client is not None:
            await self._client.aclose()
        if self._runner is not None:
            await self._runner.cleanup()

    def latencies_between(self, start: float, end: float) -> list[float]:
        """Heartbeat latencies (s) of heartbeats sent in ``[start, end)``."""
        return [lat for pod in self.pods.values() for sent, lat in pod.samples if start <= sent < end]


def _percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, max(0, math.ceil(q / 100 * len(ordered)) - 1))]


async def _loop_lag(stop: asyncio.Event, into: list[float], every_s: float = 0.05) -> None:
    """How late this process's own event loop wakes up: the load generator's share of latency."""
    while not stop.is_set():
        before = time.perf_counter()
        await asyncio.sleep(every_s)
        into.append(time.perf_counter() - before - every_s)


async def run_fleet(
    pods: int, tasks: list[str], timing: ControllerTiming, window_s: float, losses: int, workdir: Path, core: int
) -> dict[str, Any]:
    """One controller, ``pods`` simulated pods: latency over a steady window, then pod losses."""
    token = secrets.token_urlsafe(24)
    job = job_for(pods, tasks, losses)
    with controller_process(timing, token, workdir, core) as url:
        put = httpx.put(f"{url}/v1/job", json=job, headers=bearer_headers(token), timeout=120)
        if put.status_code != 200:
            raise RuntimeError(f"controller refused the job: {put.status_code} {put.text[:500]}")
        fleet = Fleet(url, token, pods, timing)
        stop, lag = asyncio.Event(), []
        lag_task = asyncio.create_task(_loop_lag(stop, lag))
        try:
            started = time.perf_counter()
            await fleet.start()
            table = await fleet.wait_ready(timeout_s=120 + pods * 0.1)
            ready_s = time.perf_counter() - started
            # One interval to settle (the first heartbeats after the pushes), then the window.
            await asyncio.sleep(timing.heartbeat_interval_s)
            window_start = time.perf_counter()
            lag.clear()
            await asyncio.sleep(window_s)
            window_end = time.perf_counter()
            window_lag = list(lag)
            holders = [p["pod"] for stage in table["stages"] for p in stage["pods"]]
            lost = [await fleet.lose_pod(name) for name in holders[:losses]]
        finally:
            stop.set()
            await lag_task
            await fleet.stop()
    latencies = fleet.latencies_between(window_start, window_end)
    if not latencies:
        raise RuntimeError(f"no heartbeat answered in the window; errors: {fleet.errors[:5]}")
    return {
        "pods": pods,
        "slots": job["num_stages"] * job["pods_per_stage"],
        "tasks": len(job["tasks"]),
        "ready_after_s": round(ready_s, 2),
        "heartbeats_in_window": len(latencies),
        "heartbeats_per_s": round(len(latencies) / window_s, 1),
        "heartbeat_ms": {
            "p50": round(1000 * statistics.median(latencies), 2),
            "p99": round(1000 * _percentile(latencies, 99), 2),
            "max": round(1000 * max(latencies), 2),
        },
        "generator_loop_lag_ms_p99": round(1000 * _percentile(window_lag, 99), 2) if window_lag else None,
        "losses": lost,
        "replan_s_max": round(max(x["replan_s"] for x in lost), 3) if lost else None,
        "recovered_s_max": round(max(x["recovered_s"] for x in lost), 3) if lost else None,
        "errors": fleet.errors[:10],
        "error_count": len(fleet.errors),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="tiny sizes, for the smoke test")
    parser.add_argument("--pods", type=int, default=1000)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--window-s", type=float, default=10.0)
    parser.add_argument("--losses", type=int, default=3, help="pods lost one after another per fleet")
    parser.add_argument("--wait-quiet-s", type=float, default=0.0, help="wait up to this long for load < 1.5")
    args = parser.parse_args()
    setup_logging()
    load_before = wait_for_quiet(timeout_s=args.wait_quiet_s)
    if args.quick:
        sizes, rounds, window_s, losses = (4, 12), 1, 1.5, 1
        timing = ControllerTiming(heartbeat_interval_s=0.25, heartbeat_ttl_s=1.0, reconcile_interval_s=0.25)
        tasks = robot_tasks(with_libero=False)
    else:
        sizes, rounds, window_s, losses = (BASELINE_PODS, args.pods), args.rounds, args.window_s, args.losses
        timing = ControllerTiming()
        tasks = robot_tasks(with_libero=True)
    workdir = Path(tempfile.mkdtemp(prefix="vecsim-bench-cp-"))
    # The controller gets a core of its own, the simulated pods the others (on a cluster they run
    # on other machines): otherwise the load generator's CPU would count as the controller's latency.
    cores = sorted(os.sched_getaffinity(0))
    controller_core = cores[-1]
    if len(cores) > 1:
        os.sched_setaffinity(0, set(cores[:-1]))
    runs: dict[int, list[dict[str, Any]]] = {size: [] for size in sizes}
    for r in range(rounds):
        for size in sizes if r % 2 == 0 else sizes[::-1]:
            log.info("round %d: %d pods", r + 1, size)
            runs[size].append(asyncio.run(run_fleet(size, tasks, timing, window_s, losses, workdir, controller_core)))
            log.info("%d pods: %s", size, {k: v for k, v in runs[size][-1].items() if k != "losses"})
    base, large = sizes
    p99 = max(run["heartbeat_ms"]["p99"] for run in runs[large])
    replan = max(run["replan_s_max"] for run in runs[large])
    base_p99 = max(run["heartbeat_ms"]["p99"] for run in runs[base])
    base_replan = max(run["replan_s_max"] for run in runs[base])
    summary = {
        "baseline": f"the same controller with {base} pods",
        "pods": large,
        "heartbeat_p99_ms": p99,
        "replan_s": replan,
        "baseline_heartbeat_p99_ms": base_p99,
        "baseline_replan_s": base_replan,
        "ratio": round(p99 / base_p99, 2),
        "ratio_replan": round(replan / base_replan, 2),
        "target": f"p99 < {TARGET_P99_MS:.0f} ms, replan < {TARGET_REPLAN_S:.0f} s",
        "met": p99 < TARGET_P99_MS and replan < TARGET_REPLAN_S,
        "quick": args.quick,
        "load_avg_before": round(load_before, 2),
        "timing": timing.__dict__,
        "controller_core": controller_core,
        "generator_cores": sorted(os.sched_getaffinity(0)),
        "runs": {size: [{k: v for k, v in run.items() if k != "losses"} for run in rs] for size, rs in runs.items()},
    }
    write_result("bench_control_plane", summary, {"runs": runs})


if __name__ == "__main__":
    main()
