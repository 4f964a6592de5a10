"""The pod and the controller against clients that send too much, too deep, or nothing at all.

Real ``vecsim pod`` and ``vecsim controller`` processes on loopback:

- JSON of any depth or size is a 400 naming the problem, never a 500;
- under a file-descriptor limit of 64 (``prlimit``), a flood of 80 sockets that send nothing,
  or a request head that never ends, does not lock out a health probe: such connections are
  closed after a bounded time, and a new one evicts the idlest when too many are open;
- a heartbeat cannot move a live pod to another URL (409); registering again can.
"""

from __future__ import annotations

import contextlib
import socket
from collections.abc import Iterator

import httpx
import pytest
from service_procs import Server, assignment_file, controller_server, pod_server, running, wait_until

PENDULUM = "gym/Pendulum-v1"
FD_LIMIT = ("prlimit", "--nofile=64:64", "--")
FAST_TIMEOUTS = {"VECSIM_HEADER_TIMEOUT_S": "1", "VECSIM_KEEP_ALIVE_S": "1"}


def nested(depth: int, leaf: str = "0") -> str:
    return "[" * depth + leaf + "]" * depth


@pytest.fixture(scope="module")
def pod(tmp_path_factory) -> Iterator[Server]:
    workdir = tmp_path_factory.mktemp("limits")
    path = assignment_file(workdir, "sim-0", [(PENDULUM, 1)], stage_id=0)
    with running(pod_server("sim-0", workdir, args=["--assignment", str(path)]), ready=True) as server:
        yield server


@pytest.mark.parametrize(
    ("op", "body"),
    [
        ("reset", '{"generation": 0, "env_indices": %s, "state_ids": [0]}' % nested(100_000)),
        ("step", '{"generation": 0, "env_indices": %s, "actions": [[0.0]]}' % nested(100_000)),
        ("step", '{"generation": 0, "env_indices": [0], "actions": %s}' % nested(700, "0.0")),
        ("reset", '{"generation": %s, "env_indices": [0], "state_ids": [0]}' % ("9" * 5000)),
        ("step", '{"generation": %s, "env_indices": [0], "actions": [[0.0]]}' % ("9" * 5000)),
    ],
    ids=[
        "reset-env_indices-100000-deep",
        "step-env_indices-100000-deep",
        "step-actions-700-deep",
        "reset-generation-5000-digits",
        "step-generation-5000-digits",
    ],
)
def test_json_too_deep_or_too_long_is_a_400_naming_it(pod, op, body):
    response = httpx.post(
        f"{pod.url}/v1/{op}", content=body, headers={"Content-Type": "application/json"}, timeout=30
    )
    assert response.status_code == 400, response.text[:300]
    assert "JSON" in response.json()["detail"] or "request" in response.json()["detail"]
    assert pod.answers("/readyz")


def test_json_nested_deeply_is_a_4xx_at_the_controller(tmp_path):
    with running(controller_server(tmp_path)) as controller:
        body = '{"pod": "sim-0", "url": "http://127.0.0.1:1", "capacity": %s}' % nested(100_000)
        response = httpx.post(
            f"{controller.url}/v1/pods", content=body, headers={"Content-Type": "application/json"}, timeout=30
        )
    assert 400 <= response.status_code < 500


@contextlib.contextmanager
def idle_sockets(url: str, n: int, first_bytes: bytes = b"") -> Iterator[list[socket.socket]]:
    """``n`` connections to ``url`` that send ``first_bytes`` (maybe nothing) and then nothing."""
    host, port = url.removeprefix("http://").split(":")
    held = []
    try:
        for _ in range(n):
            sock = socket.socket()
            sock.setblocking(False)
            with contextlib.suppress(BlockingIOError):
                sock.connect((host, int(port)))
            held.append(sock)
        if first_bytes:
            for sock in held:
                with contextlib.suppress(OSError):
                    sock.setblocking(True)
                    sock.settimeout(5)
                    sock.sendall(first_bytes)
        yield held
    finally:
        for sock in held:
            sock.close()


def probe_answers(url: str) -> bool:
    try:
        return httpx.get(f"{url}/healthz", timeout=3).status_code == 200
    except httpx.TransportError:
        return False


def limited(which: str, tmp_path) -> Server:
    """A pod (no envs) or a controller, under the fd limit, with a header timeout of 1 s."""
    if which == "pod":
        return pod_server("sim-9", tmp_path, wrap=FD_LIMIT, **FAST_TIMEOUTS)
    server = controller_server(tmp_path, args=["--header-timeout", "1"])
    server.argv = [*FD_LIMIT, *server.argv]
    return server


@pytest.mark.parametrize("which", ["pod", "controller"])
@pytest.mark.parametrize("first_bytes", [b"", b"GET /healthz HTTP/1.1\r\nHost: x\r\n"], ids=["silent", "endless-head"])
def test_a_flood_of_silent_connections_does_not_lock_out_health_probes(tmp_path, which, first_bytes):
    server = limited(which, tmp_path)
    with running(server), idle_sockets(server.url, 80, first_bytes):
        # Bounded: the silent connections are closed after the header timeout, and each new one
        # evicts the idlest; on a server that keeps them, the probe never gets in.
        assert wait_until(lambda: probe_answers(server.url), "a health probe through the flood", timeout_s=60)


def test_a_connection_whose_request_head_never_ends_is_closed(tmp_path):
    server = pod_server("sim-9", tmp_path, **FAST_TIMEOUTS)
    with running(server), idle_sockets(server.url, 1, b"GET /healthz HTTP/1.1\r\nHost: x\r\n") as (sock,):
        sock.settimeout(60)  # bounded: a server that keeps it makes recv raise TimeoutError
        assert sock.recv(1024) == b""


def test_a_heartbeat_cannot_move_a_live_pod_to_another_url_but_registering_again_can(tmp_path):
    with running(controller_server(tmp_path)) as controller:
        api = f"{controller.url}/v1/pods"
        assert httpx.post(api, json={"pod": "sim-0", "url": "http://10.0.0.1:8100"}, timeout=10).status_code == 200
        moved = httpx.post(f"{api}/sim-0/heartbeat", json={"url": "http://10.6.6.6:8100", "ready": True}, timeout=10)
        still = httpx.get(api, timeout=10).json()
        again = httpx.post(api, json={"pod": "sim-0", "url": "http://10.0.0.2:8100"}, timeout=10)
        after = httpx.get(api, timeout=10).json()
    assert moved.status_code == 409 and "http://10.0.0.1:8100" in moved.json()["detail"]
    assert [p["url"] for p in still] == ["http://10.0.0.1:8100"]
    assert again.status_code == 200 and [p["url"] for p in after] == ["http://10.0.0.2:8100"]
