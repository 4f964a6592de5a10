"""The pod and the controller are wired by one function (``service.app.server_app``), so they
refuse alike: the same handlers and middleware in both apps, and, served side by side by real
uvicorn on loopback, the same answer and the same metric to the same kind of bad request."""

from __future__ import annotations

import re
from collections.abc import Iterator

import httpx
import pytest
from fastapi import FastAPI
from fastapi.exceptions import RequestValidationError
from support.service_procs import AppThread

from service.controller import ControllerSettings
from service.controller.app import create_app as create_controller_app
from service.errors import RefusedError, answer_refusal, answer_validation_error
from service.http import BearerTokenMiddleware, BodyLimitMiddleware
from service.pod.app import create_app as create_pod_app
from service.pod.settings import PodSettings

TOKEN = "wiring-test-token"
LIMIT = 4096
# One route per server that takes a JSON body: the pod's assignment, the controller's job.
BODY_ROUTE = {"pod": "/v1/assignment", "controller": "/v1/job"}


def both_apps() -> dict[str, FastAPI]:
    return {
        "pod": create_pod_app(PodSettings(name="sim-0", token=TOKEN, max_body_bytes=LIMIT, max_envs=1, gpu=False)),
        "controller": create_controller_app(ControllerSettings(token=TOKEN, max_body_bytes=LIMIT), reconcile=False),
    }


@pytest.fixture(scope="module")
def servers() -> Iterator[dict[str, AppThread]]:
    threads = {name: AppThread(app, access_log=False, lifespan="on") for name, app in both_apps().items()}
    try:
        yield threads
    finally:
        for thread in threads.values():
            thread.stop()


def refused(url: str, server: str, reason: str) -> float:
    text = httpx.get(f"{url}/metrics", timeout=10).text
    match = re.search(rf'^vecsim_{server}_refused_requests_total\{{reason="{reason}"\}} (\S+)$', text, re.M)
    return float(match.group(1)) if match else 0.0


def test_both_apps_carry_the_one_wiring():
    for name, app in both_apps().items():
        assert app.exception_handlers[RefusedError] is answer_refusal, name
        assert app.exception_handlers[RequestValidationError] is answer_validation_error, name
        # The token is checked before the body is read: the last middleware added runs first.
        assert [m.cls for m in app.user_middleware] == [BearerTokenMiddleware, BodyLimitMiddleware], name
        schema = app.openapi()
        assert {"/healthz", "/readyz", "/metrics"} <= set(schema["paths"]), name
        assert "vecsimToken" in schema["components"]["securitySchemes"], name


@pytest.mark.parametrize(
    ("reason", "status", "body", "headers"),
    [
        ("invalid_request", 422, b"{}", {"Authorization": f"Bearer {TOKEN}"}),
        ("body_too_large", 413, b"x" * (LIMIT + 1), {"Authorization": f"Bearer {TOKEN}"}),
        ("unauthorized", 401, b"{}", {}),
    ],
)
def test_both_servers_refuse_a_bad_request_alike(servers, reason, status, body, headers):
    answers = {}
    for server, thread in servers.items():
        before = refused(thread.url, server, reason)
        answer = httpx.put(
            f"{thread.url}{BODY_ROUTE[server]}",
            content=body,
            headers={"Content-Type": "application/json", **headers},
            timeout=10,
        )
        answers[server] = answer
        assert answer.status_code == status, (server, answer.text)
        assert refused(thread.url, server, reason) == before + 1, server
    shapes = {server: sorted(answer.json()) for server, answer in answers.items()}
    assert shapes["pod"] == shapes["controller"] == ["detail"]


def test_a_rejected_job_and_an_unknown_pod_are_answered_by_the_shared_handler(servers):
    url = servers["controller"].url
    auth = {"Authorization": f"Bearer {TOKEN}"}
    before = refused(url, "controller", "job_rejected")
    job = {"job_id": "w", "tasks": ["libero_10/10"], "group_size": 1, "num_stages": 1, "pods_per_stage": 1}
    answer = httpx.put(f"{url}/v1/job", json=job, headers=auth, timeout=10)
    assert answer.status_code == 422
    assert answer.json()["detail"].startswith("job 'w' rejected: ") and answer.json()["problems"]
    assert refused(url, "controller", "job_rejected") == before + 1
    heartbeat = {"url": "http://127.0.0.1:9", "generation": None, "assignment": None, "ready": False}
    unknown = httpx.post(f"{url}/v1/pods/sim-9/heartbeat", json=heartbeat, headers=auth, timeout=10)
    assert unknown.status_code == 404 and "'sim-9' is not registered" in unknown.json()["detail"]
