"""The controller's own stalls are not counted against the pods' heartbeat TTL.

When the controller's event loop does not run (GC, a long pass, an overloaded machine), no
heartbeat can be taken in; on waking it must not drop every pod whose heartbeat waited in a
socket meanwhile. The state's ticks (``ControllerState.tick``) measure how long the loop was
away; pods' deadlines move on by that. Most tests drive the state with a clock they move (a
stall is a jump of the clock between two ticks); the last serves a real controller with uvicorn
and blocks its event loop with ``time.sleep`` through an endpoint the test adds.
"""

from __future__ import annotations

import threading
import time
from collections.abc import AsyncIterator, Iterator
from contextlib import asynccontextmanager, contextmanager

import httpx
import pytest
from support.controller_in_process import TTL_S, Clock, Controller, running_job
from support.service_procs import AppThread, wait_until

from service.controller import ControllerSettings, create_app
from service.controller.state import ControllerState

pytestmark = pytest.mark.anyio

PODS = ("sim-0", "sim-1", "sim-2")
PASSES = "vecsim_controller_reconcile_seconds_count"  # one per reconcile pass


@asynccontextmanager
async def ticking_controller() -> AsyncIterator[Controller]:
    """A controller running ``JOB`` on three pods, every pod just heard, its loop ticking."""
    clock = Clock()
    app = create_app(ControllerSettings(adopt_grace_s=0.0, heartbeat_ttl_s=TTL_S), clock=clock, reconcile=False)
    async with (
        httpx.AsyncClient(transport=httpx.ASGITransport(app=app), base_url="http://controller") as api,
        httpx.AsyncClient(timeout=2.0) as pushes,
    ):
        c = Controller(api, pushes, app.state.controller, clock)
        await running_job(c, PODS)
        c.state.tick()
        yield c


def run_for(state: ControllerState, clock: Clock, seconds: float, step: float = 0.25) -> None:
    """The controller runs for ``seconds``: its loop ticks every ``step``."""
    for _ in range(round(seconds / step)):
        clock.now += step
        state.tick()


async def listed(c: Controller) -> list[str]:
    return [p["pod"] for p in (await c.api.get("/v1/pods")).json()]


async def test_a_stall_longer_than_the_ttl_drops_no_pod():
    async with ticking_controller() as c:
        generation = c.state.plan.generation
        c.clock.now += 3 * TTL_S  # the loop did not run: no tick, no heartbeat
        await c.reconcile()
        assert await listed(c) == list(PODS)
        assert c.state.plan.generation == generation and not c.state.plan.unfilled


async def test_a_stall_shorter_than_the_ttl_is_not_counted_against_a_pod_heard_before_it():
    async with ticking_controller() as c:
        run_for(c.state, c.clock, TTL_S - 1.0)
        desired = c.state.desired().assignments
        for name in PODS[:2]:
            await c.heartbeat(name, desired[name])
        c.clock.now += 2.0  # sim-2 was last heard TTL + 1 s ago, 2 s of which the loop was away
        await c.reconcile()
        assert await listed(c) == list(PODS)


async def test_a_truly_silent_pod_is_still_dropped_once_the_ttl_has_run_after_a_stall():
    async with ticking_controller() as c:
        assert c.state.plan.slot_of("sim-1") is not None and c.state.plan.slot_of("sim-2") is None
        c.clock.now += 3 * TTL_S
        await c.reconcile()
        desired = c.state.desired().assignments
        for _ in range(int(TTL_S) + 1):  # sim-0 and sim-2 heartbeat every second; sim-1 never again
            for name in ("sim-0", "sim-2"):
                await c.heartbeat(name, desired[name])
            run_for(c.state, c.clock, 1.0)
            await c.reconcile()
        assert await listed(c) == ["sim-0", "sim-2"]
        assert c.state.plan.slot_of("sim-2") is not None  # sim-1's slot went to the spare


async def test_without_a_stall_a_pod_silent_past_the_ttl_is_dropped():
    async with ticking_controller() as c:
        run_for(c.state, c.clock, TTL_S + 0.5)
        await c.reconcile()
        assert await listed(c) == []


async def test_a_stall_is_counted_in_the_metrics():
    async with ticking_controller() as c:
        c.clock.now += 12.0
        c.state.tick()
        text = (await c.api.get("/metrics")).text
    assert "vecsim_controller_stalls_total 1.0" in text
    assert "vecsim_controller_stalled_seconds_total 12.0" in text


def test_the_stall_threshold_is_at_most_half_the_ttl():
    assert ControllerSettings(heartbeat_ttl_s=1.0, stall_threshold_s=5.0).stall_after_s == 0.5
    assert ControllerSettings(heartbeat_ttl_s=5.0).stall_after_s == 1.0


# A served controller whose event loop the test blocks.


@contextmanager
def serve_controller(settings: ControllerSettings) -> Iterator[str]:
    """The controller app, plus ``POST /test/stall?seconds=`` (a ``time.sleep`` on its event
    loop), served by uvicorn on a free loopback port in a thread. Yields its URL."""
    app = create_app(settings)

    @app.post("/test/stall")
    async def stall(seconds: float) -> dict[str, float]:
        time.sleep(seconds)  # the fault under test: blocks the event loop, so nothing else runs
        return {"slept": seconds}

    with AppThread(app, lifespan="on") as server:
        yield server.url


def heartbeat_until(url: str, names: tuple[str, ...], stop: threading.Event) -> None:
    """Pods that register and then heartbeat every 0.1 s, waiting out a stalled controller."""
    with httpx.Client(base_url=url, timeout=30.0) as client:
        for name in names:
            client.post("/v1/pods", json={"pod": name, "url": "http://127.0.0.1:9", "capacity": {"max_envs": 64}})
        while not stop.is_set():
            for name in names:
                body = {"url": "http://127.0.0.1:9", "generation": None, "assignment": None, "ready": False}
                client.post(f"/v1/pods/{name}/heartbeat", json=body)
            stop.wait(0.1)


def counter(metrics: str, name: str) -> float:
    """The value of one unlabelled metric in Prometheus text."""
    values = [line.split()[1] for line in metrics.splitlines() if line.startswith(f"{name} ")]
    assert len(values) == 1, f"{name} not in the metrics"
    return float(values[0])


def test_a_served_controller_whose_loop_blocks_past_the_ttl_keeps_its_pods():
    ttl = 2.0
    settings = ControllerSettings(
        heartbeat_ttl_s=ttl, heartbeat_interval_s=0.1, reconcile_interval_s=0.05, stall_threshold_s=0.3
    )
    with serve_controller(settings) as url:
        stop = threading.Event()
        beats = threading.Thread(target=heartbeat_until, args=(url, PODS, stop), daemon=True)
        beats.start()
        try:
            wait_until(lambda: len(httpx.get(f"{url}/v1/pods", timeout=5).json()) == len(PODS), "pods to register", 30)
            assert httpx.post(f"{url}/test/stall", params={"seconds": 2.5 * ttl}, timeout=30).status_code == 200
            passes = counter(httpx.get(f"{url}/metrics", timeout=5).text, PASSES)
            # A few reconcile passes after the stall: any of them would have expired the pods.
            wait_until(
                lambda: counter(httpx.get(f"{url}/metrics", timeout=5).text, PASSES) >= passes + 3,
                "three reconcile passes after the stall",
                30,
                every=0.05,
            )
            after = [p["pod"] for p in httpx.get(f"{url}/v1/pods", timeout=5).json()]
            metrics = httpx.get(f"{url}/metrics", timeout=5).text
        finally:
            stop.set()
            beats.join(timeout=35)
    assert after == list(PODS)
    assert counter(metrics, "vecsim_controller_pods_expired_total") == 0
    assert counter(metrics, "vecsim_controller_stalled_seconds_total") >= 2.5 * ttl
