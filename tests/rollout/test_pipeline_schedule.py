"""EnvLoop's schedule, specified exactly: in-process scripted pods whose every answer the test
releases (tests/support/scripted_pod.py), a real StageClient over them, and a policy that notes its calls.

The loop's own thread writes ``("reset", s)`` / ``("step", s)`` when it sends stage s's call,
``("take", s)`` when it takes stage s's answer and ``("policy", s)`` when it runs the policy on
stage s; its order is the loop's program order. The test releases one answer at a time and waits
until the loop has taken it (and, for :meth:`Scene.step`, sent the stage's next call) before the
next, so the sequence is fixed by the script: where several answers must have landed at once, the
policy is held while the test lands them. No sleeps, no timed assertions; every wait is bounded.
"""

from __future__ import annotations

import concurrent.futures
from collections.abc import Iterator, Mapping, Sequence
from typing import Any

import pytest
import torch
from support.scripted_pod import TASK, TOKEN, WAIT_S, PodRouter, Timeline, scripted_job

from vecsim.client import PendingCall, StageBatch, StageClient
from vecsim.config import RoutingTable
from vecsim.rollout import EnvLoop, RolloutResult

# What the loop's own thread records: a call sent (reset or step), an answer taken, a policy call.
LOOP_EVENTS = ("reset", "step", "take", "policy")


class RecordingClient(StageClient):
    """A real StageClient that notes, on the caller's thread, each call sent and each answer taken.

    The loop sends one call per pod (``pod_call``); each is noted as ``("reset", s)`` (resets
    only) or ``("step", s)`` for the pod's stage s, and comes back as a :class:`_Watched` pending
    call (same answer, same errors); ``calls[stage]`` lists them, so the test can wait for an
    answer to land.
    """

    def __init__(self, routing: RoutingTable, timeline: Timeline, **kwargs: Any) -> None:
        super().__init__(routing, **kwargs)
        self.timeline = timeline
        self.calls: dict[int, list[_Watched]] = {}

    def pod_call(
        self,
        pod: str,
        *,
        reset: Sequence[str] | Mapping[str, int] = (),
        step: Mapping[str, Any] | None = None,
        record: Sequence[str] = (),
    ) -> PendingCall[tuple[StageBatch, StageBatch]]:
        stage = {routed.pod: s.stage_id for s in self.routing.stages for routed in s.pods}[pod]
        call = super().pod_call(pod, reset=reset, step=step, record=record)
        return self._watch(stage, "step" if step else "reset", call)

    def _watch(self, stage: int, op: str, call: PendingCall[Any]) -> _Watched:
        relay: concurrent.futures.Future[Any] = concurrent.futures.Future()

        async def forward() -> None:
            try:
                relay.set_result(await call)
            except Exception as exc:  # noqa: BLE001 - the caller meets it in result()
                relay.set_exception(exc)

        self.submit(forward())
        watched = _Watched(relay, stage, self.timeline)
        self.calls.setdefault(stage, []).append(watched)
        self.timeline.add(op, stage)
        return watched


class _Watched(PendingCall[Any]):
    """A pending call whose ``result()`` is noted as ``("take", stage)``."""

    def __init__(self, future: concurrent.futures.Future[Any], stage: int, timeline: Timeline) -> None:
        super().__init__(future)
        self.stage, self.timeline = stage, timeline

    def result(self, timeout: float | None = None) -> Any:
        try:
            return super().result(timeout)
        finally:
            self.timeline.add("take", self.stage)


class CountingPolicy:
    """Acts ``[t + 1, k]`` on an observation ``[stage, env, k, t]`` (chunks: ``[t + 1 + j, k]``
    for action j of K), so each trajectory's rewards are 1, 2, 3, ...; notes ``("policy", stage)``
    and what it was given; :meth:`hold` makes its next call on a stage wait for the test."""

    def __init__(self, timeline: Timeline, chunk: int | None = None) -> None:
        self.timeline = timeline
        self.chunk = chunk
        self.seen: list[tuple[int, list[tuple[int, int, int]]]] = []  # (stage, [(env, k, t)]) per call
        self._holds: dict[int, _Gate] = {}

    def hold(self, stage: int) -> _Gate:
        gate = _Gate()
        self._holds[stage] = gate
        return gate

    def __call__(self, obs: dict[str, torch.Tensor], instructions: list[str], task_ids: list[str]) -> torch.Tensor:
        state = obs["state"]
        stages = set(state[:, 0].long().tolist())
        assert len(stages) == 1, f"one policy call mixed stages {stages}"
        assert instructions == ["count"] * len(task_ids) and task_ids == [TASK] * len(task_ids)
        (stage,) = stages
        self.seen.append((stage, [tuple(row) for row in state[:, 1:].long().tolist()]))
        self.timeline.add("policy", stage)
        gate = self._holds.pop(stage, None)
        if gate is not None:
            gate.wait()
        t, k = state[:, 3], state[:, 2]
        if self.chunk is None:
            return torch.stack([t + 1, k], dim=1)
        steps = torch.arange(self.chunk, dtype=torch.float32)
        return torch.stack([t[:, None] + 1 + steps, k[:, None].expand(-1, self.chunk)], dim=2)


class _Gate:
    def __init__(self) -> None:
        self._opened = concurrent.futures.Future()

    def open(self) -> None:
        self._opened.set_result(None)

    def wait(self) -> None:
        try:
            self._opened.result(WAIT_S)
        except concurrent.futures.TimeoutError:
            raise AssertionError(f"the policy was held for {WAIT_S} s and never let go") from None


class Scene:
    """S scripted pods (one per stage), a recording client over them, a counting policy, and
    ``EnvLoop.run`` on a thread of its own once :meth:`start` is called."""

    def __init__(self, num_stages: int, envs_per_pod: int = 1, chunk: int | None = None) -> None:
        self.timeline = Timeline()
        self.pods, table = scripted_job(num_stages, envs_per_pod, self.timeline)
        # Calls are held as long as the script says; the timeout only ends a broken test.
        self.client = RecordingClient(
            table, self.timeline, transport=PodRouter(self.pods), token=TOKEN, timeout_s=2 * WAIT_S
        )
        self.policy = CountingPolicy(self.timeline, chunk)
        self._runner = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="envloop")
        self.run: concurrent.futures.Future[RolloutResult] | None = None

    def start(self, state_ids: Sequence[int], horizon: int) -> None:
        """Run one trajectory per state id (request i on stage i % S, traj_key ``traj-<i>``)."""
        loop = EnvLoop(self.client, self.policy, horizon=horizon, keep_obs=("state",))
        requests = [(TASK, k) for k in state_ids]
        self.run = self._runner.submit(loop.run, requests, [f"traj-{i}" for i in range(len(requests))])
        if all(pod.holding for pod in self.pods):
            # The loop sends every stage's reset before it waits for any (the first test says so).
            # The client notes a call once it is handed over, which can be after its pod has it.
            self.timeline.wait_for(
                lambda: all(pod.held() and self.sent(pod.stage_id) >= len(pod.calls) for pod in self.pods),
                "every stage's reset held at its pod and noted as sent",
            )

    def result(self) -> RolloutResult:
        assert self.run is not None
        return self.run.result(WAIT_S)

    # -- the script -----------------------------------------------------------------------------

    def loop_events(self) -> list[tuple[str, int]]:
        return self.timeline.of(*LOOP_EVENTS)  # type: ignore[return-value]

    def sent(self, stage: int) -> int:
        return self.timeline.count("reset", stage) + self.timeline.count("step", stage)

    def in_flight(self) -> None:
        """Wait until every call the loop has sent has reached its pod."""

        def arrived() -> bool:
            return all(len(pod.calls) == self.sent(pod.stage_id) for pod in self.pods)

        self.timeline.wait_for(arrived, "every call sent has reached its pod")

    def land(self, stage: int) -> None:
        """Let stage ``stage``'s held call answer and wait until its answer has landed at the
        client (not necessarily taken by the loop)."""
        self.in_flight()
        pod = self.pods[stage]
        assert pod.held(), f"stage {stage} has no call in flight to answer"
        # The call to wait for is picked before the release: once it lands, the loop may take it
        # and send the stage's next call at once.
        call = self.client.calls[stage][-1]
        self.timeline.add("release", stage)
        pod.release()
        assert PendingCall.wait_any([call], WAIT_S), f"stage {stage}'s answer did not land: {self.timeline.events}"

    def serve(self, stage: int) -> None:
        """Land stage ``stage``'s answer and wait until the loop has taken it."""
        taken = self.timeline.count("take", stage)
        self.land(stage)
        self.timeline.wait_for(lambda: self.timeline.count("take", stage) > taken, f"the loop takes stage {stage}")

    def step(self, stage: int) -> None:
        """Serve stage ``stage`` and wait until the loop has sent its next call."""
        sent = self.sent(stage)
        self.serve(stage)
        self.timeline.wait_for(lambda: self.sent(stage) > sent, f"the loop sends stage {stage}'s next call")

    def close(self) -> None:
        for pod in self.pods:
            pod.open()
        self._runner.shutdown(wait=True)  # the run ends: nothing is held any more
        self.client.close()


@pytest.fixture
def scenes() -> Iterator[Any]:
    made: list[Scene] = []

    def make(num_stages: int, envs_per_pod: int = 1, chunk: int | None = None) -> Scene:
        made.append(Scene(num_stages, envs_per_pod, chunk))
        return made[-1]

    yield make
    for scene in made:
        scene.close()


def rounds(*stages: int) -> list[tuple[str, int]]:
    """The loop's events for serving each of ``stages`` in turn: take, policy, next step."""
    return [event for s in stages for event in (("take", s), ("policy", s), ("step", s))]


def resets(num_stages: int) -> list[tuple[str, int]]:
    return [("reset", s) for s in range(num_stages)]


# -- the schedule --------------------------------------------------------------------------------


def test_every_stage_reset_is_in_flight_before_the_loop_waits_for_any(scenes):
    scene = scenes(3)
    scene.start(state_ids=[0, 0, 0], horizon=1)  # returns once every pod holds a call
    # Each reset is held at its pod: had the loop waited on one before sending the next, the
    # others could never arrive.
    assert [pod.held() for pod in scene.pods] == [[("reset", (0,))]] * 3
    assert scene.loop_events() == resets(3)
    assert scene.policy.seen == []


def test_the_loop_serves_whichever_stage_lands_when_none_had(scenes):
    scene = scenes(3)
    scene.start(state_ids=[0, 0, 0], horizon=2)
    for stage in (2, 1, 0):  # against the turn: 0 is next after nothing, but 2 lands alone
        scene.step(stage)
    for stage in (1, 2, 0):
        scene.step(stage)
    for stage in (0, 2, 1):
        scene.serve(stage)
    result = scene.result()
    assert scene.loop_events() == [
        *resets(3),
        *rounds(2, 1, 0),
        *rounds(1, 2, 0),
        ("take", 0),
        ("take", 2),
        ("take", 1),
    ]
    assert [t.length for t in result.trajectories.values()] == [2, 2, 2]


def test_of_the_stages_that_have_landed_the_next_in_turn_is_served(scenes):
    scene = scenes(3)
    scene.start(state_ids=[0, 0, 0], horizon=2)
    # Stage 1's reset lands alone and is served; while the policy works on it, 0 and then 2
    # land. Next in turn after 1 is 2 (neither the lowest stage nor the first to land), then 0.
    held_1 = scene.policy.hold(1)
    scene.serve(1)
    scene.timeline.wait_for(lambda: scene.timeline.count("policy", 1) == 1, "the policy on stage 1")
    scene.land(0)
    scene.land(2)
    held_0 = scene.policy.hold(0)
    held_1.open()
    # While the policy works on stage 0, stage 2's step lands and then stage 1's: after 0 the
    # turn goes on to 1 (not to 2, the first to land), then 2.
    scene.timeline.wait_for(lambda: scene.timeline.count("policy", 0) == 1, "the policy on stage 0")
    scene.land(2)
    scene.land(1)
    held_0.open()
    scene.timeline.wait_for(lambda: scene.timeline.count("policy", 2) == 2, "the second policy on stage 2")
    scene.step(0)
    for stage in (2, 0, 1):
        scene.serve(stage)
    scene.result()
    assert scene.loop_events() == [
        *resets(3),
        *rounds(1, 2, 0),
        *rounds(1, 2),
        *rounds(0),
        ("take", 2),
        ("take", 0),
        ("take", 1),
    ]


def test_while_the_policy_works_on_one_stage_the_others_calls_are_at_their_pods(scenes):
    scene = scenes(3)
    scene.start(state_ids=[0, 0, 0], horizon=2)
    scene.step(0)
    scene.step(1)
    held = scene.policy.hold(2)
    scene.serve(2)
    scene.timeline.wait_for(lambda: scene.timeline.count("policy", 2) == 1, "the policy on stage 2")
    # The loop sent stages 0's and 1's steps without waiting for them; they reached the pods and
    # are simulating while the policy works on stage 2.
    scene.in_flight()
    assert [pod.held() for pod in scene.pods] == [[("step", (0,))], [("step", (0,))], []]
    assert scene.loop_events()[-1] == ("policy", 2)
    held.open()
    for stage in (0, 1, 2):
        scene.step(stage)
    for stage in (0, 1, 2):
        scene.serve(stage)
    assert len(scene.result().trajectories) == 3


def test_a_slow_stage_holds_up_only_itself(scenes):
    scene = scenes(3)
    scene.start(state_ids=[0, 0, 0], horizon=3)
    # Stage 2's reset is never answered while stages 0 and 1 run their whole episodes.
    for _ in range(3):
        scene.step(0)
        scene.step(1)
    scene.serve(0)
    scene.serve(1)
    assert [pod.held() for pod in scene.pods] == [[], [], [("reset", (0,))]]
    assert not scene.run.done()
    for _ in range(3):
        scene.step(2)
    scene.serve(2)
    result = scene.result()
    assert scene.loop_events() == [
        *resets(3),
        *rounds(0, 1) * 3,
        ("take", 0),
        ("take", 1),
        *rounds(2) * 3,
        ("take", 2),
    ]
    assert [pod.calls for pod in scene.pods] == [[("reset", (0,))] + [("step", (0,))] * 3] * 3
    assert {key: t.length for key, t in result.trajectories.items()} == {"traj-0": 3, "traj-1": 3, "traj-2": 3}


# -- what the trajectories hold ------------------------------------------------------------------


def expected_trajectory(stage: int, env: int, state_id: int, horizon: int) -> dict[str, Any]:
    """What a counter env reset to ``state_id`` yields under CountingPolicy within ``horizon``."""
    length = min(state_id, horizon) if state_id > 0 else horizon
    terminated = 0 < state_id <= horizon
    return {
        "state": [[stage, env, state_id, t] for t in range(length + 1)],
        "actions": [[t + 1, state_id] for t in range(length)],
        "rewards": [t + 1 for t in range(length)],
        "dones": [False] * (length - 1) + [True],
        "terminated": terminated,
        "truncated": not terminated,
        "success": terminated,
    }


def observed(trajectory: Any) -> dict[str, Any]:
    return {
        "state": trajectory.observations["state"].tolist(),
        "actions": trajectory.actions.tolist(),
        "rewards": trajectory.rewards.tolist(),
        "dones": trajectory.dones.tolist(),
        "terminated": trajectory.terminated,
        "truncated": trajectory.truncated,
        "success": trajectory.success,
    }


def test_each_trajectory_holds_exactly_what_its_env_did_and_ended_ones_are_not_stepped(scenes):
    scene = scenes(2, envs_per_pod=2)
    for pod in scene.pods:
        pod.open()  # the order is not the point here
    # Request i runs on stage i % 2, on the stage's lowest free env: state ids 1 and 0 on stage 0
    # (envs 0, 1), 2 and 3 on stage 1. State k > 0 terminates at action k; horizon 3.
    scene.start(state_ids=[1, 2, 0, 3], horizon=3)
    result = scene.result()
    placed = {"traj-0": (0, 0, 1), "traj-1": (1, 0, 2), "traj-2": (0, 1, 0), "traj-3": (1, 1, 3)}
    assert list(result.trajectories) == list(placed) and result.lost == {}
    for key, (stage, env, state_id) in placed.items():
        trajectory = result.trajectories[key]
        assert (trajectory.route.pod, trajectory.route.env_index, trajectory.route.state_id) == (
            f"pod-{stage}",
            env,
            state_id,
        )
        assert observed(trajectory) == expected_trajectory(stage, env, state_id, horizon=3), key
        assert trajectory.num_steps.tolist() == [1] * trajectory.length
    # A terminated env is not stepped again; none is stepped past the horizon.
    assert scene.pods[0].calls == [("reset", (0, 1)), ("step", (0, 1)), ("step", (1,)), ("step", (1,))]
    assert scene.pods[1].calls == [("reset", (0, 1)), ("step", (0, 1)), ("step", (0, 1)), ("step", (1,))]
    # The policy saw only live rows, (env, state id, t) each.
    assert sorted(scene.policy.seen) == sorted(
        [
            (0, [(0, 1, 0), (1, 0, 0)]),
            (0, [(1, 0, 1)]),
            (0, [(1, 0, 2)]),
            (1, [(0, 2, 0), (1, 3, 0)]),
            (1, [(0, 2, 1), (1, 3, 1)]),
            (1, [(1, 3, 2)]),
        ]
    )
    stats = result.stats
    assert (stats.num_trajectories, stats.env_steps) == (4, 1 + 2 + 3 + 3)
    assert stats.success_per_task == {TASK: 0.75}


def test_chunks_are_cut_to_the_horizon_and_stop_at_termination(scenes):
    scene = scenes(1, envs_per_pod=2, chunk=2)
    scene.pods[0].open()
    scene.start(state_ids=[3, 0], horizon=5)
    result = scene.result()
    # Chunks of 2: state 3 applies 2, then 1 of 2 (terminated); state 0 applies 2, 2, then the
    # last chunk is cut to the 1 action left.
    assert [a.shape for a in scene.pods[0].actions] == [(2, 2, 2), (2, 2, 2), (1, 1, 2)]
    assert scene.pods[0].calls == [("reset", (0, 1)), ("step", (0, 1)), ("step", (0, 1)), ("step", (1,))]
    terminated, truncated = result.trajectories["traj-0"], result.trajectories["traj-1"]
    assert terminated.num_steps.tolist() == [2, 1] and truncated.num_steps.tolist() == [2, 2, 1]
    assert terminated.rewards.tolist() == [1, 2, 3] and truncated.rewards.tolist() == [1, 2, 3, 4, 5]
    assert terminated.actions.tolist() == [[t + 1, 3] for t in range(3)]
    assert truncated.observations["state"][:, 3].tolist() == [0, 2, 4, 5]
    assert (terminated.terminated, terminated.truncated) == (True, False)
    assert (truncated.terminated, truncated.truncated) == (False, True)


# -- the stats -----------------------------------------------------------------------------------


def intervals(result: RolloutResult, what: str) -> list[tuple[int, float, float]]:
    return [(stage, begin, end) for kind, stage, begin, end in result.stats.timeline if kind == what]


def covered(policy: tuple[int, float, float], sims: list[tuple[int, float, float]]) -> bool:
    return any(begin <= policy[1] and policy[2] <= end for _, begin, end in sims)


def touches(policy: tuple[int, float, float], sims: list[tuple[int, float, float]]) -> bool:
    return any(begin < policy[2] and policy[1] < end for _, begin, end in sims)


def test_with_one_stage_the_policy_never_overlaps_simulation(scenes):
    scene = scenes(1, envs_per_pod=2)
    scene.pods[0].open()
    scene.start(state_ids=[0, 0], horizon=3)
    result = scene.result()
    stats = result.stats
    policies, sims = intervals(result, "policy"), intervals(result, "sim")
    assert len(policies) == 3 and len(sims) == 4
    assert not any(touches(policy, sims) for policy in policies)
    assert stats.policy_s > 0 and stats.overlap_s == 0.0 and stats.overlap_fraction == 0.0


def test_when_every_policy_call_has_another_stage_in_flight_the_overlap_is_whole(scenes):
    scene = scenes(2)
    scene.start(state_ids=[0, 0], horizon=2)
    # Each stage is answered only after the policy has finished with the other one.
    for stage in (0, 1, 0, 1):
        scene.step(stage)
    scene.serve(0)
    scene.serve(1)
    result = scene.result()
    assert scene.loop_events() == [*resets(2), *rounds(0, 1, 0, 1), ("take", 0), ("take", 1)]
    policies, sims = intervals(result, "policy"), intervals(result, "sim")
    assert [stage for stage, _, _ in policies] == [0, 1, 0, 1]
    assert all(covered(policy, [s for s in sims if s[0] != policy[0]]) for policy in policies)
    stats = result.stats
    assert stats.overlap_s == stats.policy_s > 0 and stats.overlap_fraction == 1.0


def test_policy_calls_with_nothing_in_flight_are_not_counted_as_overlap(scenes):
    scene = scenes(2)
    # Stage 0's trajectory terminates at its first action, stage 1's runs to the horizon of 3.
    scene.start(state_ids=[1, 0], horizon=3)
    scene.step(0)  # covered by stage 1's reset
    scene.step(1)  # covered by stage 0's step
    scene.serve(0)  # stage 0 is done: from here the policy on stage 1 runs alone
    scene.step(1)
    scene.step(1)
    scene.serve(1)
    result = scene.result()
    assert scene.loop_events() == [*resets(2), *rounds(0, 1), ("take", 0), *rounds(1, 1), ("take", 1)]
    policies, sims = intervals(result, "policy"), intervals(result, "sim")
    assert [(p[0], covered(p, sims), touches(p, sims)) for p in policies] == [
        (0, True, True),
        (1, True, True),
        (1, False, False),
        (1, False, False),
    ]
    stats = result.stats
    alone = sum(end - begin for _, begin, end in policies[2:])
    together = sum(end - begin for _, begin, end in policies[:2])
    assert stats.overlap_s == pytest.approx(together, rel=1e-6)
    assert stats.policy_s == pytest.approx(together + alone, rel=1e-6)
    assert stats.overlap_fraction == pytest.approx(together / (together + alone), rel=1e-6)
    assert 0.0 < stats.overlap_fraction < 1.0
