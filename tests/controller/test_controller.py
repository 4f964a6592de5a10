"""The controller: pure reconcile, its HTTP API in process, and pushes to real peers on loopback."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Iterator
from contextlib import ExitStack, asynccontextmanager

import httpx
import pytest
from fastapi import FastAPI
from fastapi.responses import JSONResponse
from support.service_procs import AppThread, wait_until

from service.controller import ControllerSettings, create_app
from service.controller.reconcile import (
    Desired,
    Observed,
    ObservedPod,
    PushAssignment,
    reconcile,
    safe_generation,
)
from service.controller.reconciler import Reconciler
from vecsim.config import Assignment, JobSpec, TaskBlock
from vecsim.plan import plan

pytestmark = pytest.mark.anyio

TASKS = ("tiny/lift", "tiny/stack", "tiny/door")
JOB = {
    "job_id": "t",
    "tasks": list(TASKS),
    "group_size": 2,
    "num_stages": 2,
    "pods_per_stage": 1,
    "camera": {"names": []},
}


def assignment(pod: str, generation: int = 1, stage_id: int = 0, tasks: tuple[str, ...] = ("a",)) -> Assignment:
    blocks = tuple(TaskBlock(task_id=t, env_start=2 * i, num_envs=2) for i, t in enumerate(tasks))
    return Assignment(generation=generation, job_id="t", pod=pod, stage_id=stage_id, tasks=blocks)


# reconcile(desired, observed): pure, no network.


def test_reconcile_pushes_to_a_pod_that_runs_nothing():
    want = assignment("sim-0")
    actions = reconcile(Desired({"sim-0": want}), Observed(now=0.0, pods={"sim-0": ObservedPod(url="http://p0")}))
    assert actions == [PushAssignment(pod="sim-0", url="http://p0", assignment=want)]


def test_reconcile_leaves_a_pod_that_reports_its_assignment_alone():
    want = assignment("sim-0")
    observed = Observed(now=0.0, pods={"sim-0": ObservedPod(url="http://p0", reported=want)})
    assert reconcile(Desired({"sim-0": want}), observed) == []


def test_reconcile_pushes_a_new_generation_even_with_the_same_envs():
    observed = Observed(now=0.0, pods={"sim-0": ObservedPod(url="http://p0", reported=assignment("sim-0", 1))})
    assert [a.assignment.generation for a in reconcile(Desired({"sim-0": assignment("sim-0", 2)}), observed)] == [2]


def test_reconcile_waits_for_the_heartbeat_after_an_accepted_push_then_pushes_again():
    want = assignment("sim-0")
    pod = ObservedPod(url="http://p0", acked=want, acked_at=10.0)
    desired = Desired({"sim-0": want}, repush_after_s=5.0)
    assert reconcile(desired, Observed(now=12.0, pods={"sim-0": pod})) == []
    assert len(reconcile(desired, Observed(now=15.0, pods={"sim-0": pod}))) == 1


def test_reconcile_skips_a_pod_backing_off_after_a_failed_push():
    pod = ObservedPod(url="http://p0", retry_at=3.0)
    desired = Desired({"sim-0": assignment("sim-0")})
    assert reconcile(desired, Observed(now=2.0, pods={"sim-0": pod})) == []
    assert len(reconcile(desired, Observed(now=3.0, pods={"sim-0": pod}))) == 1


def test_reconcile_accepts_any_empty_assignment_for_a_spare():
    spare = Assignment(generation=5, pod="sim-2", stage_id=0)
    observed = Observed(
        now=0.0, pods={"sim-2": ObservedPod(url="http://p2", reported=spare.model_copy(update={"generation": 2}))}
    )
    assert reconcile(Desired({"sim-2": spare}), observed) == []


def test_reconcile_ignores_pods_it_cannot_reach_and_pods_without_a_desire():
    desired = Desired({"sim-0": assignment("sim-0")})
    observed = Observed(now=0.0, pods={"sim-9": ObservedPod(url="http://p9")})
    assert reconcile(desired, observed) == []


def test_reconcile_is_idempotent_and_ordered_by_pod():
    desired = Desired({n: assignment(n) for n in ("sim-1", "sim-0", "sim-2")})
    observed = Observed(now=0.0, pods={n: ObservedPod(url=f"http://{n}") for n in ("sim-2", "sim-0", "sim-1")})
    first = reconcile(desired, observed)
    assert first == reconcile(desired, observed)
    assert [a.pod for a in first] == ["sim-0", "sim-1", "sim-2"]


def _two_pod_plan():
    from vecsim.config import PodRecord

    job = JobSpec(**JOB)
    return plan(job, [PodRecord(pod="sim-0", url="a"), PodRecord(pod="sim-1", url="b")], None, list(TASKS))


def test_safe_generation_keeps_the_plans_generation_when_pods_agree():
    p = _two_pod_plan()
    assert safe_generation(p, {"sim-0": p.assignments["sim-0"], "sim-1": None}) == p.generation


def test_safe_generation_moves_past_a_newer_generation_a_pod_reports():
    p = _two_pod_plan()
    assert safe_generation(p, {"sim-0": assignment("sim-0", generation=7)}) == 8


def test_safe_generation_moves_on_when_a_pod_runs_other_content_at_the_plans_generation():
    p = _two_pod_plan()
    assert safe_generation(p, {"sim-0": assignment("sim-0", generation=p.generation)}) == p.generation + 1


# The HTTP API, in process, driven pass by pass with a clock the test moves.


class Clock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


class Controller:
    """A controller app behind an in-process transport; ``reconcile()`` runs one pass."""

    def __init__(self, api: httpx.AsyncClient, pods: httpx.AsyncClient, app: FastAPI, clock: Clock) -> None:
        self.api, self.pods, self.app, self.clock = api, pods, app, clock
        self.state = app.state.controller
        self.urls: dict[str, str] = {}

    async def reconcile(self) -> list[PushAssignment]:
        return await Reconciler(self.state, self.pods).run_once()

    async def register(self, name: str, url: str | None = None, max_envs: int = 64) -> httpx.Response:
        self.urls[name] = url or f"http://127.0.0.1:9/{name}"
        body = {"pod": name, "url": self.urls[name], "capacity": {"max_envs": max_envs}}
        return await self.api.post("/v1/pods", json=body)

    async def heartbeat(self, name: str, reported: Assignment | None = None, ready: bool = False) -> httpx.Response:
        body = {
            "url": self.urls[name],
            "generation": reported.generation if reported else None,
            "assignment": reported.model_dump(mode="json") if reported else None,
            "ready": ready,
        }
        return await self.api.post(f"/v1/pods/{name}/heartbeat", json=body)

    async def report_desired(self, *names: str, ready: bool = True) -> None:
        """Every named pod heartbeats that it runs what the plan wants of it."""
        desired = self.state.desired().assignments
        for name in names:
            await self.heartbeat(name, desired[name], ready=ready)


@asynccontextmanager
async def controller(**settings: object) -> AsyncIterator[Controller]:
    clock = Clock()
    settings.setdefault("adopt_grace_s", 0.0)
    app = create_app(ControllerSettings(**settings), clock=clock, reconcile=False)
    async with (
        httpx.AsyncClient(transport=httpx.ASGITransport(app=app), base_url="http://controller") as api,
        httpx.AsyncClient(timeout=2.0) as pods,
    ):
        yield Controller(api, pods, app, clock)


async def test_a_registered_pod_is_listed_without_a_stage():
    async with controller() as c:
        record = (await c.register("sim-0", "http://127.0.0.1:8100/")).json()
        assert record["pod"] == "sim-0" and record["url"] == "http://127.0.0.1:8100" and record["stage_id"] is None
        assert [p["pod"] for p in (await c.api.get("/v1/pods")).json()] == ["sim-0"]


async def test_a_registration_in_the_old_spelling_name_is_still_taken_for_this_release():
    async with controller() as c:
        old = {"name": "sim-0", "url": "http://127.0.0.1:8100"}
        assert (await c.api.post("/v1/pods", json=old)).json()["pod"] == "sim-0"
        both = await c.api.post("/v1/pods", json={**old, "pod": "sim-1"})
        assert both.status_code == 422 and "name: " in both.text
        assert [p["pod"] for p in (await c.api.get("/v1/pods")).json()] == ["sim-0"]


async def test_registration_with_a_bad_name_is_refused_naming_the_field():
    async with controller() as c:
        response = await c.register("Sim_0")
        assert response.status_code == 422 and "pod: " in response.text
        assert (await c.api.get("/v1/pods")).json() == []


async def test_a_heartbeat_from_an_unknown_pod_asks_it_to_register():
    async with controller() as c:
        response = await c.api.post("/v1/pods/sim-3/heartbeat", json={"url": "http://x", "ready": False})
        assert (
            response.status_code == 404
            and "sim-3" in response.json()["detail"]
            and "POST /v1/pods" in response.json()["detail"]
        )


async def test_a_heartbeat_whose_generation_contradicts_its_assignment_is_refused():
    async with controller() as c:
        await c.register("sim-0")
        body = {
            "url": "http://x",
            "generation": 3,
            "assignment": assignment("sim-0", 2).model_dump(mode="json"),
            "ready": True,
        }
        response = await c.api.post("/v1/pods/sim-0/heartbeat", json=body)
        assert response.status_code == 422 and "generation" in response.json()["detail"]
        assert (await c.api.get("/v1/pods")).json()[0]["generation"] is None


async def test_job_is_404_before_one_is_set_and_echoed_after():
    async with controller() as c:
        assert (await c.api.get("/v1/job")).status_code == 404
        assert (await c.api.put("/v1/job", json=JOB)).status_code == 200
        assert (await c.api.get("/v1/job")).json()["tasks"] == list(TASKS)


async def test_a_job_with_an_unknown_task_is_refused_naming_the_task_and_changes_nothing():
    async with controller() as c:
        await c.api.put("/v1/job", json=JOB)
        response = await c.api.put("/v1/job", json={**JOB, "tasks": ["tiny/lift", "nope/missing"]})
        assert response.status_code == 422
        assert any("nope/missing" in p for p in response.json()["problems"])
        assert (await c.api.get("/v1/job")).json()["tasks"] == list(TASKS)


async def test_a_job_whose_tasks_have_different_spaces_is_refused_naming_them():
    async with controller() as c:
        response = await c.api.put(
            "/v1/job", json={**JOB, "tasks": ["gym/Pendulum-v1", "gym/MountainCarContinuous-v0"]}
        )
        assert response.status_code == 422
        assert (
            "'gym/MountainCarContinuous-v0' has other observation/action spaces than 'gym/Pendulum-v1'" in response.text
        )


async def test_a_job_with_an_unknown_suite_is_refused_naming_the_suite():
    async with controller() as c:
        response = await c.api.put("/v1/job", json={"suite": "no_such_suite"})
        assert response.status_code == 422 and "no_such_suite" in response.json()["detail"]


async def test_a_job_too_big_for_the_pods_is_refused_saying_what_to_change():
    async with controller() as c:
        await c.register("sim-0", max_envs=4)
        response = await c.api.put("/v1/job", json=JOB)
        assert response.status_code == 422
        detail = response.json()["detail"]
        assert "sim-0" in detail and "6" in detail and "group_size" in detail
        assert (await c.api.get("/v1/job")).status_code == 404


async def test_a_malformed_job_is_refused_naming_the_field():
    async with controller() as c:
        response = await c.api.put("/v1/job", json={**JOB, "group_size": -1})
        assert response.status_code == 422 and "group_size" in response.text


async def test_a_job_with_zero_envs_per_task_is_planned_with_empty_pods():
    async with controller() as c:
        for name in ("sim-0", "sim-1"):
            await c.register(name)
            await c.heartbeat(name)
        assert (await c.api.put("/v1/job", json={**JOB, "group_size": 0})).status_code == 200
        await c.reconcile()
        table = (await c.api.get("/v1/routing")).json()
        assert [[(p["pod"], p["num_envs"]) for p in s["pods"]] for s in table["stages"]] == [
            [("sim-0", 0)],
            [("sim-1", 0)],
        ]


async def test_routing_is_404_without_a_job_and_503_before_a_plan():
    async with controller(adopt_grace_s=60.0) as c:
        assert (await c.api.get("/v1/routing")).status_code == 404
        await c.api.put("/v1/job", json=JOB)
        await c.reconcile()
        response = await c.api.get("/v1/routing")
        assert response.status_code == 503 and "waiting for pods" in response.json()["detail"]


async def test_routing_table_gives_every_stage_every_task():
    async with controller() as c:
        await c.register("sim-0", "http://127.0.0.1:9/a")
        await c.register("sim-1", "http://127.0.0.1:9/b")
        await c.api.put("/v1/job", json=JOB)
        await c.heartbeat("sim-0")
        await c.heartbeat("sim-1")
        await c.reconcile()
        table = (await c.api.get("/v1/routing")).json()
        assert table["generation"] == 1 and table["job_id"] == "t" and table["ready"] is False
        for stage, (pod, url) in zip(
            table["stages"], [("sim-0", "http://127.0.0.1:9/a"), ("sim-1", "http://127.0.0.1:9/b")]
        ):
            assert [(p["pod"], p["url"], p["num_envs"]) for p in stage["pods"]] == [(pod, url, 6)]
            assert [t["task_id"] for t in stage["pods"][0]["tasks"]] == list(TASKS)


async def test_pods_list_their_stage_generation_and_readiness():
    async with controller() as c:
        for name in ("sim-0", "sim-1", "sim-2"):
            await c.register(name)
            await c.heartbeat(name)
        await c.api.put("/v1/job", json=JOB)
        await c.reconcile()
        await c.report_desired("sim-0")
        pods = {p["pod"]: p for p in (await c.api.get("/v1/pods")).json()}
        assert [
            (pods[n]["stage_id"], pods[n]["ready"], pods[n]["generation"]) for n in ("sim-0", "sim-1", "sim-2")
        ] == [
            (0, True, 1),
            (1, False, None),
            (None, False, None),
        ]


async def test_readyz_names_what_is_missing_until_every_slot_runs_the_plan():
    async with controller() as c:
        await c.register("sim-0")
        await c.heartbeat("sim-0")
        await c.api.put("/v1/job", json=JOB)
        await c.reconcile()
        response = await c.api.get("/readyz")
        assert response.status_code == 503 and "stage 1 slot 0 has no pod" in response.json()["detail"]
        await c.register("sim-1")
        await c.reconcile()
        await c.report_desired("sim-0")
        await c.report_desired("sim-1", ready=False)
        response = await c.api.get("/readyz")
        assert response.status_code == 503 and "sim-1 is not ready" in response.json()["detail"]
        await c.report_desired("sim-1")
        assert (await c.api.get("/readyz")).json() == {"status": "ready", "generation": 2}
        assert (await c.api.get("/v1/routing")).json()["ready"] is True


async def test_a_pod_not_heard_from_within_the_ttl_is_dropped_and_its_slot_waits():
    async with controller(heartbeat_ttl_s=5.0) as c:
        for name in ("sim-0", "sim-1"):
            await c.register(name)
            await c.heartbeat(name)
        await c.api.put("/v1/job", json=JOB)
        await c.reconcile()
        c.clock.now += 4.0
        await c.heartbeat("sim-0")
        c.clock.now += 2.0
        await c.reconcile()
        assert [p["pod"] for p in (await c.api.get("/v1/pods")).json()] == ["sim-0"]
        table = (await c.api.get("/v1/routing")).json()
        assert table["generation"] == 2 and [len(s["pods"]) for s in table["stages"]] == [1, 0]
        assert (await c.heartbeat("sim-1")).status_code == 404


async def test_a_dropped_pod_that_comes_back_gets_its_slot_and_a_new_generation():
    async with controller(heartbeat_ttl_s=5.0) as c:
        for name in ("sim-0", "sim-1", "sim-2"):
            await c.register(name)
            await c.heartbeat(name)
        await c.api.put("/v1/job", json={**JOB, "pods_per_stage": 2})
        await c.reconcile()
        before = c.state.plan
        c.clock.now += 6.0
        for name in ("sim-0", "sim-2"):
            await c.heartbeat(name)
        await c.reconcile()
        await c.register("sim-1")
        await c.reconcile()
        assert c.state.plan.pods == before.pods
        assert c.state.plan.generation == before.generation + 2


async def test_a_slot_holder_that_registers_again_keeps_its_slot_and_moves_the_generation():
    async with controller() as c:
        for name in ("sim-0", "sim-1"):
            await c.register(name)
            await c.heartbeat(name)
        await c.api.put("/v1/job", json=JOB)
        await c.reconcile()
        before = c.state.plan
        await c.register("sim-1")
        await c.reconcile()
        assert c.state.plan.pods == before.pods and c.state.plan.generation == before.generation + 1


async def test_a_restarted_controller_adopts_what_pods_report_without_reassigning():
    async with controller() as first:
        for name in ("sim-1", "sim-0", "sim-2"):
            await first.register(name)
            await first.heartbeat(name)
        await first.api.put("/v1/job", json=JOB)
        await first.reconcile()
        await first.api.put("/v1/job", json={**JOB, "seed": 3})
        await first.reconcile()
        reports = first.state.desired().assignments
    async with controller(adopt_grace_s=30.0) as second:
        for name in ("sim-0", "sim-1", "sim-2"):
            await second.register(name)
            await second.heartbeat(name, reports[name], ready=True)
        await second.api.put("/v1/job", json={**JOB, "seed": 3})
        assert await second.reconcile() == []
        assert second.state.plan.pods == {"sim-0": (0, 0), "sim-1": (1, 0)}
        assert (await second.api.get("/readyz")).json() == {"status": "ready", "generation": 2}


async def test_a_fresh_controller_waits_for_the_grace_period_before_planning_without_reports():
    async with controller(adopt_grace_s=10.0) as c:
        await c.register("sim-1")
        await c.heartbeat("sim-1")
        await c.api.put("/v1/job", json=JOB)
        await c.reconcile()
        assert (await c.api.get("/v1/routing")).status_code == 503
        c.clock.now += 10.0
        await c.heartbeat("sim-1")
        await c.reconcile()
        assert c.state.plan is not None and c.state.plan.pods == {"sim-1": (0, 0)}


async def test_a_fresh_controller_plans_at_once_when_enough_pods_report_nothing():
    async with controller(adopt_grace_s=60.0) as c:
        for name in ("sim-0", "sim-1"):
            await c.register(name)
            await c.heartbeat(name)
        await c.api.put("/v1/job", json=JOB)
        await c.reconcile()
        assert c.state.plan is not None and c.state.plan.generation == 1


async def first_plans_reports(*names: str) -> dict[str, Assignment]:
    """What each of ``names`` runs under a controller that planned JOB for them (the last one a spare)."""
    async with controller() as first:
        for name in names:
            await first.register(name)
            await first.heartbeat(name)
        await first.api.put("/v1/job", json=JOB)
        await first.reconcile()
        return first.state.desired().assignments


async def test_a_fresh_controller_plans_at_once_when_the_unclaimed_slots_pod_restarted():
    reports = await first_plans_reports("sim-0", "sim-1")
    async with controller(adopt_grace_s=60.0) as c:
        await c.api.put("/v1/job", json=JOB)
        await c.register("sim-1")
        await c.heartbeat("sim-1", reports["sim-1"], ready=True)
        await c.register("sim-0")  # restarted with the controller: it runs nothing
        await c.reconcile()
        assert c.state.plan is None  # sim-0 has not said what it runs yet
        await c.heartbeat("sim-0")
        await c.reconcile()
        assert c.state.plan is not None and c.state.plan.pods == {"sim-0": (0, 0), "sim-1": (1, 0)}
        assert c.state.plan.generation > reports["sim-1"].generation


async def test_a_fresh_controller_waits_for_a_slot_holder_rather_than_give_its_slot_to_a_live_spare():
    reports = await first_plans_reports("sim-0", "sim-1", "sim-2")
    assert not reports["sim-2"].tasks  # the spare
    async with controller(adopt_grace_s=60.0) as c:
        await c.api.put("/v1/job", json=JOB)
        for name in ("sim-1", "sim-2"):
            await c.register(name)
            await c.heartbeat(name, reports[name], ready=True)
        await c.reconcile()
        assert c.state.plan is None and (await c.api.get("/v1/routing")).status_code == 503
        await c.register("sim-0")
        await c.heartbeat("sim-0", reports["sim-0"], ready=True)
        await c.reconcile()
        assert c.state.plan.pods == {"sim-0": (0, 0), "sim-1": (1, 0)}
        assert c.state.plan.generation == reports["sim-0"].generation


async def test_a_pod_reporting_a_newer_generation_lifts_the_plan_above_it():
    async with controller() as c:
        await c.register("sim-0")
        await c.heartbeat("sim-0", Assignment(generation=41, job_id="old", pod="sim-0", stage_id=0))
        await c.register("sim-1")
        await c.heartbeat("sim-1")
        await c.api.put("/v1/job", json=JOB)
        await c.reconcile()
        assert c.state.plan.generation == 42


async def test_metrics_report_pods_generation_and_heartbeats():
    async with controller() as c:
        for name in ("sim-0", "sim-1"):
            await c.register(name)
            await c.heartbeat(name)
        await c.api.put("/v1/job", json=JOB)
        await c.reconcile()
        text = (await c.api.get("/metrics")).text
        assert "vecsim_controller_pods 2.0" in text
        assert "vecsim_controller_generation 1.0" in text
        assert "vecsim_controller_heartbeats_total 2.0" in text
        assert "vecsim_controller_reconcile_seconds_count 1.0" in text


async def test_each_refused_request_is_counted_under_its_reason():
    async with controller() as c:
        await c.api.get("/v1/job")  # no job yet: 404
        await c.api.post("/v1/pods/sim-3/heartbeat", json={"url": "http://x", "ready": False})  # unknown pod: 404
        await c.api.put("/v1/job", json={**JOB, "num_stages": 0})  # a malformed job: 422
        await c.api.put("/v1/job", json={**JOB, "tasks": ["tiny/no-such-task"]})  # a job that cannot run: 422
        text = (await c.api.get("/metrics")).text
        for reason in ("no_job", "unknown_pod", "invalid_request", "job_rejected"):
            assert f'vecsim_controller_refused_requests_total{{reason="{reason}"}} 1.0' in text, reason


async def test_openapi_documents_every_endpoint():
    async with controller() as c:
        paths = (await c.api.get("/openapi.json")).json()["paths"]
        assert set(paths) == {
            "/v1/pods",
            "/v1/pods/{pod}/heartbeat",
            "/v1/job",
            "/v1/routing",
            "/healthz",
            "/readyz",
            "/metrics",
        }


def test_vecsim_controller_with_a_broken_config_exits_2_naming_the_field(tmp_path, capsys):
    from service.controller.main import main

    path = tmp_path / "bad.yaml"
    path.write_text("job:\n  tasks: [gym/Pendulum-v1]\n  num_stages: 0\n")
    assert main(["-c", str(path)]) == 2
    assert "num_stages" in capsys.readouterr().err


def test_vecsim_controller_refuses_a_config_whose_job_cannot_run(tmp_path, capsys):
    from service.controller.main import main

    path = tmp_path / "unknown.yaml"
    path.write_text("job:\n  tasks: [nope/missing]\n")
    assert main(["-c", str(path)]) == 2
    assert "nope/missing" in capsys.readouterr().err


# Pushes over real HTTP to small FastAPI peers served by uvicorn on loopback.


class Peer:
    """A stand-in pod: records every assignment pushed to it and answers with ``status``."""

    def __init__(self) -> None:
        self.received: list[Assignment] = []
        self.status = 200
        self.app = FastAPI()

        @self.app.put("/v1/assignment")
        async def put_assignment(body: Assignment) -> JSONResponse:
            if self.status != 200:
                return JSONResponse({"detail": "refused by the test"}, status_code=self.status)
            self.received.append(body)
            return JSONResponse({"generation": body.generation, "rebuilt": True})

        self.url = ""


@pytest.fixture
def peers() -> Iterator[list[Peer]]:
    made = [Peer() for _ in range(3)]
    with ExitStack() as stack:
        for peer in made:
            peer.url = stack.enter_context(AppThread(peer.app, lifespan="off")).url
        yield made


async def test_reconcile_pushes_each_pod_its_slots_assignment_and_spares_an_empty_one(peers):
    async with controller() as c:
        for i, peer in enumerate(peers):
            await c.register(f"sim-{i}", peer.url)
            await c.heartbeat(f"sim-{i}")
        await c.api.put("/v1/job", json=JOB)
        pushed = await c.reconcile()
        assert sorted(a.pod for a in pushed) == ["sim-0", "sim-1", "sim-2"]
        got = [p.received[-1] for p in peers]
        assert [(a.pod, a.stage_id, a.generation, a.num_envs) for a in got] == [
            ("sim-0", 0, 1, 6),
            ("sim-1", 1, 1, 6),
            ("sim-2", 0, 1, 0),
        ]
        assert [b.task_id for b in got[1].tasks] == list(TASKS)


async def test_an_accepted_push_is_not_repeated_before_the_pod_reports_it(peers):
    async with controller() as c:
        for i, peer in enumerate(peers[:2]):
            await c.register(f"sim-{i}", peer.url)
            await c.heartbeat(f"sim-{i}")
        await c.api.put("/v1/job", json=JOB)
        await c.reconcile()
        assert await c.reconcile() == []
        assert [len(p.received) for p in peers[:2]] == [1, 1]


async def test_a_job_change_pushes_the_new_generation_to_the_same_pods(peers):
    async with controller() as c:
        for i, peer in enumerate(peers[:2]):
            await c.register(f"sim-{i}", peer.url)
            await c.heartbeat(f"sim-{i}")
        await c.api.put("/v1/job", json=JOB)
        await c.reconcile()
        await c.report_desired("sim-0", "sim-1")
        await c.api.put("/v1/job", json={**JOB, "group_size": 1})
        await c.reconcile()
        assert [(p.received[-1].generation, p.received[-1].num_envs) for p in peers[:2]] == [(2, 3), (2, 3)]
        assert [p.received[-1].stage_id for p in peers[:2]] == [0, 1]


async def test_a_refused_push_backs_off_and_is_retried(peers):
    async with controller() as c:
        for i, peer in enumerate(peers[:2]):
            await c.register(f"sim-{i}", peer.url)
            await c.heartbeat(f"sim-{i}")
        await c.api.put("/v1/job", json=JOB)
        peers[1].status = 503
        await c.reconcile()
        peers[1].status = 200
        assert [a.pod for a in await c.reconcile()] == []
        c.clock.now += 1.0
        assert [a.pod for a in await c.reconcile()] == ["sim-1"]
        assert peers[1].received[-1].generation == 1


async def test_an_unreachable_pod_does_not_hold_up_pushes_to_the_others(peers):
    async with controller(push_timeout_s=2.0) as c:
        await c.register("sim-0", peers[0].url)
        await c.register("sim-1", "http://127.0.0.1:9")
        for name in ("sim-0", "sim-1"):
            await c.heartbeat(name)
        await c.api.put("/v1/job", json=JOB)
        await c.reconcile()
        assert len(peers[0].received) == 1
        assert c.state.pods["sim-1"].push_failures == 1


class SelfReportingPeer(Peer):
    """A stand-in pod that registers itself and heartbeats whatever was last pushed to it."""

    def __init__(self, name: str) -> None:
        super().__init__()
        self.name = name

    async def beat(self, controller_url: str, stop: asyncio.Event) -> None:
        async with httpx.AsyncClient(base_url=controller_url, timeout=2.0) as client:
            await client.post("/v1/pods", json={"pod": self.name, "url": self.url})
            while not stop.is_set():
                last = self.received[-1] if self.received else None
                body = {"url": self.url, "generation": last.generation if last else None, "ready": last is not None}
                body["assignment"] = last.model_dump(mode="json") if last else None
                await client.post(f"/v1/pods/{self.name}/heartbeat", json=body)
                await asyncio.sleep(0.05)  # the stand-in pod's heartbeat period, not a wait


async def test_a_served_controller_gets_self_reporting_pods_ready():
    settings = ControllerSettings(reconcile_interval_s=0.05, heartbeat_interval_s=0.05, adopt_grace_s=0.0)
    made = [SelfReportingPeer("sim-0"), SelfReportingPeer("sim-1")]
    with AppThread(create_app(settings), lifespan="on") as controller_app:
        url = controller_app.url
        with AppThread(made[0].app, lifespan="off") as s0, AppThread(made[1].app, lifespan="off") as s1:
            u0, u1 = made[0].url, made[1].url = s0.url, s1.url
            stop = asyncio.Event()
            beats = [asyncio.create_task(p.beat(url, stop)) for p in made]
            async with httpx.AsyncClient(base_url=url, timeout=2.0) as client:
                assert (await client.put("/v1/job", json=JOB)).status_code == 200

                def ready() -> bool:
                    return httpx.get(f"{url}/readyz", timeout=2).status_code == 200

                # Polled from a thread: this event loop keeps running the pods' heartbeats.
                await asyncio.to_thread(wait_until, ready, "the controller to be ready", 30)
                table = (await client.get("/v1/routing")).json()
            stop.set()
            await asyncio.gather(*beats)
    assert table["ready"] is True
    assert [[p["url"] for p in s["pods"]] for s in table["stages"]] == [[u0], [u1]]
