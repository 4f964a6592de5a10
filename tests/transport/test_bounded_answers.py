"""Every part of an answer is bounded, on the trainer's side and the controller's: scripted
hostile peers on loopback send endless trailers, an endless chunk extension or a body a byte per
chunk, and each costs the reader what it read up to a cap, then the connection goes.

The peers are raw sockets in a thread of the test process. Each offers far more than any cap
(up to ``OFFER`` bytes) and stops by itself once the reader hangs up. The tests assert on the
counts the reader says it read, on the memory the reading took (``tracemalloc``), on the peer
seeing the reader hang up, and, for the controller, on its stall guard: never on wall time.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import re
import socket
import threading
import tracemalloc
from collections.abc import Iterator
from dataclasses import dataclass, field

import httpx
import numpy as np
import pytest
from support.controller_in_process import JOB
from support.service_procs import AppThread, loopback_socket, raw_server, socket_server, wait_until

from service.controller import ControllerSettings, create_app
from service.pod.app import create_app as create_pod_app
from service.pod.settings import PodSettings
from vecsim.client import PodRequestError
from vecsim.client.pods import PodConnection
from vecsim.transport import (
    MAX_CHUNKS,
    MAX_FRAMING_BYTES,
    MAX_HEAD_BYTES,
    HttptoolsTransport,
    get_answer,
    make_async_client,
    make_transport,
    read_answer,
)

# What a peer offers at most: far past every cap; a peer that sends it all was never cut off.
OFFER = 64 << 20
# What one read of asyncio's sockets takes at most: reading stops within one read past a cap.
READ_BYTES = 256 << 10
CHUNKED_HEAD = b"HTTP/1.1 200 OK\r\nContent-Type: application/octet-stream\r\nTransfer-Encoding: chunked\r\n\r\n"


def endless_trailers() -> Iterator[bytes]:
    yield CHUNKED_HEAD + b"2\r\nok\r\n0\r\n"
    for n in range(OFFER):
        yield b"X-Trailer-%d: %s\r\n" % (n, b"t" * 1000)


def one_endless_trailer() -> Iterator[bytes]:
    yield CHUNKED_HEAD + b"2\r\nok\r\n0\r\nX-Trailer: "
    while True:
        yield b"t" * 1000


def endless_chunk_extension() -> Iterator[bytes]:
    yield CHUNKED_HEAD + b"2;ext="
    while True:
        yield b"e" * 1000


def tiny_chunks() -> Iterator[bytes]:
    yield CHUNKED_HEAD
    while True:
        yield b"1\r\nx\r\n" * 200


PEERS = {
    "endless-trailers": endless_trailers,
    "one-endless-trailer": one_endless_trailer,
    "endless-chunk-extension": endless_chunk_extension,
    "many-tiny-chunks": tiny_chunks,
}
# What the reader's error says for each, and the count it reports read.
REFUSALS = {
    "endless-trailers": r"chunk extensions and trailers are larger than \d+ bytes \((\d+) bytes of head and framing read\)",
    "one-endless-trailer": r"chunk extensions and trailers are larger than \d+ bytes \((\d+) bytes of head and framing read\)",
    "endless-chunk-extension": r"chunk extensions and trailers are larger than \d+ bytes \((\d+) bytes of head and framing read\)",
    "many-tiny-chunks": rf"more than {MAX_CHUNKS} chunks \((\d+) bytes of body in them\)",
}
# The most that may be read of each before the reader stops.
BOUNDS = {
    "endless-trailers": MAX_HEAD_BYTES + MAX_FRAMING_BYTES + READ_BYTES,
    "one-endless-trailer": MAX_HEAD_BYTES + MAX_FRAMING_BYTES + READ_BYTES,
    "endless-chunk-extension": MAX_HEAD_BYTES + MAX_FRAMING_BYTES + READ_BYTES,
    "many-tiny-chunks": MAX_CHUNKS,
}


@dataclass
class Peer:
    """What a hostile peer saw: per connection, the bytes it sent and whether the reader hung up."""

    url: str = ""
    sent: list[int] = field(default_factory=list)
    hung_up: list[bool] = field(default_factory=list)


@contextlib.contextmanager
def hostile_peer(kind: str) -> Iterator[Peer]:
    """A loopback server that reads a request's head and body (a Content-Length's worth) and
    answers with ``PEERS[kind]`` until the reader hangs up or ``OFFER`` bytes are sent."""
    peer = Peer()

    def answer(conn: socket.socket, _number: int) -> None:
        request = conn.recv(65536)
        head, _, body = request.partition(b"\r\n\r\n")
        length = re.search(rb"(?i)\r\ncontent-length: *(\d+)", head)
        while length is not None and len(body) < int(length.group(1)):
            more = conn.recv(65536)
            if not more:
                break
            body += more
        sent, hung_up = 0, False
        try:
            for piece in PEERS[kind]():
                conn.sendall(piece)
                sent += len(piece)
                if sent >= OFFER:
                    break
        except (BrokenPipeError, ConnectionResetError):
            hung_up = True  # not a reader that merely stopped reading: that is a timeout here
        finally:
            peer.sent.append(sent)
            peer.hung_up.append(hung_up)

    with socket_server(answer) as url:
        peer.url = url
        yield peer


def read_count(kind: str, error: BaseException) -> int:
    """The count the reader's error says it read, checking that the error names its cap."""
    found = re.search(REFUSALS[kind], str(error))
    assert found, f"{kind}: {error}"
    return int(found.group(1))


def fetch_traced(url: str, lean: bool) -> tuple[BaseException, int]:
    """GET ``url`` through vecsim's transport (``lean``: ``Transport.fetch``, as the client asks a
    pod; else an ``httpx.AsyncClient`` on it, as the controller pushes); return the error raised and
    the peak of memory traced while reading."""

    async def main() -> None:
        if lean:
            async with make_transport() as transport:
                await transport.fetch("GET", url, (), b"", 64 << 20)
        else:
            async with make_async_client() as client:
                await read_answer(await client.send(client.build_request("GET", url), stream=True), 64 << 20)

    tracemalloc.start()
    try:
        with pytest.raises(httpx.RemoteProtocolError) as caught:
            asyncio.run(main())
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    return caught.value, peak


@pytest.mark.parametrize("lean", [True, False], ids=["fetch", "httpx-client"])
@pytest.mark.parametrize("kind", list(PEERS))
def test_a_hostile_answer_costs_what_was_read_up_to_its_cap(kind: str, lean: bool) -> None:
    with hostile_peer(kind) as peer:
        error, peak = fetch_traced(f"{peer.url}/", lean)
        wait_until(lambda: len(peer.sent) == 1, "the peer to end its answer", 10)
    assert read_count(kind, error) <= BOUNDS[kind]
    assert peer.hung_up == [True] and peer.sent[0] < OFFER  # reading stopped: the reader hung up
    # Bounded memory: the caps' worth and a read buffer, not the megabytes offered (one endless
    # trailer cost 240 MB here before its cap).
    assert peak < 4 * READ_BYTES + 2 * (MAX_HEAD_BYTES + MAX_FRAMING_BYTES) + 64 * MAX_CHUNKS


@pytest.mark.parametrize("in_a_loop", [False, True], ids=["blocking", "inside-a-running-loop"])
def test_the_control_planes_blocking_get_is_capped_alike(in_a_loop: bool) -> None:
    """``get_answer`` (the routing table before a client runs, a pod's ``/v1/info``) takes the
    transport's path, from a blocking caller or from inside a running event loop."""

    async def inside(url: str) -> None:
        get_answer(url, timeout_s=30)

    with hostile_peer("one-endless-trailer") as peer, pytest.raises(httpx.RemoteProtocolError) as caught:
        if in_a_loop:
            asyncio.run(inside(f"{peer.url}/v1/routing"))
        else:
            get_answer(f"{peer.url}/v1/routing", timeout_s=30)
    assert f"GET {peer.url}/v1/routing" in str(caught.value)
    assert read_count("one-endless-trailer", caught.value) <= BOUNDS["one-endless-trailer"]


async def fetch_once(url: str) -> tuple[int, bytes]:
    """``GET url`` once through a fresh transport, answers up to 64 MiB."""
    async with make_transport() as transport:
        return await transport.fetch("GET", url, (), b"", 64 << 20)


def test_a_chunked_answer_with_extensions_and_trailers_under_the_caps_arrives_whole() -> None:
    pieces = [bytes([i % 256]) * 4000 for i in range(1000)]
    body = b"".join(b"%x;n=%d\r\n%s\r\n" % (len(p), i, p) for i, p in enumerate(pieces))
    reply = CHUNKED_HEAD + body + b"0\r\nX-Checksum: abc\r\nX-Other: " + b"o" * 1000 + b"\r\n\r\n"
    with raw_server(reply) as url:
        assert asyncio.run(fetch_once(f"{url}/")) == (200, b"".join(pieces))


@pytest.mark.parametrize("chunks", [MAX_CHUNKS, MAX_CHUNKS + 1])
def test_an_answer_of_max_chunks_arrives_and_one_more_is_refused(chunks: int) -> None:
    reply = CHUNKED_HEAD + b"1\r\nx\r\n" * chunks + b"0\r\n\r\n"
    with raw_server(reply) as url:
        if chunks <= MAX_CHUNKS:
            assert asyncio.run(fetch_once(f"{url}/")) == (200, b"x" * chunks)
        else:
            with pytest.raises(httpx.RemoteProtocolError, match=f"more than {MAX_CHUNKS} chunks"):
                asyncio.run(fetch_once(f"{url}/"))


@pytest.mark.parametrize("lean", [True, False], ids=["fetch", "httpx-client"])
def test_junk_after_a_whole_answer_leaves_the_answer_and_drops_the_connection(lean: bool) -> None:
    """Bytes after an answer, in the same read, are no answer to the next request: that one goes
    on a new connection, and each gets its own answer."""
    requests_per_connection: list[int] = []

    def answer(conn: socket.socket, number: int) -> None:
        count = 0
        while conn.recv(65536):
            count += 1
            conn.sendall(b"HTTP/1.1 200 OK\r\nContent-Length: 1\r\n\r\n%dHTTP/1.1 500 Junk\r\n\r\n" % number)
        requests_per_connection.append(count)

    async def main(url: str) -> list[bytes]:
        transport = HttptoolsTransport()
        try:
            if lean:
                return [(await transport.fetch("GET", url, (), b"", 1 << 20))[1] for _ in range(2)]
            async with make_async_client(transport) as client:
                return [(await client.get(url)).content for _ in range(2)]
        finally:
            await transport.aclose()

    with socket_server(answer) as url:
        assert asyncio.run(main(f"{url}/")) == [b"1", b"2"]
        wait_until(lambda: len(requests_per_connection) == 2, "both connections to end", 10)
    assert requests_per_connection == [1, 1]


def test_an_early_413_reaches_the_client_as_a_refusal_not_an_outage() -> None:
    """A pod that refuses a body too large before reading it (and closes) is answered as a
    refusal: the client's ``PodRequestError`` (413), not a ``PodUnavailableError``."""

    def refuse(conn: socket.socket, _number: int) -> None:
        conn.recv(4096)
        conn.sendall(b'HTTP/1.1 413 Content Too Large\r\nContent-Length: 21\r\n\r\n{"detail":"too big!"}')
        conn.shutdown(socket.SHUT_WR)
        conn.recv(4096)

    async def main(url: str) -> None:
        async with make_transport() as transport:
            pod = PodConnection("sim-x", url, transport, timeout_s=10)
            body = {"generation": 0, "env_indices": np.arange(2), "actions": np.zeros((2, 1 << 21), np.float32)}
            await pod.call("step", body, ["a", "b"])

    with socket_server(refuse) as url, pytest.raises(PodRequestError, match="too big") as caught:
        asyncio.run(main(url))
    assert caught.value.status == 413


# ------------------------------------------------------------------ the controller's side


@dataclass
class Pods:
    """Pods that exist as registrations and heartbeats sent from a thread of the test."""

    url: str
    names: tuple[str, ...]
    stop: threading.Event = field(default_factory=threading.Event)

    def heartbeat(self, controller: str) -> None:
        with httpx.Client(base_url=controller, timeout=30.0) as client:
            for name in self.names:
                client.post("/v1/pods", json={"pod": name, "url": f"{self.url}/{name}", "capacity": {"max_envs": 64}})
            while not self.stop.is_set():
                for name in self.names:
                    body = {"url": f"{self.url}/{name}", "generation": None, "assignment": None, "ready": False}
                    client.post(f"/v1/pods/{name}/heartbeat", json=body)
                self.stop.wait(0.2)


def metric(text: str, name: str) -> float:
    values = [float(line.split()[-1]) for line in text.splitlines() if line.startswith(name)]
    assert values, f"{name} not in the metrics"
    return sum(values)


@pytest.mark.parametrize("kind", ["one-endless-trailer", "many-tiny-chunks"])
def test_a_pod_answering_pushes_with_endless_framing_never_stalls_the_controller(
    kind: str, caplog: pytest.LogCaptureFixture
) -> None:
    """The controller pushes assignments to two pods whose every answer is hostile: each push
    fails at the cap and backs off, the controller's stall guard logs no stall of its loop, and
    the pods, heartbeating meanwhile, stay registered."""
    settings = ControllerSettings(adopt_grace_s=0.0, push_backoff_max_s=0.25, push_timeout_s=30.0)
    caplog.set_level(logging.WARNING, logger="service.controller")
    with hostile_peer(kind) as peer, AppThread(create_app(settings), lifespan="on") as controller:
        pods = Pods(peer.url, ("sim-0", "sim-1"))
        beats = threading.Thread(target=pods.heartbeat, args=(controller.url,), daemon=True)
        beats.start()
        try:
            wait_until(
                lambda: len(httpx.get(f"{controller.url}/v1/pods", timeout=5).json()) == 2, "pods to register", 30
            )
            assert httpx.put(f"{controller.url}/v1/job", json=JOB, timeout=10).status_code == 200

            def failed_pushes() -> float:
                text = httpx.get(f"{controller.url}/metrics", timeout=5).text
                return metric(text, 'vecsim_controller_pushes_total{result="failed"}')

            # Both ends have counted six: the peer its answers, the controller its failed pushes.
            wait_until(lambda: len(peer.sent) >= 6 and failed_pushes() >= 6, "six pushes failed", 60)
            metrics = httpx.get(f"{controller.url}/metrics", timeout=5).text
            listed = [p["pod"] for p in httpx.get(f"{controller.url}/v1/pods", timeout=5).json()]
        finally:
            pods.stop.set()
            beats.join(timeout=35)
    assert all(peer.hung_up[:6]) and max(peer.sent[:6]) < OFFER, (peer.hung_up, peer.sent)
    assert metric(metrics, "vecsim_controller_stalls_total") == 0
    failed = [r.getMessage() for r in caplog.records if r.getMessage().startswith("push of generation")]
    assert failed and all(read_count(kind, message) <= BOUNDS[kind] for message in failed)
    assert not [r for r in caplog.records if "did not run for" in r.getMessage()]
    assert listed == ["sim-0", "sim-1"]


# ------------------------------------------------------------------------- the pod's side


@pytest.mark.parametrize("kind", ["endless-trailers", "many-tiny-chunks"])
def test_a_controller_answering_a_pod_with_endless_framing_costs_the_pod_its_cap(
    kind: str, caplog: pytest.LogCaptureFixture
) -> None:
    """A pod registers with a controller whose every answer is hostile: each registration fails
    at the cap (the pod's agent logs it and retries), and the controller sees the pod hang up."""
    caplog.set_level(logging.WARNING, logger="service.pod.agent")
    with hostile_peer(kind) as peer:
        sock = loopback_socket()
        port = sock.getsockname()[1]
        settings = PodSettings(name="sim-9", port=port, controller_url=peer.url, max_envs=1, gpu=False)
        settings = settings.model_copy(update={"heartbeat_interval_s": 0.05, "max_backoff_s": 0.1})
        with AppThread(create_pod_app(settings), sock, access_log=False, lifespan="on"):
            wait_until(lambda: len(peer.sent) >= 3, "three registrations answered", 60)
    assert all(peer.hung_up[:3]) and max(peer.sent[:3]) < OFFER
    failed = [r.getMessage() for r in caplog.records if "unreachable or refusing" in r.getMessage()]
    assert failed and all(read_count(kind, message) <= BOUNDS[kind] for message in failed)
