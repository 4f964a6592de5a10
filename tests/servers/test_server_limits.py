"""The pod and the controller against clients that send too much, too deep, or nothing at all.

Real ``vecsim pod`` and ``vecsim controller`` processes on loopback:

- JSON of any depth or size is a 400 naming the problem, never a 500;
- under a file-descriptor limit of 64 (``prlimit``), a flood of 80 sockets that send nothing,
  or a request head that never ends, does not lock out a health probe: such connections are
  closed after a bounded time, and a new one evicts the idlest when too many are open;
- a heartbeat cannot move a live pod to another URL (409); registering again can;
- an answer's head and body leave in one write, in order, and still before a close.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
from collections.abc import Iterator

import httpx
import pytest
from support.service_procs import Server, assignment_file, controller_server, pod_server, running, wait_until

from service.serving import COALESCE_MAX_BYTES, CoalescingWrites

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
    response = httpx.post(f"{pod.url}/v1/{op}", content=body, headers={"Content-Type": "application/json"}, timeout=30)
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


class _Recording:
    """The part of an ``asyncio.Transport`` that CoalescingWrites uses, recording its calls."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, bytes]] = []
        self.closing = False

    def write(self, data: bytes) -> None:
        self.calls.append(("write", bytes(data)))

    def close(self) -> None:
        self.closing = True
        self.calls.append(("close", b""))

    def abort(self) -> None:
        self.closing = True
        self.calls.append(("abort", b""))

    def is_closing(self) -> bool:
        return self.closing

    def get_write_buffer_size(self) -> int:
        return 0

    def get_extra_info(self, name: str, default: object = None) -> object:
        return {"peername": ("127.0.0.1", 1)}.get(name, default)


def test_one_loop_turn_of_writes_leaves_as_one_write_in_order():
    async def scenario() -> list[list[tuple[str, bytes]]]:
        inner = _Recording()
        writes = CoalescingWrites(inner, asyncio.get_running_loop())  # type: ignore[arg-type]
        seen = []
        writes.write(b"HTTP/1.1 200 OK\r\ncontent-length: 4\r\n\r\n")
        writes.write(bytearray(b"body"))
        seen.append(list(inner.calls))  # nothing yet: held until the turn ends
        assert writes.get_write_buffer_size() == 42
        await asyncio.sleep(0)
        seen.append(list(inner.calls))
        big = b"x" * (COALESCE_MAX_BYTES + 1)
        writes.write(b"head")
        writes.write(big)  # too big to hold: what is held goes first, then it, unjoined
        seen.append(list(inner.calls))
        writes.write(b"bye")
        writes.close()  # a close hands over what is held before closing
        seen.append(list(inner.calls))
        assert writes.get_extra_info("peername") == ("127.0.0.1", 1)
        await asyncio.sleep(0)
        return seen

    before, after_turn, after_big, after_close = asyncio.run(scenario())
    assert before == []
    assert after_turn == [("write", b"HTTP/1.1 200 OK\r\ncontent-length: 4\r\n\r\nbody")]
    assert after_big[1:] == [("write", b"head"), ("write", b"x" * (COALESCE_MAX_BYTES + 1))]
    assert after_close[3:] == [("write", b"bye"), ("close", b"")]


def test_an_abort_drops_what_is_held():
    async def scenario() -> list[tuple[str, bytes]]:
        inner = _Recording()
        writes = CoalescingWrites(inner, asyncio.get_running_loop())  # type: ignore[arg-type]
        writes.write(b"never sent")
        writes.abort()
        await asyncio.sleep(0)
        return inner.calls

    assert asyncio.run(scenario()) == [("abort", b"")]


def _exchange(url: str, data: bytes, until_closed: bool = False, expect: int = 1) -> bytes:
    """Send ``data`` on one raw connection to ``url``; read ``expect`` answers (or until EOF)."""
    host, port = url.removeprefix("http://").split(":")
    with socket.create_connection((host, int(port)), timeout=30) as sock:
        sock.sendall(data)
        got = b""
        while True:
            chunk = sock.recv(65536)
            if not chunk:
                return got
            got += chunk
            if not until_closed and got.count(b"HTTP/1.1 ") >= expect and _complete(got, expect):
                return got


def _complete(got: bytes, expect: int) -> bool:
    """Whether ``got`` holds ``expect`` whole answers with Content-Length bodies."""
    rest = got
    for _ in range(expect):
        head, sep, rest = rest.partition(b"\r\n\r\n")
        if not sep:
            return False
        length = next(
            (int(line.split(b":")[1]) for line in head.split(b"\r\n") if line.lower().startswith(b"content-length:")),
            0,
        )
        if len(rest) < length:
            return False
        rest = rest[length:]
    return True


def test_answers_on_one_kept_alive_connection_arrive_whole_and_in_order(pod):
    # Two requests sent back to back on one connection: two whole answers, the first one's.
    get = b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\nGET /v1/info HTTP/1.1\r\nHost: x\r\n\r\n"
    got = _exchange(pod.url, get, expect=2)
    first, second = got.split(b"HTTP/1.1 ")[1:]
    assert first.startswith(b"200") and b'"status"' in first
    assert second.startswith(b"200") and b'"pod":"sim-0"' in second


def test_a_malformed_request_is_answered_400_before_the_connection_closes(pod):
    # uvicorn writes its 400 and closes at once: the held answer must leave before the close.
    got = _exchange(pod.url, b"NOT A REQUEST\r\n\r\n", until_closed=True)
    assert got.startswith(b"HTTP/1.1 400"), got[:200]
