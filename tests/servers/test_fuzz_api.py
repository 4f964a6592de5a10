"""Bad input: schemathesis against the pod's and the controller's OpenAPI schemas.

Every operation of each schema gets a bounded number of generated requests, schema-conforming
and schema-violating alike, sent with the job's token to real uvicorn servers on loopback.
Every answer must be below 500, and every refusal a 4xx whose JSON ``detail`` says what is
wrong. State must change only through accepted requests:

- pod: two identical `vecsim pod` processes; the target takes every generated request, the
  reference only the ones the target accepted, replayed byte for byte. Afterwards both are
  stepped alike: any env a refused request touched would answer differently. An accepted reset
  with a null seed is the env's own unseeded reset, random on each pod by design: the envs it
  reset are put in one fixed state on both pods before the comparison.
- controller: afterwards its registry holds exactly the pods whose registration was accepted
  and its job is the last one accepted.
"""

from __future__ import annotations

import contextlib
import json
import secrets
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import httpx
import numpy as np
import pytest
import schemathesis
import uvicorn
from hypothesis import HealthCheck, given, settings
from schemathesis import GenerationMode
from support.service_procs import assignment_file, free_port, pod_server, post_wire, running, step_body, wait_until

from service.controller import ControllerSettings, create_app
from vecsim import wire
from vecsim.auth import bearer_headers
from vecsim.config import CameraConfig

# 200 generated requests an operation against a real pod and controller, and later tests
# read what the fuzzing left: the module is slow as a whole.
pytestmark = pytest.mark.slow

# Runtime values, not literals: Hypothesis draws from constants it finds in local source, and a
# request that names the right pod and generation by luck would change state legitimately.
TOKEN = secrets.token_urlsafe(24)
POD_NAME = f"fz-{secrets.token_hex(4)}"
TASKS = [("gym/HalfCheetah-v5", 1), ("gym/Walker2d-v5", 1)]
NUM_ENVS = 2
ACTION_DIM = 6
CAMERA = CameraConfig(names=("render",), height=8, width=8)
EXAMPLES_PER_OPERATION = 200

POD_OPERATIONS = [
    "GET /healthz",
    "GET /readyz",
    "GET /v1/info",
    "PUT /v1/assignment",
    "POST /v1/reset",
    "POST /v1/step",
    "POST /v1/get_attr",
    "POST /v1/call",
    "POST /v1/set_attr",
    "GET /v1/envs/{env_index}/frame.png",
    "GET /metrics",
]
CONTROLLER_OPERATIONS = [
    "POST /v1/pods",
    "GET /v1/pods",
    "POST /v1/pods/{pod}/heartbeat",
    "PUT /v1/job",
    "GET /v1/job",
    "GET /v1/routing",
    "GET /healthz",
    "GET /readyz",
    "GET /metrics",
]

# The wire body is declared as binary: send what Hypothesis generates as it is.
schemathesis.serializer.alias(wire.CONTENT_TYPE, "application/octet-stream")


def fuzz(operation: Any, send: Any) -> None:
    """Send ``EXAMPLES_PER_OPERATION`` generated requests (valid and invalid) through ``send``."""
    strategy = operation.as_strategy(GenerationMode.POSITIVE) | operation.as_strategy(GenerationMode.NEGATIVE)

    @settings(
        max_examples=EXAMPLES_PER_OPERATION,
        deadline=None,
        database=None,
        derandomize=True,
        suppress_health_check=list(HealthCheck),
    )
    @given(case=strategy)
    def run(case: Any) -> None:
        send(case)

    run()


# Answers that report a state, not a failure: the controller is not ready before a job is planned.
NOT_READY_ANSWERS = {"GET /readyz", "GET /v1/routing"}


def check_answer(label: str, response: Any, not_ready_ok: bool = False) -> None:
    """No 5xx (but a documented 503 "not ready" where ``not_ready_ok``); a refusal is a 4xx with
    a JSON ``detail`` message; 401 exactly when a state-changing request went out without the
    token (schemathesis' negative cases drop it)."""
    request = response.request
    sent = f"{label}: {request.method} {request.url} body {str(request.body)[:300]}"
    failed = response.status_code >= 500 and not (not_ready_ok and response.status_code == 503)
    assert not failed, f"{sent} -> {response.status_code} {response.content[:500]!r}"
    signed = request.headers.get("Authorization") == bearer_headers(TOKEN)["Authorization"]
    guarded = request.method.upper() not in ("GET", "HEAD")
    assert (response.status_code == 401) == (guarded and not signed), f"{sent} -> {response.status_code}"
    if response.status_code >= 400:
        detail = response.json().get("detail")
        assert isinstance(detail, str) and detail, f"{sent} -> {response.status_code} without a detail message"


def operation_of(schema: Any, label: str) -> Any:
    method, path = label.split(" ", 1)
    return schema[path][method]


def labels_of(schema: Any) -> set[str]:
    return {f"{op.method.upper()} {op.path}" for op in (result.ok() for result in schema.get_all_operations())}


# -- the pod -------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def pods(tmp_path_factory) -> Iterator[dict[str, Any]]:
    """Target and reference: the same standalone assignment, the same name, the token."""
    workdir: Path = tmp_path_factory.mktemp("fuzz-pods")
    path = assignment_file(workdir, POD_NAME, TASKS, camera=CAMERA)
    target = pod_server(POD_NAME, workdir / "target", args=["--assignment", str(path)], token=TOKEN)
    reference = pod_server(POD_NAME, workdir / "reference", args=["--assignment", str(path)], token=TOKEN)
    with running(target, ready=True), running(reference, ready=True):
        schema = schemathesis.openapi.from_url(f"{target.url}/openapi.json")
        yield {"target": target, "reference": reference, "schema": schema, "unseeded": set()}


def unseeded_envs(request: Any) -> list[int]:
    """The env ids an accepted JSON reset reset without a seed (nothing for any other request)."""
    if not str(request.url).endswith("/v1/reset") or "json" not in request.headers.get("content-type", ""):
        return []
    body = json.loads(request.body)
    seeds = body.get("seeds")
    if not isinstance(seeds, list):
        return []
    return [env for env, seed in zip(body["env_indices"], seeds) if seed is None]


def test_the_pod_operations_fuzzed_are_every_operation_of_its_schema(pods):
    assert labels_of(pods["schema"]) == set(POD_OPERATIONS)


@pytest.mark.parametrize("label", POD_OPERATIONS)
def test_fuzzed_requests_to_the_pod_get_no_5xx_and_refusals_say_why(pods, label):
    target, reference = pods["target"], pods["reference"]
    auth = bearer_headers(TOKEN)

    def send(case: Any) -> None:
        response = case.call(base_url=target.url, headers=auth, timeout=60)
        check_answer(label, response)
        if response.status_code < 300 and case.method.upper() != "GET":
            request = response.request
            parts = urlsplit(request.url)
            replay = httpx.request(
                request.method,
                f"{reference.url}{parts.path}{'?' + parts.query if parts.query else ''}",
                content=request.body or b"",
                headers={k: v for k, v in request.headers.items() if k.lower() not in ("host", "content-length")},
                timeout=60,
            )
            assert replay.status_code == response.status_code, f"the reference answered {replay.status_code}"
            pods["unseeded"].update(unseeded_envs(request))

    fuzz(operation_of(pods["schema"], label), send)


def test_after_the_fuzzing_every_env_is_where_the_accepted_requests_left_it(pods):
    # Named so that it runs after the fuzzing above (pytest keeps the file's order).
    target, reference = pods["target"], pods["reference"]
    for server in (target, reference):
        wait_until(lambda s=server: s.answers("/readyz"), f"{server.name} ready again")
    generations = [httpx.get(f"{s.url}/v1/info", timeout=10).json()["generation"] for s in (target, reference)]
    assert generations[0] == generations[1]
    if pods["unseeded"]:
        envs = sorted(pods["unseeded"])
        body = {"generation": generations[0], "env_indices": np.array(envs), "state_ids": np.zeros(len(envs), np.int64)}
        assert [post_wire(s.url, "reset", body, TOKEN).status_code for s in (target, reference)] == [200, 200]
    rng = np.random.default_rng(7)
    for _ in range(3):
        actions = rng.uniform(-1, 1, size=(NUM_ENVS, ACTION_DIM)).astype(np.float32)
        body = step_body(generations[0], list(range(NUM_ENVS)), actions)
        answers = [post_wire(s.url, "step", body, TOKEN) for s in (target, reference)]
        assert [a.status_code for a in answers] == [200, 200], answers[0].text
        mine, theirs = (wire.decode(a.content) for a in answers)
        for key in ("reward", "terminated", "truncated"):
            assert mine[key].tobytes() == theirs[key].tobytes(), key
        assert mine["obs"]["proprio"].tobytes() == theirs["obs"]["proprio"].tobytes()
        assert mine["obs"]["images"]["render"].tobytes() == theirs["obs"]["images"]["render"].tobytes()


# -- the controller ------------------------------------------------------------------------------


@contextlib.contextmanager
def serve_controller() -> Iterator[str]:
    """The controller app under uvicorn on loopback, in a thread of this process.

    Without its reconcile loop: fuzzed registrations name arbitrary URLs, and the loop would push
    assignments to them, off loopback. Everything else is the served app.
    """
    settings = ControllerSettings(token=TOKEN, heartbeat_ttl_s=3600.0)
    port = free_port()
    server = uvicorn.Server(
        uvicorn.Config(create_app(settings, reconcile=False), host="127.0.0.1", port=port, log_level="warning")
    )
    thread = threading.Thread(target=server.run, name="fuzz-controller", daemon=True)
    thread.start()
    try:
        wait_until(lambda: server.started, "the controller to serve", timeout_s=60)
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(timeout=30)


@pytest.fixture(scope="module")
def controller() -> Iterator[dict[str, Any]]:
    with serve_controller() as url:
        schema = schemathesis.openapi.from_url(f"{url}/openapi.json")
        yield {"url": url, "schema": schema, "registered": set(), "job": None}


def test_the_controller_operations_fuzzed_are_every_operation_of_its_schema(controller):
    assert labels_of(controller["schema"]) == set(CONTROLLER_OPERATIONS)


@pytest.mark.parametrize("label", CONTROLLER_OPERATIONS)
def test_fuzzed_requests_to_the_controller_get_no_5xx_and_refusals_say_why(controller, label):
    auth = bearer_headers(TOKEN)

    def send(case: Any) -> None:
        response = case.call(base_url=controller["url"], headers=auth, timeout=60)
        check_answer(label, response, not_ready_ok=label in NOT_READY_ANSWERS)
        if response.status_code == 200 and label == "POST /v1/pods":
            controller["registered"].add(response.json()["pod"])
        if response.status_code == 200 and label == "PUT /v1/job":
            controller["job"] = response.json()

    fuzz(operation_of(controller["schema"], label), send)


def test_after_the_fuzzing_the_controller_holds_only_what_it_accepted(controller):
    pods = httpx.get(f"{controller['url']}/v1/pods", timeout=10).json()
    assert {p["pod"] for p in pods} == controller["registered"]
    job = httpx.get(f"{controller['url']}/v1/job", timeout=10)
    if controller["job"] is None:
        assert job.status_code == 404
    else:
        assert job.json() == controller["job"]
