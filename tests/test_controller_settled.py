"""A controller with nothing to do does nothing: a reconcile pass that found every pod running its
assignment settles it, and passes skip planning until something changes; re-planning happens on
changes of the job or the live pods, while heartbeat reports still move the generation on.

The controller's HTTP API runs in process with a clock the test moves; pushes go to an address
that refuses them (the pods here are only reports)."""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass

import httpx
import pytest

from service.controller import ControllerSettings, create_app
from service.controller.reconcile import PushAssignment, Reconciler
from service.controller.state import ControllerState
from vecsim.config import Assignment

pytestmark = pytest.mark.anyio

TTL_S = 5.0
JOB = {
    "job_id": "t",
    "tasks": ["tiny/lift", "tiny/stack"],
    "group_size": 1,
    "num_stages": 2,
    "pods_per_stage": 1,
    "camera": {"names": []},
}


@pytest.fixture
def anyio_backend() -> str:
    return "asyncio"


class Clock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


@dataclass
class Controller:
    api: httpx.AsyncClient
    pushes: httpx.AsyncClient
    state: ControllerState
    clock: Clock

    async def reconcile(self) -> list[PushAssignment]:
        return await Reconciler(self.state, self.pushes).run_once()

    async def register(self, name: str, max_envs: int = 64) -> None:
        body = {"name": name, "url": f"http://127.0.0.1:9/{name}", "capacity": {"max_envs": max_envs}}
        assert (await self.api.post("/v1/pods", json=body)).status_code == 200

    async def heartbeat(self, name: str, reported: Assignment | None, ready: bool = True) -> None:
        body = {
            "url": f"http://127.0.0.1:9/{name}",
            "generation": reported.generation if reported else None,
            "assignment": reported.model_dump(mode="json") if reported else None,
            "ready": ready,
        }
        assert (await self.api.post(f"/v1/pods/{name}/heartbeat", json=body)).status_code == 200

    async def report_desired(self, *names: str) -> None:
        desired = self.state.desired().assignments
        for name in names:
            await self.heartbeat(name, desired[name])


@asynccontextmanager
async def controller() -> AsyncIterator[Controller]:
    clock = Clock()
    settings = ControllerSettings(adopt_grace_s=0.0, heartbeat_ttl_s=TTL_S)
    app = create_app(settings, clock=clock, reconcile=False)
    async with (
        httpx.AsyncClient(transport=httpx.ASGITransport(app=app), base_url="http://controller") as api,
        httpx.AsyncClient(timeout=2.0) as pushes,
    ):
        yield Controller(api, pushes, app.state.controller, clock)


async def running_job(c: Controller, pods: tuple[str, ...] = ("sim-0", "sim-1", "sim-2")) -> None:
    """Register ``pods``, set the job, plan it, and have every pod report its assignment."""
    for name in pods:
        await c.register(name)
        await c.heartbeat(name, None, ready=False)
    assert (await c.api.put("/v1/job", json=JOB)).status_code == 200
    await c.reconcile()
    await c.report_desired(*pods)


async def test_a_pass_that_finds_every_pod_on_its_assignment_settles_the_controller():
    async with controller() as c:
        await running_job(c)
        assert not c.state.settled
        assert await c.reconcile() == []
        assert c.state.settled
        assert await c.reconcile() == [] and c.state.settled
        assert (await c.api.get("/readyz")).status_code == 200


async def test_a_settled_controller_still_moves_a_silent_pods_slot_to_a_spare():
    async with controller() as c:
        await running_job(c)
        await c.reconcile()
        assert c.state.settled
        holder = c.state.plan.slots[0].pod
        c.clock.now += TTL_S / 2
        await c.report_desired(*(n for n in ("sim-0", "sim-1", "sim-2") if n != holder))
        c.clock.now += TTL_S / 2 + 0.1
        before = c.state.plan.generation
        pushes = await c.reconcile()
        assert c.state.plan.generation == before + 1
        assert holder not in c.state.pods and c.state.plan.slots[0].pod not in (None, holder)
        assert {p.pod for p in pushes} == set(c.state.pods)


async def test_a_new_pod_or_a_changed_report_unsettles_the_controller():
    async with controller() as c:
        await running_job(c)
        await c.reconcile()
        await c.register("sim-3")
        assert not c.state.settled
        await c.heartbeat("sim-3", None, ready=False)
        pushes = await c.reconcile()
        assert [p.pod for p in pushes] == ["sim-3"] and not c.state.settled
        await c.report_desired("sim-3")
        await c.reconcile()
        assert c.state.settled
        await c.heartbeat("sim-0", c.state.desired().assignments["sim-0"], ready=False)
        assert not c.state.settled


async def test_a_pod_reporting_a_newer_generation_moves_the_plan_past_it_without_new_pods():
    async with controller() as c:
        await running_job(c)
        await c.reconcile()
        generation = c.state.plan.generation
        ahead = c.state.desired().assignments["sim-0"].model_copy(update={"generation": generation + 5})
        await c.heartbeat("sim-0", ahead)
        c.clock.now += 1.0  # past the back-off of the pushes that failed while planning the job
        pushes = await c.reconcile()
        assert c.state.plan.generation == generation + 6
        assert {p.assignment.generation for p in pushes} == {generation + 6}


async def test_an_unfilled_slots_problem_names_the_spares_too_small_for_it():
    async with controller() as c:
        await running_job(c, pods=("sim-0", "sim-1"))
        await c.register("sim-5", max_envs=0)
        await c.heartbeat("sim-5", None, ready=False)
        holder = c.state.plan.slots[1].pod
        c.clock.now += TTL_S / 2
        await c.report_desired(*(n for n in ("sim-0", "sim-1") if n != holder))
        await c.heartbeat("sim-5", None, ready=False)
        c.clock.now += TTL_S / 2 + 0.1
        await c.reconcile()
        detail = (await c.api.get("/readyz")).json()["detail"]
        assert "stage 1 slot 0 has no pod (pods sim-5 have max_envs below the 2 envs it needs)" in detail
