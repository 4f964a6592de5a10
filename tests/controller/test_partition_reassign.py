"""The controller's side of a partition, with real processes: a slot holder cut off from the
controller loses its slot to a spare, and is taken back as a spare when the link heals.

The controller listens on this namespace's end (.1) of a private /24 that the test makes and
deletes (`service_procs.HostLink`); sim-0 lives in a network namespace of its own at .2 and holds
the job's one slot; sim-1, on loopback, is the spare. Taking sim-0's side of the link down stops
its heartbeats: within the heartbeat TTL the controller drops it, gives the slot to sim-1 at a new
generation and routes the slot there. Healed, sim-0 registers again and gets a spare's empty
assignment at that generation, while sim-1 keeps the slot and its envs.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from support.service_procs import HostLink, Server, controller_server, pod_server, running, wait_until

TOKEN = "partition-test-token-0123456789abcdef"
PENDULUM = "gym/Pendulum-v1"
JOB = {
    "job_id": "partition",
    "tasks": [PENDULUM],
    "group_size": 2,
    "num_stages": 1,
    "pods_per_stage": 1,  # one slot, two replicas: one spare
    "camera": {"names": []},
    "max_episode_steps": 20,
}
HEARTBEAT_S = 0.5
TTL_S = 3.0
# Beyond the TTL: one reconcile interval, one missed heartbeat's worth, and a loaded CI machine.
SLACK_S = 5.0
# A healed pod retries the controller with its backoff (at most 10 s), then re-registers.
RETURN_S = 30.0
BUILD_S = 60.0


@pytest.fixture
def link() -> Iterator[HostLink]:
    if os.geteuid() != 0 or shutil.which("ip") is None:
        pytest.skip("needs root and iproute2's `ip` to make a network namespace")
    made = HostLink()
    try:
        try:
            made.create()
        except (subprocess.CalledProcessError, FileNotFoundError) as exc:
            detail = exc.stderr.strip() if isinstance(exc, subprocess.CalledProcessError) else exc
            pytest.skip(f"`ip netns` is not permitted here: {detail}")
        yield made
    finally:
        made.delete()


def get(server: Server, path: str) -> Any:
    response = httpx.get(f"{server.url}{path}", timeout=5)
    response.raise_for_status()
    return response.json()


def pods(controller: Server) -> dict[str, dict[str, Any]]:
    """The controller's registry (GET /v1/pods), by pod name."""
    return {record["pod"]: record for record in get(controller, "/v1/pods")}


def routing(controller: Server) -> dict[str, Any] | None:
    """The routing table, or None before the first plan."""
    response = httpx.get(f"{controller.url}/v1/routing", timeout=5)
    return response.json() if response.status_code == 200 else None


def holder(table: dict[str, Any] | None) -> dict[str, Any] | None:
    """The routed pod of the job's one slot when the table is ready, else None."""
    if table is None or not table["ready"]:
        return None
    (routed,) = table["stages"][0]["pods"]
    return routed


def expired_count(controller: Server) -> float:
    text = httpx.get(f"{controller.url}/metrics", timeout=5).text
    (line,) = [ln for ln in text.splitlines() if ln.startswith("vecsim_controller_pods_expired_total ")]
    return float(line.split()[1])


@pytest.mark.slow
def test_a_slot_holder_partitioned_from_the_controller_loses_its_slot_to_the_spare_and_returns_as_a_spare(
    link: HostLink, tmp_path: Path
):
    gateway = str(link.subnet.network_address + 1)  # this namespace's end of the veth
    # The controller must be reachable from sim-0's namespace: it listens on the veth's address.
    controller = controller_server(
        tmp_path,
        host=gateway,
        token=TOKEN,
        args=["--heartbeat-interval", str(HEARTBEAT_S), "--heartbeat-ttl", str(TTL_S), "--reconcile-interval", "0.2"],
    )
    agent = {"CONTROLLER_URL": controller.url, "VECSIM_HEARTBEAT_INTERVAL_S": str(HEARTBEAT_S), "VECSIM_MAX_ENVS": "4"}
    far = pod_server("sim-0", tmp_path, token=TOKEN, host=link.address, wrap=link.wrap(), POD_IP=link.address, **agent)
    near = pod_server("sim-1", tmp_path, token=TOKEN, **agent)

    with running(controller):
        put = httpx.put(f"{controller.url}/v1/job", json=JOB, headers={"Authorization": f"Bearer {TOKEN}"}, timeout=10)
        assert put.status_code == 200, put.text
        with running(far):
            # sim-0 takes the slot before the spare exists, so the test knows who holds it.
            wait_until(lambda: pods(controller).get("sim-0", {}).get("stage_id") == 0, "sim-0 to hold the slot")
            with running(near):
                before = wait_until(lambda: holder(routing(controller)), "the job to be ready on sim-0", BUILD_S)
                assert before["pod"] == "sim-0" and before["url"] == far.url
                generation_before = routing(controller)["generation"]
                wait_until(lambda: pods(controller).get("sim-1", {}).get("generation") is not None, "the spare")
                assert pods(controller)["sim-1"]["stage_id"] is None

                link.cut()
                try:
                    # The controller drops the silent pod within its TTL (plus bounded slack) ...
                    wait_until(
                        lambda: "sim-0" not in pods(controller), "sim-0 to be dropped", TTL_S + SLACK_S, every=0.05
                    )
                    assert expired_count(controller) == 1
                    # ... gives the slot to the spare at a new generation, and routes it there.
                    after = wait_until(
                        lambda: (h := holder(routing(controller))) and h["pod"] == "sim-1" and h,
                        "the slot to be ready on sim-1",
                        BUILD_S,
                    )
                    table = routing(controller)
                    generation = table["generation"]
                    assert generation > generation_before
                    assert after["url"] == near.url
                    assert (after["num_envs"], after["tasks"]) == (before["num_envs"], before["tasks"])
                    registry = pods(controller)
                    assert list(registry) == ["sim-1"]
                    assert registry["sim-1"]["stage_id"] == 0 and registry["sim-1"]["ready"]
                    assert registry["sim-1"]["generation"] == generation
                    assert near.answers("/readyz")
                    info = get(near, "/v1/info")
                    assert (info["generation"], info["stage_id"], info["num_envs"]) == (generation, 0, 2)
                    assert [(t["task_id"], t["env_start"], t["num_envs"]) for t in info["tasks"]] == [
                        (b["task_id"], b["env_start"], b["num_envs"]) for b in before["tasks"]
                    ]
                    holder_instance = info["instance"]
                finally:
                    link.heal()

                # Healed: sim-0 registers again and takes a spare's empty assignment at the
                # current generation; the slot, its routing and sim-1's envs stay as they were.
                wait_until(
                    lambda: pods(controller).get("sim-0", {}).get("generation") == generation,
                    "sim-0 to come back as a spare",
                    RETURN_S,
                )
                registry = pods(controller)
                assert registry["sim-0"]["stage_id"] is None and registry["sim-0"]["url"] == far.url
                assert registry["sim-1"]["stage_id"] == 0 and registry["sim-1"]["generation"] == generation
                spare = get(far, "/v1/info")
                assert (spare["generation"], spare["num_envs"], spare["tasks"]) == (generation, 0, [])
                table = routing(controller)
                assert table["generation"] == generation and holder(table) == after
                kept = get(near, "/v1/info")
                assert (kept["generation"], kept["instance"]) == (generation, holder_instance)
                assert expired_count(controller) == 1
