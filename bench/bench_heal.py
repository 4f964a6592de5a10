"""Heal time: a pod and the controller killed together, until the routing table is ready again.

Starts a local job (``LocalJob``: the controller and two pods as processes, two stages of one pod,
``gym/Pendulum-v1`` with 2 envs per pod, heartbeats every 0.5 s, restarts after 0.2 s) and, each
round, sends SIGKILL to the controller's and sim-0's process groups at once; the runner restarts
both. Measured per round, in seconds from the kill: ``planned_s``, until ``GET /v1/routing``
answers a table at a new generation (the controller has planned), and ``heal_s``, until that
table is ready with the layout it had (sim-0 back in its slot, its envs built). The baseline is
the adopt grace the controller would have waited for (``adopt_grace_s``, 30 s by default).

    python bench/bench_heal.py              # 5 rounds
    python bench/bench_heal.py --rounds 10

Prints ``RESULT {json}``; writes out/bench/bench_heal.json.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import time

import httpx
from lib.records import spread, write_result

from service.controller import ControllerSettings
from service.runner import Backoff, LocalJob
from service.runner.ports import free_port, free_port_block
from vecsim.config import JobConfig, RoutingTable

log = logging.getLogger("bench_heal")

JOB = {
    "job_id": "heal",
    "tasks": ["gym/Pendulum-v1"],
    "group_size": 2,
    "num_stages": 2,
    "pods_per_stage": 1,
    "camera": {"names": []},
}
POLL_S = 0.05


def heal_config() -> JobConfig:
    """The job on free ports, with the test job's heartbeat timing (tests/support/service_procs.py)."""
    controller_port = free_port()
    return JobConfig.model_validate(
        {
            "job": JOB,
            "pods": {"replicas": 2, "base_port": free_port_block(2, avoid={controller_port}), "max_envs": 16},
            "controller": {
                "port": controller_port,
                "heartbeat_interval_s": 0.5,
                "heartbeat_ttl_s": 3.0,
                "reconcile_interval_s": 0.25,
            },
        }
    )


def layout(table: RoutingTable) -> list[tuple[int, str, str]]:
    return [(s.stage_id, p.pod, p.url) for s in table.stages for p in s.pods]


def routing_table(url: str) -> RoutingTable | None:
    """The controller's table (ready or not), None while it answers none."""
    try:
        response = httpx.get(f"{url}/v1/routing", timeout=2)
        return RoutingTable.model_validate(response.json()) if response.status_code == 200 else None
    except (httpx.HTTPError, ValueError):
        return None


def heal_once(job: LocalJob, limit_s: float) -> tuple[float, float, RoutingTable, RoutingTable]:
    """Kill the controller and sim-0 together; return the seconds until the controller planned
    and until the job was ready again, and the tables before and after.

    Raises:
        TimeoutError: not ready again within ``limit_s``.
    """
    before = routing_table(job.controller_url)
    assert before is not None and before.ready, "the job is not ready before the kill"
    groups = [job.processes[name].pid for name in ("controller", "sim-0")]
    killed = time.monotonic()
    for pgid in groups:
        os.killpg(pgid, signal.SIGKILL)
    planned = None
    while time.monotonic() - killed < limit_s:
        after = routing_table(job.controller_url)
        if after is not None and after.generation > before.generation:
            planned = planned or time.monotonic() - killed
            if after.ready:
                return planned, time.monotonic() - killed, before, after
        time.sleep(POLL_S)
    raise TimeoutError(f"the job was not ready again within {limit_s} s of the kill")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    grace = ControllerSettings.model_fields["adopt_grace_s"].default
    planned_s, heal_s = [], []
    # The runner's restart backoff is reset after a process ran this long: every round starts alike.
    backoff = Backoff(initial_s=0.2, reset_after_s=5.0)
    with LocalJob(heal_config(), grace_s=10, backoff=backoff) as job:
        job.wait_ready(timeout=180)
        for i in range(args.rounds):
            time.sleep(backoff.reset_after_s + 1)
            planned, healed, before, after = heal_once(job, 2 * grace)
            assert layout(after) == layout(before), "the layout moved"
            planned_s.append(round(planned, 2))
            heal_s.append(round(healed, 2))
            log.info("round %d: planned after %.2f s, ready again after %.2f s", i, planned, healed)
    write_result(
        "bench_heal",
        {"planned_s": spread(planned_s), "heal_s": spread(heal_s), "adopt_grace_s": grace, "rounds": args.rounds},
        {"planned_s": planned_s, "heal_s": heal_s},
    )


if __name__ == "__main__":
    main()
