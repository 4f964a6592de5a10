"""One pod that answers something no pod should costs that pod's trajectories alone.

Two real pods serve one stage (sim-0 and sim-1, two ``gym/Pendulum-v1`` envs each). sim-1 is
reached through a proxy written here: a raw asyncio socket server on loopback that forwards each
request to the real sim-1 and passes its answer back, until a test tells it to answer steps with
a hostile reply instead (an absurd Content-Length, a chunk size past 2^64, an undecodable or
bomb-sized gzip body, bytes that are not HTTP, a body that is not vecsim's wire, megabytes of
trailers, of one chunk extension or of one-byte chunks). Every such answer must end as the client's own
``PodUnavailableError`` naming sim-1 and its traj_keys, with sim-0's rows delivered; a rollout
must lose sim-1's trajectories only, and the next one must run at once. A valid gzip-encoded
answer (a compressing proxy) must work like a plain one.
"""

from __future__ import annotations

import asyncio
import gzip
import threading
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
import torch
from support.service_procs import Server, assignment_file, pod_server, raw_server, running

from vecsim import wire
from vecsim.client import HTTPVectorEnv, PodRequestError, PodUnavailableError, StageClient
from vecsim.client.pods import PodConnection
from vecsim.client.stage import fetch_routing
from vecsim.rollout import EnvLoop
from vecsim.transport import MAX_CONTROL_ANSWER_BYTES, HttpxTransport, make_transport

PENDULUM = "gym/Pendulum-v1"
EPISODE = 12
KEYS = ["t0", "t1", "t2", "t3"]
REQUESTS = [(PENDULUM, k) for k in (3, 4, 5, 6)]

HEAD_OK = b"HTTP/1.1 200 OK\r\nContent-Type: application/x-vecsim\r\n"
CHUNKED = b"Transfer-Encoding: chunked\r\n\r\n"
# A body that inflates to 256 MiB from about 256 KiB: far past the cap for these small answers.
BOMB = gzip.compress(bytes(256 << 20), compresslevel=9)
HOSTILE = {
    "content-length-past-2^64": HEAD_OK + b"Content-Length: 18446744073709551616\r\n\r\n",
    "content-length-100-GB": HEAD_OK + b"Content-Length: 100000000000\r\n\r\n" + bytes(1000),
    "chunk-size-ffffffffffffffff": HEAD_OK + b"Transfer-Encoding: chunked\r\n\r\nffffffffffffffff\r\n" + bytes(1000),
    "undecodable-gzip": HEAD_OK + b"Content-Encoding: gzip\r\nContent-Length: 12\r\n\r\nnot gzip!!!!",
    "gzip-bomb": HEAD_OK + b"Content-Encoding: gzip\r\nContent-Length: %d\r\n\r\n" % len(BOMB) + BOMB,
    "not-http": b"SSH-2.0-OpenSSH_9.6\r\n\r\n",
    "http-fine-body-not-wire": HEAD_OK + b"Content-Length: 10\r\n\r\n0123456789",
    "8-MB-of-trailers": HEAD_OK + CHUNKED + b"0\r\n" + b"X-Trailer: %s\r\n" % (b"t" * 1000) * 8000,
    "8-MB-chunk-extension": HEAD_OK + CHUNKED + b"2;ext=" + b"e" * (8 << 20),
    "a-million-one-byte-chunks": HEAD_OK + CHUNKED + b"1\r\nx\r\n" * 1_000_000,
}
# The cap each answer of endless framing meets, as the error's reason names it.
CAPPED = {
    "8-MB-of-trailers": "chunk extensions and trailers are larger than",
    "8-MB-chunk-extension": "chunk extensions and trailers are larger than",
    "a-million-one-byte-chunks": "the answer has more than",
}


class HostileProxy:
    """A loopback proxy to ``upstream``: forwards requests and answers, except that while
    ``reply`` is set, a ``POST /v1/step`` is answered with ``reply`` and the connection closed;
    while ``gzip_answers`` is set, answers go back gzip-encoded."""

    def __init__(self, upstream: str) -> None:
        self.upstream = upstream
        self.reply: bytes | None = None
        self.gzip_answers = False
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()
        self.server = asyncio.run_coroutine_threadsafe(self._start(), self.loop).result(10)
        self.url = f"http://127.0.0.1:{self.server.sockets[0].getsockname()[1]}"

    async def _start(self) -> asyncio.Server:
        self.http = httpx.AsyncClient(timeout=60)
        return await asyncio.start_server(self._serve, "127.0.0.1", 0)

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            while True:
                head = await reader.readuntil(b"\r\n\r\n")
                lines = head.decode("latin-1").split("\r\n")
                method, path, _ = lines[0].split(" ", 2)
                headers = dict(line.split(": ", 1) for line in lines[1:] if line)
                length = int(next((v for k, v in headers.items() if k.lower() == "content-length"), "0"))
                body = await reader.readexactly(length)
                if self.reply is not None and path == "/v1/step":
                    writer.write(self.reply)
                    await writer.drain()
                    return
                sent = {k: v for k, v in headers.items() if k.lower() not in ("host", "content-length")}
                answer = await self.http.request(method, f"{self.upstream}{path}", headers=sent, content=body)
                content, extra = answer.content, b""
                if self.gzip_answers:
                    content, extra = gzip.compress(content), b"Content-Encoding: gzip\r\n"
                writer.write(
                    b"HTTP/1.1 %d X\r\nContent-Type: %s\r\n%sContent-Length: %d\r\n\r\n"
                    % (answer.status_code, answer.headers.get("content-type", "").encode(), extra, len(content))
                    + content
                )
                await writer.drain()
        except (asyncio.IncompleteReadError, ConnectionError):
            pass
        finally:
            writer.close()

    def close(self) -> None:
        async def stop() -> None:
            self.server.close()
            await self.http.aclose()

        asyncio.run_coroutine_threadsafe(stop(), self.loop).result(10)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(10)


def pod(name: str, workdir: Path) -> Server:
    path = assignment_file(workdir, name, [(PENDULUM, 2)], stage_id=0, max_episode_steps=EPISODE)
    return pod_server(name, workdir, args=["--assignment", str(path)])


@pytest.fixture(scope="module")
def pods(tmp_path_factory) -> Iterator[tuple[Server, HostileProxy]]:
    """sim-0 reached directly, sim-1 through the proxy (honest until a test says otherwise)."""
    workdir = tmp_path_factory.mktemp("hostile")
    with running(pod("sim-0", workdir), ready=True) as first, running(pod("sim-1", workdir), ready=True) as second:
        proxy = HostileProxy(second.url)
        try:
            yield first, proxy
        finally:
            proxy.close()


@pytest.fixture
def proxy(pods) -> Iterator[HostileProxy]:
    yield pods[1]
    pods[1].reply, pods[1].gzip_answers = None, False


def client_of(pods, **kwargs) -> StageClient:
    first, proxy = pods
    return StageClient.from_pods([first.url, proxy.url], timeout_s=10, **kwargs)


def actions(keys, value: float) -> dict[str, np.ndarray]:
    return {key: np.array([value], np.float32) for key in keys}


@pytest.mark.parametrize("hostile", list(HOSTILE))
def test_a_hostile_answer_fails_the_call_for_its_pods_trajectories_alone(pods, proxy, hostile):
    with client_of(pods) as client:
        client.reset_trajectories(REQUESTS, KEYS)
        on_sim_1 = [k for k, r in client.routes.items() if r.pod == "sim-1"]
        on_sim_0 = [k for k in KEYS if k not in on_sim_1]
        client.reset_stage(0).result(timeout=60)
        proxy.reply = HOSTILE[hostile]
        with pytest.raises(PodUnavailableError) as caught:
            client.step_stage(0, actions(KEYS, 0.5)).result(timeout=60)
        assert caught.value.pods == ["sim-1"] and sorted(caught.value.traj_keys) == sorted(on_sim_1)
        assert caught.value.answered.traj_keys == on_sim_0
        assert CAPPED.get(hostile, "") in caught.value.reason
        # The client is whole: the next call on the stage goes out at once and is answered.
        proxy.reply = None
        after = client.step_stage(0, actions(on_sim_0, 0.5)).result(timeout=60)
        assert after.traj_keys == on_sim_0


def test_a_gzip_encoded_answer_is_decoded_once_and_equals_the_plain_one(pods, proxy):
    with client_of(pods) as client:
        client.reset_trajectories(REQUESTS, KEYS)
        client.reset_stage(0).result(timeout=60)
        plain = client.step_stage(0, actions(KEYS, 0.5)).result(timeout=60)
        client.reset_stage(0).result(timeout=60)
        proxy.gzip_answers = True
        encoded = client.step_stage(0, actions(KEYS, 0.5)).result(timeout=60)
    assert np.array_equal(encoded.obs, plain.obs)
    assert np.array_equal(encoded.reward, plain.reward)


def test_a_rollout_loses_only_the_hostile_pods_trajectories_and_the_next_runs_at_once(pods, proxy):
    def policy(obs, instructions, task_ids) -> torch.Tensor:
        return torch.clamp(-0.5 * obs[:, 2:3], -2.0, 2.0)

    with client_of(pods) as client:
        loop = EnvLoop(client, policy, horizon=EPISODE)
        proxy.reply = HOSTILE["content-length-past-2^64"]
        hit = loop.run(REQUESTS, KEYS)
        on_sim_1 = sorted(k for k, r in client.routes.items() if r.pod == "sim-1")
        proxy.reply = None
        clean = loop.run(REQUESTS, KEYS)
    assert sorted(hit.lost) == on_sim_1
    assert sorted(hit.trajectories) == sorted(set(KEYS) - set(on_sim_1))
    assert all(t.length == EPISODE for t in hit.trajectories.values())
    assert clean.lost == {} and sorted(clean.trajectories) == sorted(KEYS)


def test_the_vector_env_fails_the_hostile_pods_envs_alone(pods, proxy):
    first, _ = pods
    env = HTTPVectorEnv(pod_urls=[first.url, proxy.url], timeout_s=10)
    try:
        env.reset(seed=0)
        failed = sorted(i for i, route in env.routes.items() if route.pod == "sim-1")
        proxy.reply = HOSTILE["chunk-size-ffffffffffffffff"]
        with pytest.raises(PodUnavailableError) as caught:
            env.step(np.zeros((env.num_envs, 1), np.float32))
        proxy.reply = None
        obs, _info = env.reset(options={"reset_mask": np.isin(np.arange(env.num_envs), failed)})
    finally:
        env.close()
    assert caught.value.failed_envs == failed
    assert obs.shape[0] == env.num_envs


def test_the_client_answers_as_httpx_own_connections_read_the_pods(pods, proxy):
    answers = []
    for transport in (None, HttpxTransport(httpx.AsyncHTTPTransport(trust_env=False))):
        with client_of(pods, transport=transport) as client:
            client.reset_trajectories(REQUESTS, KEYS)
            client.reset_stage(0).result(timeout=60)
            answers.append(client.step_stage(0, actions(KEYS, 0.5)).result(timeout=60))
    default, httpx_own = answers
    assert np.array_equal(default.obs, httpx_own.obs)
    assert np.array_equal(default.reward, httpx_own.reward)


class HostileServer:
    """A loopback server that answers every request with ``reply`` and closes the connection:
    a controller or a pod gone wrong, met before the client has any routing."""

    def __init__(self, reply: bytes) -> None:
        self.reply = reply
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()
        self.server = asyncio.run_coroutine_threadsafe(
            asyncio.start_server(self._serve, "127.0.0.1", 0), self.loop
        ).result(10)
        self.url = f"http://127.0.0.1:{self.server.sockets[0].getsockname()[1]}"

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            await reader.readuntil(b"\r\n\r\n")
            writer.write(self.reply)
            await writer.drain()
        except (asyncio.IncompleteReadError, ConnectionError):
            pass
        finally:
            writer.close()

    def __enter__(self) -> HostileServer:
        return self

    def __exit__(self, *exc: object) -> None:
        async def stop() -> None:
            self.server.close()

        asyncio.run_coroutine_threadsafe(stop(), self.loop).result(10)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(10)


@pytest.mark.parametrize("hostile", list(HOSTILE))
def test_a_hostile_info_or_routing_answer_is_the_clients_own_error(hostile):
    """``from_pods`` (a pod's ``/v1/info``) and ``fetch_routing`` (the controller's table) read
    their answers under the control plane's cap: every hostile answer is a
    ``PodUnavailableError`` or ``PodRequestError`` naming the server, never a raw
    ``OverflowError``/``MemoryError`` or an inflated bomb."""
    with HostileServer(HOSTILE[hostile]) as server:
        with pytest.raises((PodUnavailableError, PodRequestError)) as from_pods:
            StageClient.from_pods([server.url], timeout_s=10)
        with pytest.raises((PodUnavailableError, PodRequestError)) as routing:
            fetch_routing(server.url, timeout_s=10)
    assert server.url.split("//")[1] in str(from_pods.value) or "127.0.0.1" in str(from_pods.value)
    assert "/v1/routing" in str(routing.value) or "controller" in str(routing.value)


def test_the_control_plane_cap_bounds_an_info_answer():
    body = b"{" + b'"x": 1, ' * ((MAX_CONTROL_ANSWER_BYTES // 8) + 1) + b'"y": 2}'
    reply = (
        HEAD_OK.replace(b"application/x-vecsim", b"application/json") + b"Content-Length: %d\r\n\r\n" % len(body) + body
    )
    with HostileServer(reply) as server, pytest.raises(PodUnavailableError, match="exceeds the cap"):
        StageClient.from_pods([server.url], timeout_s=10)


@pytest.mark.parametrize(
    "info",
    [
        b"[1, 2]",
        b'{"x": 1}',
        b'{"pod": "p", "stage_id": 0, "num_envs": "many", "tasks": []}',
        b'{"pod": "p", "stage_id": 0, "num_envs": 1, "tasks": [3]}',
    ],
)
def test_an_info_answer_that_is_not_a_pods_is_a_value_error_naming_the_url(info):
    reply = (
        HEAD_OK.replace(b"application/x-vecsim", b"application/json") + b"Content-Length: %d\r\n\r\n" % len(info) + info
    )
    with HostileServer(reply) as server, pytest.raises(ValueError, match="is not a pod's") as caught:
        StageClient.from_pods([server.url], timeout_s=10)
    assert server.url in str(caught.value)


@pytest.mark.parametrize("kind", ["httptools", "httpx"])
def test_a_pod_that_sets_a_cookie_gets_none_back_and_each_call_carries_its_own_headers(kind):
    """A pod's answers plant nothing in the client: a ``Set-Cookie`` is not sent back on the
    next call. Every step carries the wire's content type, the token and the encodings the
    client decodes, on vecsim's transport as on httpx's own connections (the reference)."""
    env_indices = np.arange(2, dtype=np.int64)
    answer = wire.encode({"env_indices": env_indices})
    reply = (
        HEAD_OK
        + b"Set-Cookie: session=planted; Path=/\r\nConnection: close\r\nContent-Length: %d\r\n\r\n" % len(answer)
        + answer
    )
    requests: list[bytes] = []

    async def two_steps(url: str) -> None:
        if kind == "httptools":
            transport = make_transport()
        else:
            transport = HttpxTransport(httpx.AsyncHTTPTransport(trust_env=False))
        async with transport:
            pod = PodConnection("sim-x", url, transport, timeout_s=10, token="s3cret")
            for _ in range(2):
                body = {"generation": 0, "env_indices": env_indices, "actions": np.zeros((2, 1), np.float32)}
                await pod.call("step", body, ["a", "b"])

    with raw_server(reply, requests) as url:
        asyncio.run(two_steps(url))
    heads = [request.split(b"\r\n\r\n")[0].lower() for request in requests]
    assert len(heads) == 2
    for head in heads:
        assert head.startswith(b"post /v1/step http/1.1")
        assert b"\r\ncontent-type: application/x-vecsim" in head
        assert b"\r\nauthorization: bearer s3cret" in head
        assert b"\r\naccept-encoding: gzip, deflate" in head
        assert b"\r\ncookie:" not in head
