"""StageClient: placement (pure) and the per-stage data plane over real pods on loopback."""

from __future__ import annotations

import asyncio
import os
import signal
from collections import Counter

import httpx
import numpy as np
import pytest
import yaml
from gymnasium.error import AlreadyPendingCallError, ClosedEnvironmentError
from hypothesis import given, settings
from hypothesis import strategies as st
from support.scripted_pod import TASK, TOKEN, PodRouter, ScriptedPod, Timeline, scripted_job
from support.service_procs import PodSpec, job_config, local_job, standalone_pods, wait_for_generation
from starlette.applications import Starlette
from starlette.responses import JSONResponse
from starlette.routing import Route

from vecsim.client import (
    CapacityError,
    HTTPVectorEnv,
    PodUnavailableError,
    RoutingChangedError,
    StageClient,
    StaleGenerationError,
    TrajRoute,
    place_requests,
    routed_envs,
)
from vecsim.client.stagestate import StageState
from vecsim.client.routing import changed_routes, routing_from_pod_infos, validate_routes
from vecsim.config import RoutedPod, RoutedStage, RoutingTable, TaskBlock
from vecsim.rollout.sampler import TaskBalancedSampler, stage_of


def _pod(name: str, port: int, blocks: list[tuple[str, int]]) -> RoutedPod:
    tasks, start = [], 0
    for task_id, n in blocks:
        tasks.append(TaskBlock(task_id=task_id, env_start=start, num_envs=n))
        start += n
    return RoutedPod(pod=name, url=f"http://127.0.0.1:{port}", num_envs=start, tasks=tuple(tasks))


def _table(stages: list[list[RoutedPod]], generation: int = 1) -> RoutingTable:
    return RoutingTable(
        generation=generation,
        job_id="t",
        ready=True,
        stages=tuple(RoutedStage(stage_id=s, pods=tuple(pods)) for s, pods in enumerate(stages)),
    )


TWO_STAGES = _table(
    [
        [_pod("sim-0", 9000, [("a", 2), ("b", 2)]), _pod("sim-1", 9001, [("a", 1), ("c", 2)])],
        [_pod("sim-2", 9002, [("a", 3), ("b", 2), ("c", 2)])],
    ]
)


# -- placement (pure) ----------------------------------------------------------------------------


def test_request_i_is_placed_on_stage_i_mod_s_on_an_env_of_its_task():
    requests = [("a", 0), ("a", 1), ("b", 2), ("c", 3), ("c", 4), ("b", 5)]
    keys = [f"k{i}" for i in range(len(requests))]
    routes = place_requests(TWO_STAGES, requests, keys)
    assert list(routes) == keys
    for i, (task_id, state_id) in enumerate(requests):
        route = routes[keys[i]]
        assert (route.stage_id, route.task_id, route.state_id) == (stage_of(i, 2), task_id, state_id)
    validate_routes(TWO_STAGES, routes)


def test_a_stage_spreads_one_task_over_its_pods():
    routes = place_requests(TWO_STAGES, [("a", 0), ("a", 1), ("a", 2)], ["x", "y", "z"])
    stage0 = [r for r in routes.values() if r.stage_id == 0]
    assert sorted(r.pod for r in stage0) == ["sim-0", "sim-1"]


def test_over_capacity_names_the_task_and_the_stage():
    requests = [("c", 0), ("a", 0), ("c", 1), ("a", 1), ("c", 2), ("a", 2)]
    with pytest.raises(CapacityError, match=r"stage 0 has 2 env\(s\) of task 'c' \(on pods sim-1\).*3 request"):
        place_requests(TWO_STAGES, requests, [str(i) for i in range(6)])


def test_a_task_the_stage_lacks_is_a_capacity_error():
    with pytest.raises(CapacityError, match=r"stage 0 has 0 env\(s\) of task 'zzz' \(on no pod\)"):
        place_requests(TWO_STAGES, [("zzz", 0)], ["k"])


def test_empty_batch_places_nothing():
    assert place_requests(TWO_STAGES, [], []) == {}
    assert place_requests(_table([]), [], []) == {}


@pytest.mark.parametrize(
    "request_, field", [(("a", -1), "state_id"), (("", 0), "task_id"), (("a",), "pair"), (("a", True), "state_id")]
)
def test_malformed_request_is_an_error_naming_it(request_, field):
    with pytest.raises(ValueError, match=rf"request 0: .*{field}"):
        place_requests(TWO_STAGES, [request_], ["k"])


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 10_000), group_size=st.integers(1, 3), per_stage=st.integers(1, 6))
def test_sampler_batches_always_fit_a_job_of_group_size_envs_per_task(seed, group_size, per_stage):
    tasks = ["a", "b", "c"]
    if per_stage > group_size * len(tasks):
        return
    table = _table([[_pod(f"sim-{s}", 9000 + s, [(t, group_size) for t in tasks])] for s in range(2)])
    dataset = [(t, k) for t in tasks for k in range(7)]
    sampler = TaskBalancedSampler(dataset, batch_size=2 * per_stage, group_size=group_size, num_stages=2, seed=seed)
    for batch in sampler:
        requests = [dataset[i] for i in batch]
        routes = place_requests(table, requests, [str(i) for i in range(len(requests))])
        envs = Counter((r.pod, r.env_index) for r in routes.values())
        assert max(envs.values()) == 1


def test_routed_envs_are_stage_major_then_pod_then_env_index():
    envs = routed_envs(TWO_STAGES)
    assert [(e.stage_id, e.pod, e.env_index, e.task_id) for e in envs[:6]] == [
        (0, "sim-0", 0, "a"),
        (0, "sim-0", 1, "a"),
        (0, "sim-0", 2, "b"),
        (0, "sim-0", 3, "b"),
        (0, "sim-1", 0, "a"),
        (0, "sim-1", 1, "c"),
    ]
    assert len(envs) == TWO_STAGES.num_envs
    assert {e.stage_id for e in envs[7:]} == {1}


def test_routes_sharing_an_env_are_rejected_naming_both_keys():
    shared = {"x": TrajRoute("sim-0", 0, "a", 0, 0), "y": TrajRoute("sim-0", 0, "a", 0, 1)}
    with pytest.raises(ValueError, match="traj_keys x and y share env 0 of pod sim-0"):
        validate_routes(TWO_STAGES, shared)


def test_a_route_to_an_env_of_another_task_is_rejected():
    with pytest.raises(ValueError, match="env 2 of pod sim-0 runs 'b', not 'a'"):
        validate_routes(TWO_STAGES, {"x": TrajRoute("sim-0", 2, "a", 0, 0)})


def test_changed_routes_names_trajectories_on_pods_whose_blocks_changed():
    routes = {"keep": TrajRoute("sim-2", 0, "a", 1, 0), "moved": TrajRoute("sim-1", 0, "a", 0, 0)}
    # sim-1's env 0 still runs "a", but its blocks changed: it rebuilds, the trajectory is gone.
    new = _table(
        [
            [_pod("sim-0", 9000, [("a", 2), ("b", 2)]), _pod("sim-1", 9001, [("a", 1), ("c", 3)])],
            [_pod("sim-2", 9002, [("a", 3), ("b", 2), ("c", 2)])],
        ],
        generation=2,
    )
    assert changed_routes(TWO_STAGES, new, routes) == ["moved"]


def test_a_new_generation_with_the_same_pods_changes_no_route():
    routes = {"k": TrajRoute("sim-1", 0, "a", 0, 0)}
    assert changed_routes(TWO_STAGES, TWO_STAGES.model_copy(update={"generation": 5}), routes) == []


def test_a_pod_at_a_new_url_loses_its_trajectories():
    routes = {"k": TrajRoute("sim-2", 0, "a", 1, 0)}
    moved = _table([TWO_STAGES.stages[0].pods, [_pod("sim-2", 9999, [("a", 3), ("b", 2), ("c", 2)])]])
    assert changed_routes(TWO_STAGES, moved, routes) == ["k"]


def test_routing_from_pod_infos_groups_pods_by_stage():
    infos = [
        (
            "http://127.0.0.1:1",
            {
                "pod": "p1",
                "stage_id": 1,
                "generation": 0,
                "ready": True,
                "num_envs": 2,
                "tasks": [{"task_id": "a", "instruction": "", "env_start": 0, "num_envs": 2}],
            },
        ),
        (
            "http://127.0.0.1:2",
            {
                "pod": "p0",
                "stage_id": 0,
                "generation": 0,
                "ready": True,
                "num_envs": 1,
                "tasks": [{"task_id": "a", "instruction": "", "env_start": 0, "num_envs": 1}],
            },
        ),
    ]
    table = routing_from_pod_infos(infos)
    assert [[p.pod for p in s.pods] for s in table.stages] == [["p0"], ["p1"]]
    assert table.num_envs == 3


# -- the data plane over real pods -----------------------------------------------------------------
# Two stages: stage 0 has two pods, stage 1 one; tasks are two gymnasium MuJoCo ids with equal
# spaces, no cameras, so every call is cheap.

PENDULUM, PENDULUM_V4 = "gym/InvertedPendulum-v5", "gym/InvertedPendulum-v4"
STAGE_PODS = [
    PodSpec("sim-0", 0, [(PENDULUM, 2), (PENDULUM_V4, 1)]),
    PodSpec("sim-1", 0, [(PENDULUM, 1), (PENDULUM_V4, 2)]),
    PodSpec("sim-2", 1, [(PENDULUM, 2), (PENDULUM_V4, 2)]),
]


@pytest.fixture(scope="module")
def pods(tmp_path_factory):
    with standalone_pods(STAGE_PODS, tmp_path_factory.mktemp("pods")) as running:
        yield running


@pytest.fixture
def client(pods):
    with StageClient.from_pods([p.url for p in pods], timeout_s=30) as c:
        yield c


def _zero_actions(keys) -> dict[str, np.ndarray]:
    return {key: np.zeros(1, dtype=np.float32) for key in keys}


def test_from_pods_reads_stages_tasks_and_spaces(client):
    assert [[p.pod for p in s.pods] for s in client.routing.stages] == [["sim-0", "sim-1"], ["sim-2"]]
    assert client.action_space.shape == (1,)
    assert client.observation_space.shape == (4,)  # the env's own Box observation
    assert set(client.instructions) == {PENDULUM, PENDULUM_V4}


def test_reset_stage_answers_for_every_trajectory_of_the_stage_in_placement_order(client):
    requests = [(PENDULUM, 0), (PENDULUM, 1), (PENDULUM_V4, 2), (PENDULUM_V4, 3), (PENDULUM, 4), (PENDULUM, 5)]
    routes = client.reset_trajectories(requests)
    batch = client.reset_stage(0).result(timeout=60)
    stage0 = [key for key, route in routes.items() if route.stage_id == 0]
    assert batch.traj_keys == stage0
    assert batch.task_ids == [routes[k].task_id for k in stage0]
    assert list(batch.state_ids) == [routes[k].state_id for k in stage0]
    assert batch.obs.shape == (3, 4)
    assert {routes[k].pod for k in stage0} == {"sim-0", "sim-1"}


def test_the_same_task_and_state_id_give_bit_identical_observations_on_any_pod(client):
    # Request 0 lands on stage 0 (pods sim-0/sim-1), request 1 on stage 1 (pod sim-2).
    routes = client.reset_trajectories([(PENDULUM_V4, 17), (PENDULUM_V4, 17), (PENDULUM, 17), (PENDULUM, 17)])
    first = client.reset_stage(0).result(timeout=60)
    second = client.reset_stage(1).result(timeout=60)
    assert {routes[k].pod for k in first.traj_keys}.isdisjoint({routes[k].pod for k in second.traj_keys})
    assert np.array_equal(first.obs, second.obs)


def test_step_stage_returns_the_stepped_trajectories_rows_in_the_mappings_order(client):
    routes = client.reset_trajectories([(PENDULUM, 0), (PENDULUM, 1), (PENDULUM_V4, 2), (PENDULUM_V4, 3)])
    client.reset_stage(0).result(timeout=60)
    keys = [k for k, r in routes.items() if r.stage_id == 0][::-1]
    batch = client.step_stage(0, _zero_actions(keys)).result(timeout=60)
    assert batch.traj_keys == keys
    assert batch.obs.shape == (2, 4)
    assert batch.reward.shape == batch.terminated.shape == batch.truncated.shape == (2,)


def test_a_stage_call_can_be_awaited(client):
    client.reset_trajectories([(PENDULUM, 0), (PENDULUM, 1)])

    async def reset_both():
        return await asyncio.gather(client.reset_stage(0), client.reset_stage(1))

    first, second = asyncio.run(reset_both())
    assert (first.n, second.n) == (1, 1)


def test_a_stage_without_trajectories_is_a_no_op(client):
    client.reset_trajectories([(PENDULUM, 0)])
    assert client.stage_traj_keys(1) == []
    batch = client.reset_stage(1).result(timeout=1)
    assert batch.n == 0 and batch.obs.shape == (0, 4)
    assert client.step_stage(0, {}).result(timeout=1).n == 0


def test_an_empty_batch_is_a_no_op(client):
    assert client.reset_trajectories([]) == {}
    assert client.reset_stage(0).result(timeout=1).n == 0


def test_over_capacity_on_real_pods_names_task_and_stage(client):
    requests = [(PENDULUM_V4, k) for k in range(6)]  # 3 per stage: stage 0 holds 3, stage 1 only 2
    with pytest.raises(CapacityError, match=f"stage 1 has 2 env\\(s\\) of task '{PENDULUM_V4}'"):
        client.reset_trajectories(requests)


def test_a_second_call_on_a_waiting_stage_raises_already_pending_call_error():
    # A scripted pod holds the first call's answer until the test lets it go: the stage is
    # waiting, whatever the machine's timing.
    timeline = Timeline()
    (pod,), table = scripted_job(1, 2, timeline)
    with StageClient(table, transport=PodRouter([pod]), token=TOKEN, timeout_s=60) as client:
        client.reset_trajectories([(TASK, 0), (TASK, 1)])
        pending = client.reset_stage(0)
        timeline.wait_for(lambda: pod.held(), "the first reset held at the pod")
        with pytest.raises(AlreadyPendingCallError):
            client.reset_stage(0)
        pod.open()
        pending.result(timeout=60)
        client.reset_stage(0).result(timeout=60)


def test_a_stage_waits_on_its_call_until_the_answer_is_handed_over(client):
    keys = list(client.reset_trajectories([(PENDULUM, 0), (PENDULUM, 1)]))
    pending = client.reset_stage(0)
    assert client.stage_state(0) in (StageState.WAITING_RESET, StageState.IDLE)  # IDLE: answered already
    pending.result(timeout=60)
    # A returned result means an idle stage: the next call goes out at once.
    assert client.stage_state(0) is StageState.IDLE
    stage0 = [k for k in keys if client.routes[k].stage_id == 0]
    pending = client.call(reset=[k for k in keys if k not in stage0], step=_zero_actions(stage0))
    pending.result(timeout=60)
    assert [client.stage_state(s) for s in (0, 1)] == [StageState.IDLE, StageState.IDLE]


def test_keys_of_another_stage_or_unknown_keys_are_refused(client):
    routes = client.reset_trajectories([(PENDULUM, 0), (PENDULUM, 1)])
    stage1_key = [k for k, r in routes.items() if r.stage_id == 1][0]
    with pytest.raises(ValueError, match=f"traj_key '{stage1_key}' runs on stage 1, not stage 0"):
        client.step_stage(0, _zero_actions([stage1_key]))
    with pytest.raises(ValueError, match="traj_key 'nope' is not a live trajectory"):
        client.step_stage(0, _zero_actions(["nope"]))


@pytest.mark.parametrize(
    "action, message",
    [
        (np.array([np.nan], dtype=np.float32), "NaN or inf"),
        (np.zeros(2, dtype=np.float32), r"shape \[2\], expected \[1\]"),
    ],
)
def test_a_bad_action_is_refused_naming_the_traj_key_before_anything_is_sent(client, action, message):
    routes = client.reset_trajectories([(PENDULUM, 0)])
    key = next(iter(routes))
    before = client.reset_stage(0).result(timeout=60)
    with pytest.raises(ValueError, match=f"traj_key '{key}': .*{message}"):
        client.step_stage(0, {key: action})
    after = client.step_stage(0, _zero_actions([key])).result(timeout=60)
    assert after.n == 1 and before.n == 1


def test_a_stale_generation_without_a_controller_names_the_pod(pods):
    with StageClient.from_pods([p.url for p in pods]) as fresh:
        table = fresh.routing
    stale = table.model_copy(update={"generation": table.generation + 1})
    with StageClient(stale, timeout_s=30) as client:
        client.reset_trajectories([(PENDULUM, 0)])
        with pytest.raises(StaleGenerationError, match=r"pod sim-\d refused generation 1 \(409\)"):
            client.reset_stage(0).result(timeout=60)


def test_placing_a_new_batch_while_a_call_is_in_flight_is_refused(client):
    client.reset_trajectories([(PENDULUM, 0)])
    pending = client.reset_stage(0)
    with pytest.raises(AlreadyPendingCallError):
        client.reset_trajectories([(PENDULUM, 1)])
    pending.result(timeout=60)


def test_a_closed_client_refuses_calls(pods):
    client = StageClient.from_pods([pods[0].url])
    client.close()
    with pytest.raises(ClosedEnvironmentError):
        client.reset_trajectories([(PENDULUM, 0)])


# -- unavailable pods: each test gets its own pod, since it stops or kills it --------------------


@pytest.fixture
def lone_pod(start_pods):
    (pod,) = start_pods([PodSpec("sim-9", 0, [(PENDULUM, 2)])])
    return pod


@pytest.mark.slow
def test_a_partitioned_pod_raises_pod_unavailable_naming_it_and_its_trajectories(lone_pod):
    with StageClient.from_pods([lone_pod.url], timeout_s=1.5) as client:
        routes = client.reset_trajectories([(PENDULUM, 0), (PENDULUM, 1)])
        client.reset_stage(0).result(timeout=30)
        lone_pod.signal_group(signal.SIGSTOP)  # the pod accepts nothing and answers nothing
        try:
            with pytest.raises(PodUnavailableError) as caught:
                client.step_stage(0, _zero_actions(routes)).result(timeout=30)
        finally:
            lone_pod.signal_group(signal.SIGCONT)
    assert caught.value.pods == ["sim-9"]
    assert sorted(caught.value.traj_keys) == sorted(routes)
    assert "sim-9" in str(caught.value)


def test_a_dead_pod_raises_pod_unavailable_at_once(lone_pod):
    with StageClient.from_pods([lone_pod.url], timeout_s=30) as client:
        key = next(iter(client.reset_trajectories([(PENDULUM, 0)])))
        lone_pod.stop()
        with pytest.raises(PodUnavailableError, match=rf"pod sim-9 \(traj_keys: {key}\)"):
            client.reset_stage(0).result(timeout=30)


# -- under a controller (LocalJob): routing from GET /v1/routing, 409s, changed routing ----------

JOB = {"job_id": "client-tests", "tasks": [PENDULUM], "group_size": 2, "num_stages": 2, "camera": {"names": []}}


@pytest.fixture(scope="module")
def job(tmp_path_factory):
    with local_job(job_config(JOB, replicas=2), tmp_path_factory.mktemp("job")) as running:
        yield running


@pytest.fixture
def fresh_job(tmp_path):
    with local_job(job_config(JOB, replicas=2), tmp_path) as running:
        yield running


def _step_all(client: StageClient, stage: int):
    return client.step_stage(stage, _zero_actions(client.stage_traj_keys(stage))).result(timeout=60)


def test_a_client_from_the_controller_routes_over_the_jobs_pods(job):
    with StageClient.from_controller(job.controller_url, token=job.token) as client:
        assert [[p.pod for p in s.pods] for s in client.routing.stages] == [["sim-0"], ["sim-1"]]
        client.reset_trajectories([(PENDULUM, 0), (PENDULUM, 1), (PENDULUM, 2)])
        assert client.reset_stage(0).result(timeout=60).n == 2
        assert _step_all(client, 0).n == 2


def test_http_vector_env_comes_from_a_controller_url_or_a_job_config(job, tmp_path):
    path = tmp_path / "job.yaml"
    path.write_text(yaml.safe_dump(job.config.model_dump(mode="json")))
    for source in ({"controller_url": job.controller_url}, {"job_config": job.config}, {"job_config": path}):
        env = HTTPVectorEnv(**source, token=job.token)
        try:
            assert env.num_envs == 4
            assert env.reset(seed=0)[0].shape == (4, 4)
        finally:
            env.close()


@pytest.mark.slow
def test_a_changed_job_raises_routing_changed_naming_the_lost_trajectories(fresh_job):
    with StageClient.from_controller(fresh_job.controller_url, token=fresh_job.token) as client:
        routes = client.reset_trajectories([(PENDULUM, 0), (PENDULUM, 1)])
        client.reset_stage(0).result(timeout=60)
        generation = client.routing.generation
        bigger = {**JOB, "group_size": 3}
        assert (
            httpx.put(
                f"{fresh_job.controller_url}/v1/job",
                json=bigger,
                timeout=30,
                headers={"Authorization": f"Bearer {fresh_job.token}"},
            ).status_code
            == 200
        )
        new_generation = wait_for_generation(fresh_job.controller_url, generation)
        stage0 = client.stage_traj_keys(0)
        with pytest.raises(RoutingChangedError, match=f"generation {new_generation}") as caught:
            _step_all(client, 0)
        assert caught.value.traj_keys == stage0
        stage1 = [k for k, r in routes.items() if r.stage_id == 1]
        with pytest.raises(RoutingChangedError):  # stage 1's pod was rebuilt too
            client.reset_stage(1, stage1).result(timeout=60)
        # A new batch is placed on the new routing and runs.
        client.reset_trajectories([(PENDULUM, k) for k in range(6)])
        assert client.reset_stage(0).result(timeout=60).n == 3


@pytest.mark.slow
def test_after_a_pod_restart_the_other_stage_retries_at_the_new_generation(fresh_job):
    with StageClient.from_controller(fresh_job.controller_url, token=fresh_job.token) as client:
        client.reset_trajectories([(PENDULUM, 0), (PENDULUM, 1)])
        client.reset_stage(0).result(timeout=60)
        client.reset_stage(1).result(timeout=60)
        generation = client.routing.generation
        os.killpg(fresh_job.processes["sim-0"].pid, signal.SIGKILL)  # the runner starts it again
        new_generation = wait_for_generation(fresh_job.controller_url, generation)
        assert _step_all(client, 1).n == 1  # sim-1 kept its envs: 409, re-read, retried
        assert client.routing.generation == new_generation


@pytest.mark.slow
def test_after_a_pod_restart_its_trajectories_raise_routing_changed(fresh_job):
    with StageClient.from_controller(fresh_job.controller_url, token=fresh_job.token) as client:
        if httpx.get(f"{client.routing.stages[0].pods[0].url}/v1/info", timeout=10).json().get("instance") is None:
            pytest.skip("the pods do not report 'instance' in /v1/info (docs/api.md), so a restart is invisible")
        client.reset_trajectories([(PENDULUM, 0), (PENDULUM, 1)])
        client.reset_stage(0).result(timeout=60)
        stage0 = client.stage_traj_keys(0)
        generation = client.routing.generation
        os.killpg(fresh_job.processes["sim-0"].pid, signal.SIGKILL)
        wait_for_generation(fresh_job.controller_url, generation)
        with pytest.raises(RoutingChangedError) as caught:
            _step_all(client, 0)
        assert caught.value.traj_keys == stage0


class _ControllerBesidePods(httpx.AsyncBaseTransport):
    """The client's transport: scripted pods by host name, and host ``controller`` answering
    ``GET /v1/routing`` with ``table``; every URL it carries is noted in ``urls``."""

    def __init__(self, pods: list[ScriptedPod], table: RoutingTable) -> None:
        self.urls: list[str] = []
        self._pods = PodRouter(pods)
        app = Starlette(routes=[Route("/v1/routing", lambda _: JSONResponse(table.model_dump(mode="json")))])
        self._controller = httpx.ASGITransport(app=app)

    async def handle_async_request(self, request: httpx.Request) -> httpx.Response:
        self.urls.append(str(request.url))
        via = self._controller if request.url.host == "controller" else self._pods
        return await via.handle_async_request(request)

    async def aclose(self) -> None:
        await self._pods.aclose()
        await self._controller.aclose()


def test_a_new_batch_re_reads_the_routing_table_through_the_clients_own_transport():
    pods, table = scripted_job(1, 2, Timeline())
    moved = table.model_copy(update={"generation": table.generation + 1})
    transport = _ControllerBesidePods(pods, moved)
    with StageClient(table, controller_url="http://controller", transport=transport, token=TOKEN) as client:
        client.reset_trajectories([(TASK, 0)])
        assert client.routing.generation == moved.generation
        client.reset_trajectories([(TASK, 1)])
    assert transport.urls.count("http://controller/v1/routing") == 2
