"""A controller with nothing to do does nothing: a reconcile pass that found every pod running its
assignment settles it, and passes skip planning until something changes; re-planning happens on
changes of the job or the live pods, while heartbeat reports still move the generation on.

The controller's HTTP API runs in process with a clock the test moves; pushes go to an address
that refuses them (the pods here are only reports)."""

from __future__ import annotations

import pytest
from support.controller_in_process import TTL_S, controller, running_job

pytestmark = pytest.mark.anyio


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
