"""The controller's side of faults, with real processes on loopback.

- A pod URL that answers a push with an absurd Content-Length (a raw socket server written here)
  costs a failed push, backed off and retried; the controller keeps serving.
- A client that asks for the routing table while no controller listens waits, with backoff, and
  when it gives up says what it waited for.
- A long-lived client places its next batch on the routing table of a reassignment that finished
  before the batch: the slot of a killed pod went to the spare, and nothing of the batch is lost.
- A pod and the controller killed together: the restarted controller plans as soon as every pod
  has reported (the restarted pod takes its slot back), long before its adopt grace would end.
"""

from __future__ import annotations

import os
import re
import signal

import httpx
import pytest
import torch
from support.service_procs import controller_server, job_config, pod_server, raw_server, running, wait_until

from service.controller import ControllerSettings
from service.runner import Backoff, LocalJob
from vecsim.config import RoutingTable

from vecsim.client import StageClient
from vecsim.rollout import EnvLoop

HOSTILE_PUSH_ANSWER = (
    b"HTTP/1.1 200 OK\r\nContent-Type: application/json\r\nContent-Length: 18446744073709551616\r\n\r\n"
)
JOB = {
    "job_id": "hostile",
    "tasks": ["gym/Pendulum-v1"],
    "group_size": 1,
    "num_stages": 1,
    "pods_per_stage": 1,
    "camera": {"names": []},
}


def failed_pushes(url: str) -> float:
    text = httpx.get(f"{url}/metrics", timeout=5).text
    found = re.search(r'^vecsim_controller_pushes_total\{result="failed"\} (\S+)$', text, re.M)
    return float(found.group(1)) if found else 0.0


def test_a_push_answered_with_an_absurd_content_length_is_a_failed_push_retried_with_backoff(tmp_path):
    served: list[bytes] = []
    with (
        raw_server(HOSTILE_PUSH_ANSWER, served) as pod_url,
        running(controller_server(tmp_path, args=["--adopt-grace", "0"])) as c,
    ):
        assert httpx.put(f"{c.url}/v1/job", json=JOB, timeout=30).status_code == 200
        assert httpx.post(f"{c.url}/v1/pods", json={"pod": "sim-0", "url": pod_url}, timeout=10).status_code == 200

        def failed_twice() -> bool:
            httpx.post(f"{c.url}/v1/pods/sim-0/heartbeat", json={"url": pod_url, "ready": False}, timeout=10)
            return failed_pushes(c.url) >= 2

        wait_until(failed_twice, "two failed pushes recorded", timeout_s=60, every=0.5)
        assert c.answers("/healthz")
    # Each failed push was one request to the pod: the retries came after the failures, not in a loop.
    assert len(served) >= 2


def test_waiting_for_a_controller_that_never_listens_gives_up_saying_what_it_waited_for(refusing_port):
    url = f"http://127.0.0.1:{refusing_port}"
    with pytest.raises(TimeoutError) as caught:
        StageClient.from_controller(url, timeout_s=1, wait_ready_s=1.5)
    message = str(caught.value)
    assert f"{url}/v1/routing" in message and "ready routing table" in message and "no answer" in message


def ready_holder(controller_url: str) -> str | None:
    """The pod holding the job's one slot, once the routing table is ready."""
    response = httpx.get(f"{controller_url}/v1/routing", timeout=5)
    if response.status_code != 200 or not response.json()["ready"]:
        return None
    (routed,) = response.json()["stages"][0]["pods"]
    return routed["pod"]


@pytest.mark.slow
def test_a_long_lived_client_places_its_next_batch_on_the_routing_a_finished_reassignment_made(tmp_path):
    job = {**JOB, "group_size": 2, "max_episode_steps": 10}
    requests, keys = [("gym/Pendulum-v1", 0), ("gym/Pendulum-v1", 1)], ["t0", "t1"]
    controller = controller_server(tmp_path, args=["--heartbeat-interval", "0.5", "--heartbeat-ttl", "3"])
    agent = {"CONTROLLER_URL": controller.url, "VECSIM_HEARTBEAT_INTERVAL_S": "0.5", "VECSIM_MAX_ENVS": "2"}

    def policy(obs, instructions, task_ids) -> torch.Tensor:
        return torch.clamp(-0.5 * obs[:, 2:3], -2.0, 2.0)

    with running(controller):
        assert httpx.put(f"{controller.url}/v1/job", json=job, timeout=30).status_code == 200
        with running(pod_server("sim-0", tmp_path, **agent)) as first:
            wait_until(lambda: ready_holder(controller.url) == "sim-0", "the slot ready on sim-0")
            with running(pod_server("sim-1", tmp_path, **agent)):
                with StageClient.from_controller(controller.url, timeout_s=10, wait_ready_s=60) as client:
                    loop = EnvLoop(client, policy, horizon=10)
                    before = loop.run(requests, keys)
                    first.signal_group(signal.SIGKILL)  # between batches: the spare takes the slot
                    wait_until(lambda: ready_holder(controller.url) == "sim-1", "the slot ready on sim-1")
                    after = loop.run(requests, keys)
    assert before.lost == {} and after.lost == {}
    assert sorted(after.trajectories) == keys and all(t.length == 10 for t in after.trajectories.values())
    for key in keys:
        mine, theirs = after.trajectories[key], before.trajectories[key]
        assert torch.equal(mine.observations, theirs.observations)


def ready_table(controller_url: str) -> RoutingTable | None:
    try:
        table = RoutingTable.model_validate(httpx.get(f"{controller_url}/v1/routing", timeout=2).json())
    except (httpx.HTTPError, ValueError):
        return None
    return table if table.ready else None


@pytest.mark.slow
def test_a_pod_and_the_controller_killed_together_heal_before_the_adopt_grace_would_end(tmp_path):
    grace = ControllerSettings.model_fields["adopt_grace_s"].default
    two_stages = {**JOB, "job_id": "heal", "group_size": 2, "num_stages": 2}
    config = job_config(two_stages, replicas=2)
    with LocalJob(config, log_dir=tmp_path, grace_s=10, backoff=Backoff(initial_s=0.2)) as job:
        job.wait_ready(timeout=180)
        before = ready_table(job.controller_url)
        for name in ("controller", "sim-0"):
            os.killpg(job.processes[name].pid, signal.SIGKILL)

        def healed() -> RoutingTable | None:
            table = ready_table(job.controller_url)
            return table if table is not None and table.generation > before.generation else None

        # Only a plan made before the grace ends can be ready within it (sim-0 runs nothing now).
        after = wait_until(healed, "the job ready again at a new generation", timeout_s=grace - 5, every=0.1)
        restarts = {name: job.processes[name].restarts for name in ("controller", "sim-0", "sim-1")}
        log = (tmp_path / "controller.log").read_text()
    assert restarts == {"controller": 1, "sim-0": 1, "sim-1": 0}
    assert [(s.stage_id, p.pod, p.url) for s in after.stages for p in s.pods] == [
        (s.stage_id, p.pod, p.url) for s in before.stages for p in s.pods
    ]
    assert "adopted 1 slots" in log
