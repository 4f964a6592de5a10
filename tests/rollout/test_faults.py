"""Faults, with real processes: what a pipelined rollout loses and what it keeps.

A local job (controller + two pods, two stages, a cheap gymnasium task, the job's token) runs one
rollout without any fault: the reference. Each fault then strikes in the middle of the same
rollout (a scripted policy triggers it at a fixed call): the rollout must finish, lose nothing
but the trajectories of the pod that failed (reported by traj_key), and every other trajectory
must be bit-identical to the reference. Standalone pods serve the partition (a network namespace
this test makes and deletes) and the slow pod (SIGSTOP for a bounded time).
"""

from __future__ import annotations

import os
import signal
import subprocess
import threading
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import psutil
import pytest
import torch
from support.service_procs import HostLink, Server, assignment_file, job_config, pod_server, running, wait_until

from service.runner import Backoff, LocalJob
from vecsim.client import PodUnavailableError, StageClient
from vecsim.config import RoutingTable
from vecsim.rollout import EnvLoop, RolloutResult, Trajectory

TOKEN = "faults-test-token-0123456789abcdef"
PENDULUM = "gym/Pendulum-v1"
EPISODE = 40
JOB = {
    "job_id": "faults",
    "tasks": [PENDULUM],
    "group_size": 2,
    "num_stages": 2,
    "pods_per_stage": 1,
    "camera": {"names": []},
    "max_episode_steps": EPISODE,
}
# Request i runs on stage i % 2: t0 and t2 on stage 0 (pod sim-0), t1 and t3 on stage 1 (sim-1).
REQUESTS = [(PENDULUM, 0), (PENDULUM, 1), (PENDULUM, 2), (PENDULUM, 3)]
KEYS = ["t0", "t1", "t2", "t3"]
ON_STAGE = {0: {"t0", "t2"}, 1: {"t1", "t3"}}
# The fault strikes at this policy call: both stages have taken a few steps, most are to come.
STRIKE_AT = 8


class ScriptedPolicy:
    """A deterministic policy (a function of each observation alone) that runs ``fault`` once,
    at its ``at``-th call, in the middle of the rollout."""

    def __init__(self, fault: Callable[[], None] | None = None, at: int = STRIKE_AT) -> None:
        self.fault, self.at, self.calls = fault, at, 0

    def __call__(self, obs: dict[str, Any], instructions: list[str], task_ids: list[str]) -> torch.Tensor:
        self.calls += 1
        if self.calls == self.at and self.fault is not None:
            self.fault()
        return torch.clamp(-0.5 * obs[:, 2:3], -2.0, 2.0)


def assert_identical(mine: Trajectory, reference: Trajectory) -> None:
    assert mine.route.task_id == reference.route.task_id and mine.route.state_id == reference.route.state_id
    assert mine.length == reference.length
    assert torch.equal(mine.observations, reference.observations), mine.traj_key
    assert torch.equal(mine.actions, reference.actions), mine.traj_key
    assert torch.equal(mine.rewards, reference.rewards), mine.traj_key
    assert (mine.terminated, mine.truncated) == (reference.terminated, reference.truncated)


def resampled(result: RolloutResult) -> list[tuple[str, int]]:
    """The requests of a rollout's lost trajectories, to run again."""
    return [(lost.route.task_id, lost.route.state_id) for lost in result.lost.values()]


def layout(table: RoutingTable) -> list[tuple[int, str, str]]:
    return [(s.stage_id, p.pod, p.url) for s in table.stages for p in s.pods]


def routing(job: LocalJob) -> RoutingTable:
    return RoutingTable.model_validate(httpx.get(f"{job.controller_url}/v1/routing", timeout=5).json())


def ready_routing(job: LocalJob) -> RoutingTable | None:
    try:
        table = routing(job)
    except (httpx.HTTPError, ValueError):
        return None
    return table if table.ready else None


def kill_group(pid: int) -> None:
    """kill -9 of a process and everything it started (a pod's env workers)."""
    os.killpg(pid, signal.SIGKILL)


@pytest.fixture(scope="module")
def job(tmp_path_factory) -> Iterator[LocalJob]:
    config = job_config(JOB, replicas=2)
    local = LocalJob(
        config, log_dir=tmp_path_factory.mktemp("faults"), grace_s=10, backoff=Backoff(initial_s=0.2), token=TOKEN
    )
    with local:
        local.wait_ready(timeout=180)
        yield local


def roll_out(
    job: LocalJob,
    policy: ScriptedPolicy,
    requests: Sequence[tuple[str, int]] = REQUESTS,
    keys: Sequence[str] = KEYS,
) -> RolloutResult:
    """One rollout of ``requests`` on a fresh client of the job (horizon: the episode)."""
    with StageClient.from_controller(job.controller_url, timeout_s=10, wait_ready_s=120, token=TOKEN) as client:
        return EnvLoop(client, policy, horizon=EPISODE).run(requests, keys)


@pytest.fixture(scope="module")
def reference(job) -> RolloutResult:
    result = roll_out(job, ScriptedPolicy())
    assert result.lost == {} and set(result.trajectories) == set(KEYS)
    assert all(t.length == EPISODE for t in result.trajectories.values())
    return result


def test_a_controller_restart_mid_rollout_leaves_the_data_plane_stepping(job, reference):
    before = routing(job)
    controller = job.processes["controller"]
    pid, restarts = controller.pid, controller.restarts
    result = roll_out(job, ScriptedPolicy(lambda: kill_group(pid)))
    assert result.lost == {}
    for key in KEYS:
        assert_identical(result.trajectories[key], reference.trajectories[key])
    # The new controller rebuilds its registry from heartbeats and keeps the plan as it was.
    wait_until(lambda: controller.restarts > restarts and controller.pid not in (None, pid), "a new controller")
    after = wait_until(lambda: ready_routing(job), "the new controller's routing", timeout_s=120)
    assert (after.generation, layout(after)) == (before.generation, layout(before))


def test_a_crashed_env_worker_loses_only_its_pods_trajectories_and_the_pod_rebuilds(job, reference):
    before = routing(job)
    pod_url = job.pod_url("sim-1")
    instance = httpx.get(f"{pod_url}/v1/info", timeout=5).json()["instance"]

    def kill_one_worker() -> None:
        # The env workers are the children of the pod's multiprocessing forkserver.
        pod = psutil.Process(job.processes["sim-1"].pid)
        servers = [p for p in pod.children() if "forkserver" in " ".join(p.cmdline())]
        workers = [w for server in servers for w in server.children()]
        assert workers, "sim-1 runs its envs in worker processes"
        workers[0].kill()

    result = roll_out(job, ScriptedPolicy(kill_one_worker))
    assert set(result.lost) == ON_STAGE[1]
    for lost in result.lost.values():
        assert lost.route.pod == "sim-1" and lost.steps < EPISODE
        assert "sim-1" in lost.reason and "503" in lost.reason and "crashed" in lost.reason
    for key in ON_STAGE[0]:
        assert_identical(result.trajectories[key], reference.trajectories[key])
    # The same process rebuilt its envs: a new instance, the same generation and slot.
    wait_until(lambda: httpx.get(f"{pod_url}/readyz", timeout=5).status_code == 200, "sim-1 ready again")
    assert httpx.get(f"{pod_url}/v1/info", timeout=5).json()["instance"] not in (None, instance)
    after = wait_until(lambda: ready_routing(job), "the job ready again")
    assert (after.generation, layout(after)) == (before.generation, layout(before))
    # The lost trajectories are resampled as they were: same task, same state id, same steps.
    again = roll_out(job, ScriptedPolicy(), resampled(result), list(result.lost))
    for key in result.lost:
        assert_identical(again.trajectories[key], reference.trajectories[key])


def test_a_pod_killed_mid_rollout_loses_only_its_trajectories_and_comes_back_into_its_slot(job, reference):
    before = routing(job)
    process = job.processes["sim-0"]
    pid, restarts = process.pid, process.restarts
    result = roll_out(job, ScriptedPolicy(lambda: kill_group(pid)))
    assert set(result.lost) == ON_STAGE[0]
    for lost in result.lost.values():
        assert lost.route.pod == "sim-0" and lost.steps < EPISODE and "sim-0" in lost.reason
    assert set(result.trajectories) == ON_STAGE[1]
    for key in ON_STAGE[1]:
        assert_identical(result.trajectories[key], reference.trajectories[key])
    # The runner starts sim-0 again under its name; it registers and takes its slot back.
    wait_until(lambda: process.restarts > restarts, "sim-0 restarted")
    after = wait_until(
        lambda: (table := ready_routing(job)) is not None and table.generation > before.generation and table,
        "the job ready at a new generation",
        timeout_s=180,
    )
    assert layout(after) == layout(before)
    again = roll_out(job, ScriptedPolicy(), resampled(result), list(result.lost))
    for key in result.lost:
        assert_identical(again.trajectories[key], reference.trajectories[key])


def test_a_client_made_while_the_controller_restarts_waits_for_it(job, reference):
    controller = job.processes["controller"]
    restarts = controller.restarts
    kill_group(controller.pid)  # the runner starts it again; the client asks meanwhile
    with StageClient.from_controller(job.controller_url, timeout_s=5, wait_ready_s=120, token=TOKEN) as client:
        assert client.routing.ready
        result = EnvLoop(client, ScriptedPolicy(), horizon=EPISODE).run(REQUESTS, KEYS)
    assert controller.restarts > restarts
    assert result.lost == {} and set(result.trajectories) == set(KEYS)


# -- standalone pods: a partition and a slow pod --------------------------------------------------


def zero_actions(keys: Sequence[str]) -> dict[str, np.ndarray]:
    return {key: np.zeros(1, np.float32) for key in keys}


def placed(client: StageClient, state_ids: Sequence[int] = (0, 1, 2, 3)) -> dict[int, list[str]]:
    """Place one trajectory per state id (request i on stage i % 2), reset them all; return each
    stage's traj_keys."""
    client.reset_trajectories([(PENDULUM, k) for k in state_ids])
    for stage in (0, 1):
        client.reset_stage(stage).result(timeout=60)
    return {stage: client.stage_traj_keys(stage) for stage in (0, 1)}


def standalone(name: str, stage_id: int, workdir: Path, **where: Any) -> Server:
    """A standalone pod serving stage ``stage_id`` with two Pendulum envs, the job's token."""
    path = assignment_file(workdir, name, [(PENDULUM, 2)], stage_id=stage_id, max_episode_steps=EPISODE)
    return pod_server(name, workdir, args=["--assignment", str(path)], token=TOKEN, **where)


@pytest.fixture
def link() -> Iterator[HostLink]:
    if os.geteuid() != 0:
        pytest.skip("needs root to make a network namespace")
    made = HostLink()
    try:
        try:
            made.create()
        except (subprocess.CalledProcessError, FileNotFoundError) as exc:
            pytest.skip(f"cannot make a network namespace here: {exc}")
        yield made
    finally:
        made.delete()


@pytest.mark.slow
def test_a_partitioned_pod_is_named_by_the_clients_error_within_its_timeout_and_other_stages_go_on(link, tmp_path):
    # sim-0 lives in its own network namespace, reached over a veth; sim-1 on loopback.
    far = standalone("sim-0", 0, tmp_path, host=link.address, port=8100, wrap=link.wrap())
    near = standalone("sim-1", 1, tmp_path)
    with running(far, ready=True), running(near, ready=True):
        with StageClient.from_pods([far.url, near.url], timeout_s=3, token=TOKEN) as client:
            keys = placed(client)
            link.cut()
            try:
                cut_off = client.step_stage(0, zero_actions(keys[0]))
                other = client.step_stage(1, zero_actions(keys[1]))
                assert other.result(timeout=30).n == 2  # stage 1 is not held up by stage 0's pod
                with pytest.raises(PodUnavailableError) as caught:
                    cut_off.result(timeout=30)  # a bound on the test, far above the client's timeout
            finally:
                link.heal()
            assert caught.value.pods == ["sim-0"] and sorted(caught.value.traj_keys) == sorted(keys[0])
            assert "sim-0" in str(caught.value)
            # Healed: the pod answers again, and its trajectories start over from a reset.
            wait_until(lambda: far.answers("/healthz"), "sim-0 reachable again", timeout_s=60)
            assert client.reset_stage(0).result(timeout=60).n == 2
            assert client.step_stage(0, zero_actions(keys[0])).result(timeout=60).n == 2


@pytest.fixture(scope="module")
def pair(tmp_path_factory) -> Iterator[tuple[Server, Server]]:
    """Two standalone pods on loopback: sim-0 serves stage 0, sim-1 stage 1, the same task."""
    workdir = tmp_path_factory.mktemp("pair")
    slow, other = standalone("sim-0", 0, workdir), standalone("sim-1", 1, workdir)
    with running(slow, ready=True), running(other, ready=True):
        yield slow, other


@pytest.mark.slow
def test_a_pod_stalled_past_the_timeout_fails_its_stage_alone_naming_it(pair):
    slow, other = pair
    with StageClient.from_pods([slow.url, other.url], timeout_s=5, token=TOKEN) as client:
        keys = placed(client)
        slow.signal_group(signal.SIGSTOP)  # alive, connected, answering nothing
        try:
            stalled = client.step_stage(0, zero_actions(keys[0]))
            assert client.step_stage(1, zero_actions(keys[1])).result(timeout=30).n == 2
            assert not stalled.done()  # stage 1 got its answer while stage 0 still waited
            with pytest.raises(PodUnavailableError) as caught:
                stalled.result(timeout=30)
        finally:
            slow.signal_group(signal.SIGCONT)
        assert caught.value.pods == ["sim-0"] and sorted(caught.value.traj_keys) == sorted(keys[0])
        assert "Timeout" in caught.value.reason
        assert client.reset_stage(0).result(timeout=60).n == 2  # the pod serves again


@pytest.mark.slow
def test_a_pod_stalled_within_the_timeout_answers_late_and_loses_nothing(pair):
    slow, other = pair
    with StageClient.from_pods([slow.url, other.url], timeout_s=30, token=TOKEN) as client:
        # Both stages hold the same two states, so both must answer the same step alike.
        keys = placed(client, state_ids=(5, 5, 6, 6))
        actions = [np.array([0.7], np.float32), np.array([-1.2], np.float32)]
        slow.signal_group(signal.SIGSTOP)
        resume = threading.Timer(1.0, slow.signal_group, args=(signal.SIGCONT,))
        resume.start()
        try:
            late = client.step_stage(0, dict(zip(keys[0], actions))).result(timeout=60)
        finally:
            resume.cancel()
            slow.signal_group(signal.SIGCONT)
        prompt = client.step_stage(1, dict(zip(keys[1], actions))).result(timeout=60)
    assert late.obs.tobytes() == prompt.obs.tobytes()
    assert late.reward.tobytes() == prompt.reward.tobytes()
