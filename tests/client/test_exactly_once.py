"""Exactly-once resets and steps: a step the pod applied whose answer never arrived is not applied
again. A real pod (``gym/Pendulum-v1``, 2 envs, its step counter in ``/metrics``) is reached
through a loopback proxy the test scripts: it passes bytes both ways, and when armed it forwards
the next request to the pod, reads the pod's whole answer (so the step has been applied) and
closes the client's connection without a byte of it. The client's transport sends the request
again on a new connection only because it carries an ``Idempotency-Key``; the pod answers that
repeat from memory. Counting the pod's env steps and comparing observations with a fault-free
run shows each step applied once.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import threading
from collections.abc import Iterator

import httpx
import numpy as np
import pytest
from prometheus_client.parser import text_string_to_metric_families
from support.service_procs import PodSpec, loopback_socket, standalone_pods, step_body

from vecsim import wire
from vecsim.config import CameraConfig
from vecsim.client import StageClient
from vecsim.transport import Transport
from vecsim.transport.httptools_impl import IDEMPOTENCY_KEY, HttptoolsTransport, MayHaveBeenAppliedError

PENDULUM = "gym/Pendulum-v1"
KEYS = ["t0", "t1"]
REQUESTS = [(PENDULUM, 3), (PENDULUM, 4)]
WIRE = (("Content-Type", wire.CONTENT_TYPE), ("Accept", wire.CONTENT_TYPE))


def _read_message(conn: socket.socket, pending: bytearray) -> bytes | None:
    """One HTTP/1.1 message with a Content-Length (all uvicorn and vecsim send here), or None at EOF."""
    while b"\r\n\r\n" not in pending:
        data = conn.recv(65536)
        if not data:
            return None
        pending += data
    end = pending.index(b"\r\n\r\n") + 4
    length = 0
    for line in bytes(pending[:end]).split(b"\r\n"):
        name, _, value = line.partition(b":")
        if name.strip().lower() == b"content-length":
            length = int(value)
    while len(pending) < end + length:
        data = conn.recv(65536)
        if not data:
            return None
        pending += data
    message = bytes(pending[: end + length])
    del pending[: end + length]
    return message


class LosingProxy:
    """A loopback proxy to ``upstream`` that, once :meth:`arm` was called, loses the answer to the
    next request: the pod gets the request and answers it whole, the client gets nothing and its
    connection closes. Counts the requests it forwarded."""

    def __init__(self, upstream: str) -> None:
        url = httpx.URL(upstream)
        self.upstream = (url.host, url.port)
        self.armed = threading.Event()
        self.forwarded: list[bytes] = []
        self.lost = 0

    def arm(self) -> None:
        self.armed.set()

    def handle(self, conn: socket.socket) -> None:
        with socket.create_connection(self.upstream, timeout=30) as pod:
            from_client, from_pod = bytearray(), bytearray()
            while (request := _read_message(conn, from_client)) is not None:
                self.forwarded.append(request)
                pod.sendall(request)
                answer = _read_message(pod, from_pod)
                if answer is None:
                    return
                if self.armed.is_set():
                    self.armed.clear()
                    self.lost += 1
                    return  # the pod applied it and answered; the client's connection closes unanswered
                conn.sendall(answer)


@contextlib.contextmanager
def serving(handle) -> Iterator[str]:
    """A loopback TCP server running ``handle(connection)`` in a thread per connection; its URL."""
    listener = loopback_socket()
    listener.listen(16)
    listener.settimeout(0.1)
    stop = threading.Event()

    def one(conn: socket.socket) -> None:
        with conn, contextlib.suppress(OSError):
            conn.settimeout(30)
            handle(conn)

    def accept() -> None:
        while not stop.is_set():
            with contextlib.suppress(TimeoutError):
                conn, _ = listener.accept()
                threading.Thread(target=one, args=(conn,), daemon=True).start()

    thread = threading.Thread(target=accept, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{listener.getsockname()[1]}"
    finally:
        stop.set()
        thread.join(5)
        listener.close()


@contextlib.contextmanager
def proxied_pod() -> Iterator[tuple[str, str, LosingProxy]]:
    """A real pod and a losing proxy to it: (pod URL, proxy URL, proxy)."""
    with standalone_pods([PodSpec("sim-0", 0, [(PENDULUM, 2)], max_episode_steps=200)]) as [pod]:
        proxy = LosingProxy(pod.url)
        with serving(proxy.handle) as url:
            yield pod.url, url, proxy


@pytest.fixture(scope="module")
def pod() -> Iterator[tuple[str, str, LosingProxy]]:
    with proxied_pod() as urls:
        yield urls


def metric(pod_url: str, name: str) -> float:
    for family in text_string_to_metric_families(httpx.get(f"{pod_url}/metrics").text):
        for sample in family.samples:
            if sample.name == name:
                return sample.value
    raise AssertionError(f"no metric {name}")


def steps_of(pod_url: str) -> float:
    return metric(pod_url, "vecsim_pod_env_steps_total")


def rollout(
    client: StageClient, proxy: LosingProxy, lose: str | None = None, chunk: int | None = None
) -> list[np.ndarray]:
    """Reset both trajectories, step them 5 times (one action, or chunks of ``chunk``); the
    answer to the reset (``lose="reset"``) or to step 2 (``"step"``) is lost once."""
    client.reset_trajectories(REQUESTS, KEYS)
    if lose == "reset":
        proxy.arm()
    first = client.reset_stage(0).result(timeout=30)
    rows = [first.obs.copy()]
    for i in range(5):
        if lose == "step" and i == 2:
            proxy.arm()
        action = np.full((chunk, 1) if chunk else (1,), 0.4 * (i - 2), np.float32)
        batch = client.step_stage(0, {key: action for key in KEYS}).result(timeout=30)
        rows += [batch.obs, batch.reward]
    return rows


def counts(pod_url: str) -> np.ndarray:
    names = ["vecsim_pod_env_steps_total", "vecsim_pod_env_resets_total", "vecsim_pod_idempotency_key_repeats_total"]
    return np.array([metric(pod_url, name) for name in names])


@pytest.mark.parametrize(
    ("lose", "chunk"), [("step", None), ("step", 3), ("reset", None)], ids=["step", "chunk-step", "reset"]
)
def test_a_call_whose_answer_was_lost_after_the_pod_applied_it_is_applied_once(pod, lose: str, chunk: int | None):
    pod_url, proxy_url, proxy = pod
    with StageClient.from_pods([proxy_url], timeout_s=30) as client:
        reference = rollout(client, proxy, chunk=chunk)
        before, forwarded = counts(pod_url), len(proxy.forwarded)
        got = rollout(client, proxy, lose, chunk)
    assert proxy.lost == 1
    proxy.lost = 0
    # The lost call went to the pod twice (the same bytes, the same key), and was applied once.
    sent = proxy.forwarded[forwarded:]
    repeated = [i for i in range(len(sent) - 1) if sent[i] == sent[i + 1]]
    assert len(repeated) == 1 and sent[repeated[0]].startswith(f"POST /v1/{lose}".encode())
    assert IDEMPOTENCY_KEY.encode() in sent[repeated[0]]
    steps, resets, repeats = counts(pod_url) - before
    assert (steps, resets, repeats) == (5 * (chunk or 1) * len(KEYS), len(KEYS), 1)
    for mine, theirs in zip(got, reference, strict=True):
        assert np.array_equal(mine, theirs)


def test_a_pod_holds_at_most_one_answer_per_env(pod) -> None:
    pod_url, proxy_url, proxy = pod
    with StageClient.from_pods([proxy_url], timeout_s=30) as client:
        rollout(client, proxy)
    assert 1 <= metric(pod_url, "vecsim_pod_idempotency_key_answers") <= len(KEYS)


async def _step_after_a_read(
    proxy_url: str, proxy: LosingProxy, headers: tuple[tuple[str, str], ...], transport: Transport | None = None
) -> None:
    """Read /v1/info (so the connection is a kept-alive one), then POST a step whose answer is lost."""
    async with transport or HttptoolsTransport() as transport:
        status, content = await transport.fetch("GET", f"{proxy_url}/v1/info", (), b"", 1 << 20)
        generation = httpx.Response(status, content=content).json()["generation"]
        body = wire.encode(step_body(generation, [0, 1], np.zeros((2, 1), np.float32)))
        proxy.arm()
        await transport.fetch("POST", f"{proxy_url}/v1/step", headers, body, 1 << 20)


def test_a_step_without_an_idempotency_key_whose_answer_was_lost_is_not_sent_again(pod) -> None:
    pod_url, proxy_url, proxy = pod
    before, forwarded = steps_of(pod_url), len(proxy.forwarded)
    with pytest.raises(MayHaveBeenAppliedError, match=f"may have been applied.*no {IDEMPOTENCY_KEY} header"):
        asyncio.run(_step_after_a_read(proxy_url, proxy, WIRE))
    assert [r.split(b" ")[1] for r in proxy.forwarded[forwarded:]] == [b"/v1/info", b"/v1/step"]
    assert steps_of(pod_url) - before == 2


def test_a_repeated_key_is_answered_the_same_and_changes_nothing(pod) -> None:
    pod_url, _, _ = pod
    generation = httpx.get(f"{pod_url}/v1/info").json()["generation"]
    headers = {**dict(WIRE), IDEMPOTENCY_KEY: "repeat-0001"}
    body = wire.encode(step_body(generation, [0, 1], np.full((2, 1), 0.3, np.float32)))
    before = steps_of(pod_url)
    first = httpx.post(f"{pod_url}/v1/step", content=body, headers=headers)
    again = httpx.post(f"{pod_url}/v1/step", content=body, headers=headers)
    assert first.status_code == again.status_code == 200 and first.content == again.content
    assert steps_of(pod_url) - before == 2
    # A fresh step moves on from where the first left the envs: they moved once.
    fresh = httpx.post(f"{pod_url}/v1/step", content=body, headers=dict(WIRE))
    assert fresh.status_code == 200 and fresh.content != first.content


@pytest.mark.parametrize(
    ("key", "said"),
    [("reused-0002", "was used for another request"), ("x" * 256, "1 to 255 printable ASCII"), ("", "1 to 255")],
    ids=["another-body", "too-long", "empty"],
)
def test_a_key_reused_for_another_body_or_malformed_is_refused_naming_the_header(pod, key: str, said: str) -> None:
    pod_url, _, _ = pod
    generation = httpx.get(f"{pod_url}/v1/info").json()["generation"]
    headers = {**dict(WIRE), IDEMPOTENCY_KEY: key}
    if said.startswith("was used"):
        first = wire.encode(step_body(generation, [0], np.full((1, 1), 0.1, np.float32)))
        assert httpx.post(f"{pod_url}/v1/step", content=first, headers=headers).status_code == 200
    before = steps_of(pod_url)
    other = wire.encode(step_body(generation, [0], np.full((1, 1), -0.1, np.float32)))
    refused = httpx.post(f"{pod_url}/v1/step", content=other, headers=headers)
    assert refused.status_code == 422
    assert refused.json()["detail"].startswith(f"{IDEMPOTENCY_KEY}: ") and said in refused.json()["detail"]
    assert steps_of(pod_url) == before


def test_a_key_whose_envs_moved_on_is_refused_not_applied_again(pod) -> None:
    pod_url, _, _ = pod
    generation = httpx.get(f"{pod_url}/v1/info").json()["generation"]
    body = wire.encode(step_body(generation, [0], np.full((1, 1), 0.2, np.float32)))
    old = {**dict(WIRE), IDEMPOTENCY_KEY: "old-0003"}
    assert httpx.post(f"{pod_url}/v1/step", content=body, headers=old).status_code == 200
    later = {**dict(WIRE), IDEMPOTENCY_KEY: "later-0004"}
    assert httpx.post(f"{pod_url}/v1/step", content=body, headers=later).status_code == 200
    before = steps_of(pod_url)
    late = httpx.post(f"{pod_url}/v1/step", content=body, headers=old)
    assert late.status_code == 422 and "no longer held" in late.json()["detail"]
    assert steps_of(pod_url) == before


def test_a_repeat_arriving_while_the_first_is_applied_waits_for_its_answer() -> None:
    """A re-send that reaches the pod while the first request is still being stepped (the proxy
    lost the connection, not the pod) gets the first's answer; the chunk is applied once. A
    camera scene (tiny/lift, 256x256; a chunk of 64 actions) is stepped on the pod's worker
    thread, so the pod reads the repeat meanwhile."""
    slow = PodSpec("sim-0", 0, [("tiny/lift", 2)], camera=CameraConfig(height=256, width=256), render=None)
    with standalone_pods([slow]) as [pod]:
        generation = httpx.get(f"{pod.url}/v1/info").json()["generation"]
        chunk = np.zeros((2, 64, 7), np.float32)
        body = wire.encode(step_body(generation, [0, 1], chunk))
        headers = {**dict(WIRE), IDEMPOTENCY_KEY: "in-flight-0005"}
        before = counts(pod.url)

        async def twice() -> list[httpx.Response]:
            async with httpx.AsyncClient(timeout=120) as client:
                first = asyncio.create_task(client.post(f"{pod.url}/v1/step", content=body, headers=headers))
                await asyncio.sleep(0.05)  # whichever the pod reads first, the other overlaps it
                assert not first.done(), "the first was answered before the repeat went out"
                repeat = await client.post(f"{pod.url}/v1/step", content=body, headers=headers)
                return [await first, repeat]

        first, repeat = asyncio.run(twice())
        assert first.status_code == repeat.status_code == 200 and first.content == repeat.content
        steps, _, repeats = counts(pod.url) - before
    assert (steps, repeats) == (2 * 64, 1)
