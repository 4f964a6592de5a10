"""The controller's HTTP API in process, driven by a test: a :class:`Clock` the test moves,
reconcile passes the test runs (:meth:`Controller.reconcile`), pods that exist only as the
registrations and heartbeats the test sends. Pushes go to an address that refuses them."""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass

import httpx

from service.controller import ControllerSettings, create_app
from service.controller.reconcile import PushAssignment
from service.controller.reconciler import Reconciler
from service.controller.state import ControllerState
from vecsim.config import Assignment

TTL_S = 5.0
JOB = {
    "job_id": "t",
    "tasks": ["tiny/lift", "tiny/stack"],
    "group_size": 1,
    "num_stages": 2,
    "pods_per_stage": 1,
    "camera": {"names": []},
}


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
        body = {"pod": name, "url": f"http://127.0.0.1:9/{name}", "capacity": {"max_envs": max_envs}}
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
