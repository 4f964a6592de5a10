"""The pod's controller agent, against a stand-in controller: a small real FastAPI app on
loopback that records every registration and heartbeat it receives and can be told to forget a
pod or to fail. The pods are real pod apps served by uvicorn in this process, with no envs (a
spare assignment), so each test stays cheap.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from typing import Any

import httpx
import pytest
from fastapi import FastAPI, Response
from support.service_procs import AppThread, loopback_socket, wait_until

from service.pod.agent import backoff_delay
from service.pod.app import create_app
from service.pod.settings import PodSettings
from vecsim.config import Assignment, PodRecord, PodRegistration

HEARTBEAT_S = 0.05


class StandInController:
    """Records what pods send; forgets pods or answers 500 when a test says so."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.registrations: list[dict[str, Any]] = []
        self.heartbeats: list[dict[str, Any]] = []
        self.known: set[str] = set()
        self.failing = False
        self.refused = 0
        self.app = FastAPI()

        @self.app.post("/v1/pods")
        async def register(registration: PodRegistration) -> Any:
            with self.lock:
                if self.failing:
                    self.refused += 1
                    return Response(status_code=500)
                self.registrations.append(registration.model_dump(mode="json"))
                self.known.add(registration.pod)
            return PodRecord(pod=registration.pod, url=registration.url, capacity=registration.capacity)

        @self.app.post("/v1/pods/{pod}/heartbeat")
        async def heartbeat(pod: str, body: dict[str, Any]) -> Any:
            with self.lock:
                if self.failing:
                    self.refused += 1
                    return Response(status_code=500)
                if pod not in self.known:
                    return Response(status_code=404)
                self.heartbeats.append({"pod": pod, **body})
            return {"generation": body.get("generation")}

    def forget(self, name: str) -> None:
        with self.lock:
            self.known.discard(name)

    def last_heartbeat(self) -> dict[str, Any] | None:
        with self.lock:
            return self.heartbeats[-1] if self.heartbeats else None

    def count(self, what: str) -> int:
        with self.lock:
            return len(getattr(self, what))


@pytest.fixture
def controller() -> Iterator[tuple[StandInController, AppThread]]:
    stand_in = StandInController()
    server = AppThread(stand_in.app, access_log=False, lifespan="on")
    try:
        yield stand_in, server
    finally:
        server.stop()


def serve_pod(name: str, controller_url: str) -> AppThread:
    sock = loopback_socket()
    settings = PodSettings(
        name=name,
        port=sock.getsockname()[1],
        controller_url=controller_url,
        heartbeat_interval_s=HEARTBEAT_S,
        max_backoff_s=4 * HEARTBEAT_S,
        max_envs=3,
        gpu=False,
    )
    return AppThread(create_app(settings), sock, access_log=False, lifespan="on")


@pytest.fixture
def pod(controller: tuple[StandInController, AppThread]) -> Iterator[AppThread]:
    server = serve_pod("sim-3", controller[1].url)
    try:
        yield server
    finally:
        server.stop()


def test_pod_registers_with_its_name_url_and_capacity(
    controller: tuple[StandInController, AppThread], pod: AppThread
) -> None:
    stand_in, _ = controller
    wait_until(lambda: stand_in.count("registrations") >= 1, "a registration")
    assert stand_in.registrations[0] == {
        "pod": "sim-3",
        "url": pod.url,
        "capacity": {"max_envs": 3, "gpu": False},
    }


def test_heartbeats_say_unassigned_and_not_ready_before_an_assignment(
    controller: tuple[StandInController, AppThread], pod: AppThread
) -> None:
    stand_in, _ = controller
    wait_until(lambda: stand_in.count("heartbeats") >= 2, "two heartbeats")
    beat = stand_in.last_heartbeat()
    assert beat == {"pod": "sim-3", "url": pod.url, "generation": None, "assignment": None, "ready": False}


def test_heartbeats_report_the_assignment_generation_and_readiness(
    controller: tuple[StandInController, AppThread], pod: AppThread
) -> None:
    stand_in, _ = controller
    spare = Assignment(generation=5, job_id="agent-tests", pod="sim-3", stage_id=0, tasks=())
    response = httpx.put(f"{pod.url}/v1/assignment", json=spare.model_dump(mode="json"), timeout=30)
    assert response.status_code == 200
    wait_until(lambda: (stand_in.last_heartbeat() or {}).get("ready") is True, "a heartbeat saying ready")
    beat = stand_in.last_heartbeat()
    assert beat is not None
    assert beat["generation"] == 5
    assert Assignment.model_validate(beat["assignment"]) == spare


def test_pod_registers_again_when_the_controller_forgets_it(
    controller: tuple[StandInController, AppThread], pod: AppThread
) -> None:
    stand_in, _ = controller
    wait_until(lambda: stand_in.count("heartbeats") >= 1, "a heartbeat")
    stand_in.forget("sim-3")
    wait_until(lambda: stand_in.count("registrations") >= 2, "a second registration")
    beats = stand_in.count("heartbeats")
    wait_until(lambda: stand_in.count("heartbeats") > beats, "heartbeats after registering again")


def test_controller_errors_leave_the_pod_serving_and_heartbeats_resume(
    controller: tuple[StandInController, AppThread], pod: AppThread
) -> None:
    stand_in, _ = controller
    wait_until(lambda: stand_in.count("heartbeats") >= 1, "a heartbeat")
    with stand_in.lock:
        stand_in.failing = True
    wait_until(lambda: stand_in.refused >= 3, "three refused heartbeats")
    assert httpx.get(f"{pod.url}/healthz", timeout=10).status_code == 200
    beats = stand_in.count("heartbeats")
    with stand_in.lock:
        stand_in.failing = False
    wait_until(lambda: stand_in.count("heartbeats") > beats, "heartbeats after the errors stop")


def test_pod_finds_a_controller_that_starts_after_it() -> None:
    reserved = loopback_socket()
    controller_url = f"http://127.0.0.1:{reserved.getsockname()[1]}"
    pod = serve_pod("sim-4", controller_url)
    stand_in = StandInController()
    try:
        assert httpx.get(f"{pod.url}/healthz", timeout=10).status_code == 200
        # The controller comes up on the address the pod has been retrying all along.
        server = AppThread(stand_in.app, reserved, access_log=False, lifespan="on")
        try:
            wait_until(lambda: stand_in.count("heartbeats") >= 1, "a heartbeat from the early pod")
            assert stand_in.registrations[0]["pod"] == "sim-4"
        finally:
            server.stop()
    finally:
        pod.stop()
        reserved.close()


def test_backoff_doubles_per_failure_up_to_its_cap() -> None:
    delays = [backoff_delay(failures, 0.5, 10.0) for failures in range(8)]
    assert delays == [0.5, 1.0, 2.0, 4.0, 8.0, 10.0, 10.0, 10.0]
    assert backoff_delay(10_000, 0.5, 10.0) == 10.0
