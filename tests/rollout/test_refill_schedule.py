"""EnvLoop without lockstep, and with refill, specified against scripted pods (tests/support/scripted_pod.py)
whose answers the test releases: the pods of one stage answer independently, and a batch holds more
requests than the job has envs.

Counter envs (see scripted_pod.py): an env reset to state id k > 0 terminates at its k-th action,
k = 0 runs to the horizon; it observes ``[stage, env, k, t]``. The policy acts ``[t + 1, k]``. No
sleeps: each wait is on what the pods or the policy have recorded, and bounded.
"""

from __future__ import annotations

import concurrent.futures
from collections.abc import Iterator
from typing import Any

import pytest
import torch
from support.scripted_pod import TASK, TOKEN, WAIT_S, PodRouter, ScriptedPod, Timeline

from vecsim.client import StageClient
from vecsim.client.stagestate import StageState
from vecsim.client.routing import routing_from_pod_infos
from vecsim.rollout import EnvLoop, RolloutResult


class NotingPolicy:
    """Acts ``[t + 1, k]``; notes each call's rows ``(stage, env, k, t)`` as ``("policy", rows)``."""

    def __init__(self, timeline: Timeline) -> None:
        self.timeline = timeline
        self.calls: list[list[tuple[int, int, int, int]]] = []

    def __call__(self, obs: dict[str, torch.Tensor], instructions: list[str], task_ids: list[str]) -> torch.Tensor:
        state = obs["state"]
        rows = [tuple(row) for row in state.long().tolist()]
        self.calls.append(rows)  # type: ignore[arg-type]
        self.timeline.add("policy", tuple(rows))
        return torch.stack([state[:, 3] + 1, state[:, 2]], dim=1)


class Job:
    """Scripted pods (``pods_per_stage[s]`` pods of ``envs_per_pod`` envs on stage s), a client
    over them, and ``EnvLoop.run`` on a thread of its own."""

    def __init__(self, pods_per_stage: list[int], envs_per_pod: int) -> None:
        self.timeline = Timeline()
        self.pods = [
            ScriptedPod(f"pod-{stage}{'abcdefgh'[j]}", stage, envs_per_pod, self.timeline)
            for stage, count in enumerate(pods_per_stage)
            for j in range(count)
        ]
        self.router = PodRouter(self.pods)
        table = routing_from_pod_infos([(pod.url, pod.info()) for pod in self.pods], job_id="scripted")
        self.client = StageClient(table, transport=self.router, token=TOKEN, timeout_s=2 * WAIT_S)
        self.policy = NotingPolicy(self.timeline)
        self._runner = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="envloop")
        self.run: concurrent.futures.Future[RolloutResult] | None = None

    def pod(self, name: str) -> ScriptedPod:
        return next(pod for pod in self.pods if pod.name == name)

    def start(self, state_ids: list[int], horizon: int, **settings: Any) -> None:
        """Run request ``(TASK, state_ids[i])`` as traj_key ``r<i>`` (stage i % S)."""
        loop = EnvLoop(self.client, self.policy, horizon=horizon, keep_obs=("state",), **settings)
        keys = [f"r{i}" for i in range(len(state_ids))]
        self.run = self._runner.submit(loop.run, [(TASK, k) for k in state_ids], keys)

    def result(self) -> RolloutResult:
        assert self.run is not None
        return self.run.result(WAIT_S)

    def wait_calls(self, name: str, n: int) -> None:
        """Wait until pod ``name`` has had ``n`` calls arrive."""
        pod = self.pod(name)
        self.timeline.wait_for(lambda: len(pod.calls) >= n, f"{n} calls at {name}")

    def kill(self, name: str) -> None:
        """Make pod ``name`` refuse connections from now on (the job's spaces read before)."""
        assert self.client.observation_space is not None
        del self.router._apps[name]

    def close(self) -> None:
        for pod in self.pods:
            pod.open()
        self._runner.shutdown(wait=True)
        self.client.close()


@pytest.fixture
def jobs() -> Iterator[Any]:
    made: list[Job] = []

    def make(pods_per_stage: list[int], envs_per_pod: int = 1) -> Job:
        made.append(Job(pods_per_stage, envs_per_pod))
        return made[-1]

    yield make
    for job in made:
        job.close()


# -- no lockstep ---------------------------------------------------------------------------------


def test_a_fast_pod_of_a_stage_steps_on_while_a_slow_pod_of_the_same_stage_has_not_answered(jobs):
    job = jobs([2])  # one stage, pods pod-0a and pod-0b, one env each
    fast, slow = job.pod("pod-0a"), job.pod("pod-0b")
    fast.open()
    job.start(state_ids=[0, 0], horizon=3)
    # The fast pod runs its whole episode while the slow pod's reset is still held.
    job.wait_calls("pod-0a", 4)
    job.timeline.wait_for(lambda: len(job.policy.calls) == 3, "three policy calls on the fast pod's env")
    assert fast.calls == [("reset", (0,)), ("step", (0,)), ("step", (0,)), ("step", (0,))]
    assert slow.calls == [("reset", (0,))] and slow.held() == [("reset", (0,))]
    assert not job.run.done()
    slow.open()
    result = job.result()
    assert {key: t.length for key, t in result.trajectories.items()} == {"r0": 3, "r1": 3}
    assert [t.route.pod for t in result.trajectories.values()] == ["pod-0a", "pod-0b"]
    assert slow.calls == fast.calls
    # Each policy call had one pod's env only: the fast pod's never waited for the slow pod's.
    assert all(len(rows) == 1 for rows in job.policy.calls)


def test_the_pods_of_a_stage_landed_within_the_batch_wait_share_one_policy_call(jobs):
    job = jobs([2])
    first, second = job.pod("pod-0a"), job.pod("pod-0b")
    job.start(state_ids=[0, 0], horizon=1, batch_wait_s=WAIT_S, max_batch=2)
    job.wait_calls("pod-0a", 1)
    job.wait_calls("pod-0b", 1)
    first.release()  # the loop waits for the stage's other pod, up to batch_wait_s
    job.timeline.wait_for(lambda: not first.held(), "pod-0a's reset answered")
    assert job.policy.calls == []
    second.release()
    job.timeline.wait_for(lambda: len(job.policy.calls) == 1, "one policy call")
    assert sorted(job.policy.calls[0]) == [(0, 0, 0, 0), (0, 0, 0, 0)]
    first.open()
    second.open()
    assert len(job.result().trajectories) == 2


def test_a_policy_call_gets_at_most_max_batch_observations(jobs):
    job = jobs([1], envs_per_pod=3)
    job.pods[0].open()
    job.start(state_ids=[0, 0, 0], horizon=1, max_batch=2)
    result = job.result()
    assert [len(rows) for rows in job.policy.calls] == [2, 1]
    assert [t.length for t in result.trajectories.values()] == [1, 1, 1]


# -- refill --------------------------------------------------------------------------------------


def test_an_env_whose_trajectory_ended_starts_the_next_waiting_request_at_once(jobs):
    job = jobs([1], envs_per_pod=2)
    pod = job.pods[0]
    pod.open()  # one pod: its calls follow one another whatever the timing
    # Six requests on two envs; state id k ends at action k (0: at the horizon of 4).
    job.start(state_ids=[1, 3, 1, 2, 1, 0], horizon=4)
    result = job.result()
    assert pod.calls == [
        ("reset", (0, 1)),
        ("step", (0, 1)),  # r0 ends at its 1st action, r1 goes on
        ("reset+step", ((0,), (1,))),  # r2 starts on env 0 in the request that steps r1
        ("step", (0, 1)),  # r2 and r1 both end
        ("reset", (0, 1)),
        ("step", (0, 1)),  # r3 and r4 start at once; r4 ends
        ("reset+step", ((1,), (0,))),  # r5 starts on env 1 in the request that steps r3, which ends
        ("step", (1,)),
        ("step", (1,)),
        ("step", (1,)),
        ("step", (1,)),  # r5 runs to the horizon
    ]
    assert list(result.trajectories) == [f"r{i}" for i in range(6)] and result.lost == {}
    placed = {key: (t.route.env_index, t.route.state_id, t.length) for key, t in result.trajectories.items()}
    assert placed == {
        "r0": (0, 1, 1),
        "r1": (1, 3, 3),
        "r2": (0, 1, 1),
        "r3": (0, 2, 2),
        "r4": (1, 1, 1),
        "r5": (1, 0, 4),
    }
    # Each trajectory holds only its own env's run, from its own reset.
    for trajectory in result.trajectories.values():
        states = trajectory.observations["state"][:, 2:].long().tolist()
        assert states == [[trajectory.route.state_id, t] for t in range(trajectory.length + 1)]
        assert trajectory.rewards.tolist() == [t + 1 for t in range(trajectory.length)]


def test_waiting_requests_go_to_whichever_pod_frees_an_env_first_so_a_faster_pod_runs_more(jobs):
    job = jobs([2])  # one stage: pod-0a and pod-0b, one env each
    fast, slow = job.pod("pod-0a"), job.pod("pod-0b")
    fast.open()
    job.start(state_ids=[0] * 6, horizon=1)
    # While the slow pod still holds its first reset, the fast pod's env runs every waiting request.
    job.wait_calls("pod-0a", 10)
    assert fast.calls == [("reset", (0,)), ("step", (0,))] * 5
    assert slow.calls == [("reset", (0,))] and slow.held() == [("reset", (0,))]
    slow.open()
    result = job.result()
    assert {key: t.route.pod for key, t in result.trajectories.items()} == {
        "r0": "pod-0a",
        "r1": "pod-0b",
        "r2": "pod-0a",
        "r3": "pod-0a",
        "r4": "pod-0a",
        "r5": "pod-0a",
    }
    assert slow.calls == [("reset", (0,)), ("step", (0,))] and result.lost == {}


def test_waiting_requests_keep_their_stage_and_the_result_keeps_request_order(jobs):
    job = jobs([1, 1])
    for pod in job.pods:
        pod.open()
    job.start(state_ids=[2, 1, 1, 1, 1, 2], horizon=3)
    result = job.result()
    assert list(result.trajectories) == [f"r{i}" for i in range(6)]
    assert [t.route.stage_id for t in result.trajectories.values()] == [0, 1, 0, 1, 0, 1]
    assert [t.route.state_id for t in result.trajectories.values()] == [2, 1, 1, 1, 1, 2]
    # Stage 1's three requests ran one after another on its one env.
    assert job.pod("pod-1a").calls == [
        ("reset", (0,)),
        ("step", (0,)),
        ("reset", (0,)),
        ("step", (0,)),
        ("reset", (0,)),
        ("step", (0,)),
        ("step", (0,)),
    ]


def test_a_dead_pod_loses_its_own_trajectories_and_waiting_requests_run_on_the_pods_left(jobs):
    job = jobs([2])  # one stage: pod-0a, pod-0b, one env each
    job.pod("pod-0a").open()
    job.kill("pod-0b")
    job.start(state_ids=[1, 1, 1, 1], horizon=2)
    result = job.result()
    assert set(result.lost) == {"r1"} and result.lost["r1"].route.pod == "pod-0b"
    assert list(result.trajectories) == ["r0", "r2", "r3"]
    assert {t.route.pod for t in result.trajectories.values()} == {"pod-0a"}
    assert all(t.length == 1 and t.terminated for t in result.trajectories.values())


def test_a_waiting_request_that_only_a_dead_pod_could_run_is_reported_lost(jobs):
    job = jobs([1])
    job.kill("pod-0a")
    job.start(state_ids=[1, 1], horizon=2)
    result = job.result()
    assert result.trajectories == {}
    assert set(result.lost) == {"r0", "r1"}
    waited = result.lost["r1"]
    assert (waited.route.task_id, waited.route.state_id, waited.steps) == (TASK, 1, 0)
    assert "no env of task" in waited.reason


def test_per_request_horizons_end_each_trajectory_at_its_own_cap(jobs):
    job = jobs([1], envs_per_pod=2)
    job.pods[0].open()
    loop = EnvLoop(job.client, job.policy, horizon=4, keep_obs=())
    result = loop.run([(TASK, 0)] * 3, ["short", "long", "after"], horizons=[1, 4, 2])
    lengths = {key: (t.length, t.truncated, t.route.env_index) for key, t in result.trajectories.items()}
    # "after" waits for an env and takes the one "short" left after its one action.
    assert lengths == {"short": (1, True, 0), "long": (4, True, 1), "after": (2, True, 0)}


def test_a_horizon_past_the_loops_is_refused_naming_its_request(jobs):
    job = jobs([1])
    with pytest.raises(ValueError, match=r"horizons\[1\] is 5: each must be 1..4"):
        EnvLoop(job.client, job.policy, horizon=4).run([(TASK, 0), (TASK, 0)], horizons=[4, 5])


class InterruptedPolicy(NotingPolicy):
    """Raises KeyboardInterrupt (a Ctrl-C) at its first call."""

    def __call__(self, obs: dict[str, torch.Tensor], instructions: list[str], task_ids: list[str]) -> torch.Tensor:
        if not self.calls:
            self.calls.append([])
            raise KeyboardInterrupt
        return super().__call__(obs, instructions, task_ids)


def test_ctrl_c_while_another_pod_is_in_flight_leaves_the_client_usable(jobs):
    job = jobs([2])
    fast, slow = job.pod("pod-0a"), job.pod("pod-0b")
    fast.open()  # the slow pod's reset stays in flight when the policy is interrupted
    loop = EnvLoop(job.client, InterruptedPolicy(job.timeline), horizon=2, keep_obs=())
    with pytest.raises(KeyboardInterrupt):
        loop.run([(TASK, 0), (TASK, 0)])
    assert job.client.stage_state(0) is StageState.IDLE
    slow.open()
    result = EnvLoop(job.client, job.policy, horizon=2, keep_obs=()).run([(TASK, 0), (TASK, 0)])
    assert [t.length for t in result.trajectories.values()] == [2, 2] and result.lost == {}
