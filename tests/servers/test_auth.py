"""The shared token: who may change state on a pod and on the controller, and that nothing on the
wire is ever unpickled.

Real `vecsim pod` and `vecsim controller` processes on loopback, started with a token in
`VECSIM_TOKEN`; every state-changing endpoint is tried without the token, with a wrong one and
with the right one, and every reading endpoint without any.
"""

from __future__ import annotations

import ast
import importlib.util
import os
import re
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
import yaml
from support import ROOT
from support.service_procs import (
    Server,
    assignment_file,
    clean_env,
    controller_server,
    job_config,
    pod_server,
    post_wire,
    reset_body,
    running,
    step_body,
    wait_until,
)

from service.runner import LocalJob
from vecsim import wire
from vecsim.auth import authorization_problem, bearer_headers, tokens_match

TOKEN = "s3cret-token-for-tests_0123456789"
WRONG = "not-the-token-9876543210"
PENDULUM = "gym/Pendulum-v1"
POD_BODY_LIMIT = 64 * 1024
REPO = ROOT


def auth(token: str | None) -> dict[str, str]:
    return bearer_headers(token)


# -- the check itself (pure) -------------------------------------------------------------------


def test_tokens_match_only_when_equal():
    assert tokens_match(TOKEN, TOKEN)
    assert not tokens_match(TOKEN, TOKEN[:-1])
    assert not tokens_match(TOKEN, WRONG)


@pytest.mark.parametrize(
    ("header", "named"),
    [
        (None, "none was sent"),
        ("", "none was sent"),
        (f"Basic {TOKEN}", "form 'Bearer <token>'"),
        ("Bearer", "form 'Bearer <token>'"),
        (f"Bearer {WRONG}", "refused the bearer token"),
    ],
)
def test_a_request_without_the_right_bearer_token_is_told_what_is_wrong_never_the_token(header, named):
    problem = authorization_problem(header, TOKEN, "pod sim-0")
    assert problem is not None and named in problem and "pod sim-0" in problem
    assert TOKEN not in problem and WRONG not in problem


def test_with_no_token_configured_every_request_passes():
    assert authorization_problem(None, None, "pod sim-0") is None


# -- the pod -----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def pod(tmp_path_factory) -> Iterator[Server]:
    workdir = tmp_path_factory.mktemp("auth-pod")
    path = assignment_file(workdir, "sim-0", [(PENDULUM, 2)])
    args = ["--assignment", str(path), "--max-body-bytes", str(POD_BODY_LIMIT)]
    with running(pod_server("sim-0", workdir, args=args, token=TOKEN), ready=True) as server:
        yield server


def pod_request(pod: Server, endpoint: str, token: str | None) -> httpx.Response:
    """One request to a state-changing endpoint of the pod, valid in every other respect (the
    assignment is the pod's own, so with the token it changes nothing)."""
    if endpoint == "PUT /v1/assignment":
        own = Path(pod.argv[pod.argv.index("--assignment") + 1]).read_text()
        headers = {"Content-Type": "application/json", **auth(token)}
        return httpx.put(f"{pod.url}/v1/assignment", content=own, headers=headers, timeout=30)
    if endpoint == "POST /v1/reset":
        return post_wire(pod.url, "reset", reset_body(0, [0], [1]), token)
    return post_wire(pod.url, "step", step_body(0, [0], np.zeros((1, 1), np.float32)), token)


POD_STATE_CHANGES = ["PUT /v1/assignment", "POST /v1/reset", "POST /v1/step"]


@pytest.mark.parametrize("endpoint", POD_STATE_CHANGES)
def test_pod_refuses_a_state_change_without_the_token_with_401_naming_the_header(pod, endpoint):
    response = pod_request(pod, endpoint, None)
    assert response.status_code == 401
    assert "Authorization: Bearer" in response.json()["detail"] and "sim-0" in response.json()["detail"]
    assert response.headers["www-authenticate"].startswith("Bearer")


@pytest.mark.parametrize("endpoint", POD_STATE_CHANGES)
def test_pod_refuses_a_wrong_token_with_401_echoing_no_token(pod, endpoint):
    response = pod_request(pod, endpoint, WRONG)
    assert response.status_code == 401
    assert "refused the bearer token" in response.json()["detail"]
    assert TOKEN not in response.text and WRONG not in response.text


@pytest.mark.parametrize("endpoint", POD_STATE_CHANGES)
def test_pod_accepts_a_state_change_with_the_token(pod, endpoint):
    response = pod_request(pod, endpoint, TOKEN)
    assert response.status_code == 200, response.text


@pytest.mark.parametrize("path", ["/healthz", "/readyz", "/metrics", "/v1/info", "/openapi.json"])
def test_pod_health_metrics_and_info_stay_open(pod, path):
    assert httpx.get(f"{pod.url}{path}", timeout=10).status_code == 200


def test_a_frame_needs_no_token(pod):
    # This pod renders no camera: the refusal is about the camera, not about the token.
    response = httpx.get(f"{pod.url}/v1/envs/0/frame.png", timeout=10)
    assert response.status_code == 422 and "camera" in response.json()["detail"]


def test_a_refused_step_leaves_the_envs_as_they_were(pod):
    actions = np.array([[0.5], [-0.25]], np.float32)

    def reset_then_step(intruder: bool) -> dict[str, Any]:
        assert post_wire(pod.url, "reset", reset_body(0, [0, 1], [4, 7]), TOKEN).status_code == 200
        if intruder:
            refused = post_wire(pod.url, "step", step_body(0, [0, 1], np.ones((2, 1), np.float32)), None)
            assert refused.status_code == 401
        response = post_wire(pod.url, "step", step_body(0, [0, 1], actions), TOKEN)
        assert response.status_code == 200
        return wire.decode(response.content)

    after_intruder, reference = reset_then_step(intruder=True), reset_then_step(intruder=False)
    assert after_intruder["obs"].tobytes() == reference["obs"].tobytes()
    assert after_intruder["reward"].tobytes() == reference["reward"].tobytes()


def test_an_unauthenticated_body_is_refused_before_it_is_read(pod):
    oversized = b"\0" * (2 * POD_BODY_LIMIT)
    headers = {"Content-Type": wire.CONTENT_TYPE}
    anonymous = httpx.post(f"{pod.url}/v1/step", content=oversized, headers=headers, timeout=30)
    assert anonymous.status_code == 401
    signed = httpx.post(f"{pod.url}/v1/step", content=oversized, headers={**headers, **auth(TOKEN)}, timeout=30)
    assert signed.status_code == 413


def test_pod_counts_refused_requests_by_reason(pod):
    def refused() -> float:
        text = httpx.get(f"{pod.url}/metrics", timeout=10).text
        match = re.search(r'^vecsim_pod_refused_requests_total\{reason="unauthorized"\} (\S+)$', text, re.M)
        return float(match.group(1)) if match else 0.0

    before = refused()
    assert pod_request(pod, "POST /v1/step", None).status_code == 401
    assert refused() == before + 1


# -- the controller ----------------------------------------------------------------------------

JOB = {
    "job_id": "auth",
    "tasks": [PENDULUM],
    "group_size": 1,
    "num_stages": 1,
    "pods_per_stage": 1,
    "camera": {"names": []},
    "max_episode_steps": 20,
}
REGISTRATION = {"pod": "sim-7", "url": "http://127.0.0.1:9", "capacity": {"max_envs": 4, "gpu": False}}
HEARTBEAT = {"url": "http://127.0.0.1:9", "generation": None, "assignment": None, "ready": False}


@pytest.fixture(scope="module")
def controller(tmp_path_factory) -> Iterator[Server]:
    workdir = tmp_path_factory.mktemp("auth-controller")
    # A long TTL: the pod these tests register never heartbeats again, and must not expire mid-test.
    with running(controller_server(workdir, token=TOKEN, args=["--heartbeat-ttl", "600"])) as server:
        yield server


def controller_request(controller: Server, endpoint: str, token: str | None) -> httpx.Response:
    headers = auth(token)
    if endpoint == "POST /v1/pods":
        return httpx.post(f"{controller.url}/v1/pods", json=REGISTRATION, headers=headers, timeout=30)
    if endpoint == "POST /v1/pods/{pod}/heartbeat":
        return httpx.post(f"{controller.url}/v1/pods/sim-7/heartbeat", json=HEARTBEAT, headers=headers, timeout=30)
    return httpx.put(f"{controller.url}/v1/job", json=JOB, headers=headers, timeout=30)


CONTROLLER_STATE_CHANGES = ["POST /v1/pods", "POST /v1/pods/{pod}/heartbeat", "PUT /v1/job"]


@pytest.mark.parametrize("endpoint", CONTROLLER_STATE_CHANGES)
@pytest.mark.parametrize("token", [None, WRONG], ids=["no-token", "wrong-token"])
def test_controller_refuses_a_state_change_without_the_right_token(controller, endpoint, token):
    pods_before = httpx.get(f"{controller.url}/v1/pods", timeout=10).json()
    job_before = httpx.get(f"{controller.url}/v1/job", timeout=10).status_code
    response = controller_request(controller, endpoint, token)
    assert response.status_code == 401
    assert "the controller" in response.json()["detail"]
    assert TOKEN not in response.text and WRONG not in response.text
    assert httpx.get(f"{controller.url}/v1/pods", timeout=10).json() == pods_before
    assert httpx.get(f"{controller.url}/v1/job", timeout=10).status_code == job_before


def test_controller_accepts_registration_heartbeat_and_job_with_the_token(controller):
    for endpoint in CONTROLLER_STATE_CHANGES:
        response = controller_request(controller, endpoint, TOKEN)
        assert response.status_code == 200, f"{endpoint}: {response.text}"
    assert [p["pod"] for p in httpx.get(f"{controller.url}/v1/pods", timeout=10).json()] == ["sim-7"]


@pytest.mark.parametrize("path", ["/healthz", "/readyz", "/metrics", "/v1/pods", "/v1/job", "/v1/routing"])
def test_controller_health_metrics_and_reads_stay_open(controller, path):
    # /readyz, /v1/job and /v1/routing answer 404/503 while there is no job or plan; never 401.
    assert httpx.get(f"{controller.url}{path}", timeout=10).status_code in (200, 404, 503)


def test_controller_refuses_a_body_over_its_limit_with_413_and_changes_nothing(controller):
    pods_before = httpx.get(f"{controller.url}/v1/pods", timeout=10).json()
    huge = {**REGISTRATION, "pod": "sim-8", "url": "http://x/" + "a" * (2 * 1024 * 1024)}
    response = httpx.post(f"{controller.url}/v1/pods", json=huge, headers=auth(TOKEN), timeout=30)
    assert response.status_code == 413
    assert "the controller's limit" in response.json()["detail"]
    assert httpx.get(f"{controller.url}/v1/pods", timeout=10).json() == pods_before


@pytest.mark.parametrize("which", ["pod", "controller"])
def test_openapi_marks_every_state_changing_operation_as_needing_the_token(which, request):
    server = request.getfixturevalue(which)
    schema = httpx.get(f"{server.url}/openapi.json", timeout=10).json()
    scheme = schema["components"]["securitySchemes"]["vecsimToken"]
    assert (scheme["type"], scheme["scheme"]) == ("http", "bearer")
    for path, operations in schema["paths"].items():
        for method, operation in operations.items():
            guarded = "security" in operation
            assert guarded == (method.upper() not in ("GET", "HEAD")), f"{method.upper()} {path}"
            assert ("401" in operation["responses"]) == guarded


# -- wiring: the agent's heartbeats, the controller's pushes, the runner, without a token ------


@pytest.fixture(scope="module")
def guarded_job(tmp_path_factory) -> Iterator[dict[str, Any]]:
    """A controller and a pod sharing the token, and an intruder pod holding another."""
    workdir = tmp_path_factory.mktemp("auth-job")
    controller = controller_server(workdir, token=TOKEN, args=["--heartbeat-interval", "0.5"])
    with running(controller):
        member = pod_server(
            "sim-0", workdir, token=TOKEN, CONTROLLER_URL=controller.url, VECSIM_HEARTBEAT_INTERVAL_S="0.5"
        )
        intruder = pod_server(
            "sim-1", workdir, token=WRONG, CONTROLLER_URL=controller.url, VECSIM_HEARTBEAT_INTERVAL_S="0.5"
        )
        with running(member), running(intruder):
            assert httpx.put(f"{controller.url}/v1/job", json=JOB, headers=auth(TOKEN), timeout=30).status_code == 200
            yield {"controller": controller, "member": member, "intruder": intruder}


def test_a_pod_holding_the_token_registers_heartbeats_and_takes_its_pushed_assignment(guarded_job):
    controller = guarded_job["controller"]
    wait_until(lambda: controller.answers("/readyz"), "the job to be ready")
    table = httpx.get(f"{controller.url}/v1/routing", timeout=10).json()
    assert [p["pod"] for s in table["stages"] for p in s["pods"]] == ["sim-0"]
    assert guarded_job["member"].answers("/readyz")


def test_a_pod_holding_another_token_is_kept_out_of_the_registry(guarded_job):
    intruder, controller = guarded_job["intruder"], guarded_job["controller"]
    wait_until(lambda: "registration answered 401" in intruder.log_text(), "the intruder's refused registration")
    assert TOKEN not in intruder.log_text() and WRONG not in intruder.log_text()
    assert "sim-1" not in [p["pod"] for p in httpx.get(f"{controller.url}/v1/pods", timeout=10).json()]


def test_without_a_token_checking_is_off_and_both_servers_warn_at_start_up(tmp_path):
    controller = controller_server(tmp_path)
    pod = pod_server("sim-3", tmp_path)
    with running(controller), running(pod):
        spare = {"generation": 0, "pod": "sim-3", "stage_id": 0, "tasks": []}
        assert httpx.put(f"{pod.url}/v1/assignment", json=spare, timeout=30).status_code == 200
        assert httpx.post(f"{controller.url}/v1/pods", json=REGISTRATION, timeout=30).status_code == 200
        for server in (pod, controller):
            assert re.search(r"WARNING .*no VECSIM_TOKEN set", server.log_text()), server.name


@pytest.mark.parametrize("command", ["pod", "controller"])
def test_an_unusable_token_stops_the_server_at_start_naming_the_variable_not_the_token(command):
    bad = "two words"
    result = subprocess.run(
        [sys.executable, "-m", "service.cli", command, "--port", "9"],
        env=clean_env(VECSIM_TOKEN=bad),
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 2
    assert "VECSIM_TOKEN" in result.stderr and bad not in result.stderr


def test_each_local_job_makes_its_own_random_token_unless_given(tmp_path):
    config = job_config(JOB, replicas=1)

    def job(**kwargs: Any) -> LocalJob:
        return LocalJob(config, log_dir=tmp_path, **kwargs)

    first, second = job(env={"VECSIM_TOKEN": ""}), job(env={"VECSIM_TOKEN": ""})
    assert first.token != second.token and len(first.token) >= 32
    assert job(token=TOKEN).token == TOKEN
    assert job(env={"VECSIM_TOKEN": WRONG}).token == WRONG


@pytest.mark.slow
def test_a_local_job_hands_its_token_to_every_process_and_guards_them_all(tmp_path):
    job = LocalJob(job_config(JOB, replicas=1), log_dir=tmp_path, grace_s=10, env={"VECSIM_TOKEN": ""})
    with job:
        # Ready means the runner's PUT /v1/job, the pod's registration and heartbeats and the
        # controller's push all carried the job's token.
        table = job.wait_ready(timeout=180)
        pod_url = table.stages[0].pods[0].url
        body = reset_body(table.generation, [0], [2])
        assert post_wire(pod_url, "reset", body, None).status_code == 401
        assert post_wire(pod_url, "reset", body, job.token).status_code == 200
        assert httpx.put(f"{job.controller_url}/v1/job", json=JOB, timeout=30).status_code == 401
        assert (
            httpx.put(f"{job.controller_url}/v1/job", json=JOB, headers=auth(job.token), timeout=30).status_code == 200
        )


# -- nothing on the wire is unpickled ------------------------------------------------------------

# Modules that unpickle (or run code while loading) whatever bytes they are given.
UNPICKLERS = {"pickle", "_pickle", "cPickle", "cloudpickle", "dill", "shelve", "marshal", "joblib", "jsonpickle"}
# Calls that unpickle: torch.load (pickle underneath), pandas.read_pickle.
UNPICKLING_CALLS = {"torch.load", "pd.read_pickle", "pandas.read_pickle"}
# The one unpickling load vecsim reaches: LIBERO's own init states, read from files inside the
# installed package (vecsim.engine.tasks._libero points LIBERO's config at them), never from the network.
ALLOWED = {("libero/benchmark/__init__.py", "get_task_init_states", "torch.load")}


def unpickling_uses(path: Path, root: Path) -> set[tuple[str, str, str]]:
    """Every import of an unpickling module and unpickling call in ``path``: (file, function, what)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    found: set[tuple[str, str, str]] = set()
    where = str(path.relative_to(root))

    def visit(node: ast.AST, function: str) -> None:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            function = node.name
        if isinstance(node, ast.Import):
            found.update(
                (where, function, f"import {a.name}") for a in node.names if a.name.split(".")[0] in UNPICKLERS
            )
        elif isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] in UNPICKLERS:
            found.add((where, function, f"from {node.module} import"))
        elif isinstance(node, ast.Call):
            name = ast.unparse(node.func)
            if name in UNPICKLING_CALLS:
                found.add((where, function, name))
            for keyword in node.keywords:
                if keyword.arg == "allow_pickle" and not (
                    isinstance(keyword.value, ast.Constant) and keyword.value.value is False
                ):
                    found.add((where, function, f"{name}(allow_pickle=...)"))
        for child in ast.iter_child_nodes(node):
            visit(child, function)

    visit(tree, "<module>")
    return found


def test_no_module_of_vecsim_or_service_unpickles_anything():
    uses = set()
    for package in ("vecsim", "service"):
        for path in sorted((REPO / package).rglob("*.py")):
            uses |= unpickling_uses(path, REPO)
    assert uses == set()


def test_the_one_allowed_unpickling_load_is_libero_reading_its_own_init_state_files():
    spec = importlib.util.find_spec("libero")
    if spec is None or not spec.submodule_search_locations:
        pytest.skip("LIBERO is not installed")
    root = Path(next(iter(spec.submodule_search_locations)))
    assert unpickling_uses(root / "libero" / "benchmark" / "__init__.py", root) == ALLOWED
    libero_glue = (REPO / "vecsim" / "engine" / "tasks" / "_libero.py").read_text()
    assert '"init_states": str(package_dir / "init_files")' in libero_glue


@pytest.mark.slow
def test_vecsim_up_without_a_token_writes_the_one_it_made_to_a_file_only_its_owner_reads(tmp_path):
    config = job_config(JOB, replicas=1)
    path = tmp_path / "job.yaml"
    path.write_text(yaml.safe_dump(config.model_dump(mode="json")))
    logs = tmp_path / "logs"
    runner = subprocess.Popen(
        [sys.executable, "-m", "service.cli", "up", "-c", str(path), "--log-dir", str(logs), "--grace", "10"],
        env=clean_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    try:
        token_file = logs / "token"
        wait_until(lambda: token_file.exists() and token_file.read_text().strip(), "vecsim up to write its token")
        assert token_file.stat().st_mode & 0o777 == 0o600
        token = token_file.read_text().strip()
        controller_url = f"http://127.0.0.1:{config.controller.port}"

        def ready() -> bool:
            try:
                return httpx.get(f"{controller_url}/readyz", timeout=5).status_code == 200
            except httpx.TransportError:
                return False

        wait_until(ready, "the job ready")
        assert httpx.put(f"{controller_url}/v1/job", json=JOB, headers=auth(token), timeout=30).status_code == 200
        assert httpx.put(f"{controller_url}/v1/job", json=JOB, timeout=30).status_code == 401
    finally:
        runner.send_signal(signal.SIGINT)
        try:
            output, _ = runner.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            os.killpg(runner.pid, signal.SIGKILL)
            output, _ = runner.communicate(timeout=30)
    assert f"export VECSIM_TOKEN=$(cat {token_file})".encode() in output
    assert token.encode() not in output


def test_a_token_ending_in_a_newline_is_refused_naming_the_variable():
    # What `kubectl create secret --from-file` of a file ending in a newline holds.
    from vecsim.auth import check_token

    with pytest.raises(ValueError, match="VECSIM_TOKEN"):
        check_token("s3cret\n")
