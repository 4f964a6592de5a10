"""The controller with a ``slices`` job, in process: the plan it pushes, the routing table it
serves, and pods coming and going (a clock the test moves, reconcile passes the test runs)."""

from __future__ import annotations

import pytest
from support.controller_in_process import JOB, TTL_S, controller

pytestmark = pytest.mark.anyio


SLICES = {**JOB, "stage_layout": "slices", "pods_per_stage": 2}


def env_ids(table: dict, pod: str) -> dict[int, list[int]]:
    return {
        stage["stage_id"]: [
            env
            for p in stage["pods"]
            if p["pod"] == pod
            for t in p["tasks"]
            for env in range(t["env_start"], t["env_start"] + t["num_envs"])
        ]
        for stage in table["stages"]
    }


async def test_a_slices_job_pushes_every_pod_blocks_of_every_stage():
    async with controller() as c:
        for name in ("sim-0", "sim-1", "sim-2"):
            await c.register(name)
            await c.heartbeat(name, None, ready=False)
        assert (await c.api.put("/v1/job", json=SLICES)).status_code == 200
        pushes = await c.reconcile()
        wanted = {push.pod: push.assignment for push in pushes}
        assert wanted["sim-0"].stage_id is None and {b.stage_id for b in wanted["sim-0"].tasks} == {0, 1}
        assert wanted["sim-2"].tasks == ()  # a spare: two slots in all
        await c.report_desired("sim-0", "sim-1", "sim-2")
        assert (await c.api.get("/readyz")).status_code == 200
        pods = {p["pod"]: p["stage_id"] for p in (await c.api.get("/v1/pods")).json()}
        assert pods == {"sim-0": None, "sim-1": None, "sim-2": None}


async def test_the_routing_table_of_a_slices_job_gives_each_stage_its_own_env_ids_on_every_pod():
    async with controller() as c:
        for name in ("sim-0", "sim-1"):
            await c.register(name)
            await c.heartbeat(name, None, ready=False)
        await c.api.put("/v1/job", json=SLICES)
        await c.reconcile()
        table = (await c.api.get("/v1/routing")).json()
        assert [[p["pod"] for p in s["pods"]] for s in table["stages"]] == [["sim-0", "sim-1"]] * 2
        for pod in ("sim-0", "sim-1"):
            ids = env_ids(table, pod)
            assert ids[0] and ids[1] and not set(ids[0]) & set(ids[1])


async def test_a_dropped_slices_pod_leaves_its_slot_to_a_spare_and_the_layout_stays():
    async with controller() as c:
        for name in ("sim-0", "sim-1", "sim-2"):
            await c.register(name)
            await c.heartbeat(name, None, ready=False)
        await c.api.put("/v1/job", json=SLICES)
        await c.reconcile()
        await c.report_desired("sim-0", "sim-1", "sim-2")
        before = (await c.api.get("/v1/routing")).json()
        c.clock.now += TTL_S + 1
        await c.heartbeat("sim-0", c.state.desired().assignments["sim-0"])
        await c.heartbeat("sim-2", c.state.desired().assignments["sim-2"])
        await c.reconcile()  # sim-1 dropped; the spare sim-2 takes its slot
        await c.report_desired("sim-0", "sim-2")
        after = (await c.api.get("/v1/routing")).json()
        assert after["generation"] > before["generation"] and after["ready"] is True
        assert [[p["pod"] for p in s["pods"]] for s in after["stages"]] == [["sim-0", "sim-2"]] * 2
        assert env_ids(after, "sim-2") == env_ids(before, "sim-1")
        assert env_ids(after, "sim-0") == env_ids(before, "sim-0")
