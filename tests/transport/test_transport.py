"""vecsim.transport: httpx clients on each transport against real uvicorn servers on loopback, and
answers read under a cap from hostile servers (raw sockets that send what no pod would).

The servers are real uvicorn servers on real sockets, each in a thread of the test process, on a
port the kernel picked. vecsim's transport must give the answers and raise the httpx exceptions
that httpx's own connections do, so most tests run once per kind: ``httptools`` (vecsim's) and
``httpx`` (``httpx.AsyncHTTPTransport``, the reference, no longer one of vecsim's kinds).
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import gzip
import shutil
import socket
import ssl
import subprocess
import threading
import zlib
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import httpx
import numpy as np
import pytest
from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse, PlainTextResponse, Response, StreamingResponse
from support.service_procs import AppThread, raw_server, socket_server, wait_until

from vecsim import wire
from vecsim.transport import (
    DEFAULT_KIND,
    MAX_HEAD_BYTES,
    AnswerTooLargeError,
    HttptoolsTransport,
    HttpxTransport,
    Transport,
    as_transport,
    make_async_client,
    make_transport,
    read_answer,
)

KINDS = ["httptools", "httpx"]
T = TypeVar("T")


def transport_of(kind: str) -> Transport:
    """vecsim's transport (``httptools``), httptools' connections reached through httpx's
    interface (``httptools/httpx``, as ``HttpxTransport`` wraps an httpx transport), or the
    reference: httpx's own connections, their answers read through the same ``AnswerReader``."""
    if kind == "httpx":
        return HttpxTransport(httpx.AsyncHTTPTransport(trust_env=False))
    if kind == "httptools/httpx":
        return HttpxTransport(HttptoolsTransport())
    return make_transport(kind)  # type: ignore[arg-type]


def pattern(n: int) -> bytes:
    """``n`` bytes that differ from any shifted copy of themselves, so misplaced bytes show."""
    return (np.arange(n, dtype=np.uint64) * 2654435761 >> 7).astype(np.uint8).tobytes()


app = FastAPI()


@functools.cache
def barrier(parties: int) -> threading.Barrier:
    return threading.Barrier(parties)


@app.api_route("/bytes/{n}", methods=["GET", "HEAD"])
def get_bytes(n: int) -> Response:
    return Response(content=pattern(n), media_type="application/octet-stream")


@app.post("/echo")
async def echo(request: Request) -> Response:
    body = await request.body()
    return Response(
        content=body,
        media_type=request.headers.get("content-type", "application/octet-stream"),
        headers={
            "x-echo-test": request.headers.get("x-test", ""),
            "x-echo-transfer-encoding": request.headers.get("transfer-encoding", ""),
        },
    )


@app.get("/status/{code}")
def status(code: int) -> Response:
    if code in (204, 304):
        return Response(status_code=code)
    return JSONResponse({"detail": f"status {code} as asked"}, status_code=code)


@app.get("/drip")
def drip(chunks: int, interval: float, size: int = 1000) -> StreamingResponse:
    async def body() -> AsyncIterator[bytes]:
        for i in range(chunks):
            if interval:
                await asyncio.sleep(interval)
            yield bytes([i % 256]) * size

    return StreamingResponse(body(), media_type="application/octet-stream")


@app.get("/peer")
async def peer(request: Request, together: int = 1) -> Response:
    """The client's address; with ``together=n``, only once ``n`` such requests are here at once."""
    if together > 1:
        await asyncio.to_thread(barrier(together).wait, 30)
    return PlainTextResponse(f"{request.client.host}:{request.client.port}")


@app.get("/close")
def close() -> Response:
    return PlainTextResponse("bye", headers={"connection": "close"})


def uvicorn_server(**config: Any) -> AppThread:
    """A uvicorn server for ``app`` on a free loopback port."""
    return AppThread(app, lifespan="off", timeout_graceful_shutdown=1, **config)


@pytest.fixture(scope="module")
def server() -> Iterator[str]:
    with uvicorn_server() as served:
        yield served.url


def run_with(kind: str, use: Callable[[httpx.AsyncClient], Awaitable[T]], **client_kwargs: Any) -> T:
    """Run ``use(client)`` on a fresh event loop with a client of ``kind``, closing both after."""

    async def main() -> T:
        async with make_async_client(transport_of(kind), **client_kwargs) as client:
            return await use(client)

    return asyncio.run(main())


# ------------------------------------------------------------------------------- bodies


@pytest.mark.parametrize("size", [0, 1, 70_000, 4 << 20])
@pytest.mark.parametrize("kind", KINDS)
def test_response_body_arrives_byte_for_byte(server: str, kind: str, size: int) -> None:
    response = run_with(kind, lambda c: c.get(f"{server}/bytes/{size}"))
    assert response.status_code == 200
    assert response.headers["content-type"] == "application/octet-stream"
    assert response.content == pattern(size)


@pytest.mark.parametrize("kind", KINDS)
def test_request_body_and_headers_reach_the_server(server: str, kind: str) -> None:
    body = pattern(300_000)
    response = run_with(
        kind,
        lambda c: c.post(
            f"{server}/echo", content=body, headers={"content-type": "application/x-test", "x-test": "abc"}
        ),
    )
    assert response.content == body
    assert response.headers["content-type"] == "application/x-test"
    assert response.headers["x-echo-test"] == "abc"


@pytest.mark.parametrize("kind", KINDS)
def test_wire_parts_sent_as_a_stream_arrive_as_one_message(server: str, kind: str) -> None:
    message = {"actions": np.linspace(-1, 1, 16 * 7, dtype=np.float32).reshape(16, 7), "generation": 3}
    parts = wire.encode_parts(message)

    async def stream() -> AsyncIterator[bytes | memoryview]:
        for part in parts:
            yield part

    headers = {"content-type": wire.CONTENT_TYPE, "content-length": str(sum(len(p) for p in parts))}
    response = run_with(kind, lambda c: c.post(f"{server}/echo", content=stream(), headers=headers))
    assert response.headers["x-echo-transfer-encoding"] == ""
    decoded = wire.decode(response.content)
    assert decoded["generation"] == 3 and np.array_equal(decoded["actions"], message["actions"])


@pytest.mark.parametrize("kind", KINDS)
def test_body_of_unknown_length_arrives_whole(server: str, kind: str) -> None:
    async def stream() -> AsyncIterator[bytes]:
        for i in range(5):
            yield pattern(10_000 + i)

    response = run_with(kind, lambda c: c.post(f"{server}/echo", content=stream()))
    assert response.content == b"".join(pattern(10_000 + i) for i in range(5))


@pytest.mark.parametrize("kind", KINDS)
def test_chunked_response_is_reassembled(server: str, kind: str) -> None:
    response = run_with(kind, lambda c: c.get(f"{server}/drip", params={"chunks": 50, "interval": 0, "size": 3000}))
    assert response.content == b"".join(bytes([i]) * 3000 for i in range(50))


@pytest.mark.parametrize("kind", KINDS)
def test_head_request_has_headers_and_no_body(server: str, kind: str) -> None:
    response = run_with(kind, lambda c: c.head(f"{server}/bytes/1000"))
    assert response.status_code == 200
    assert response.headers["content-length"] == "1000"
    assert response.content == b""


@pytest.mark.parametrize("code", [404, 409, 500])
@pytest.mark.parametrize("kind", KINDS)
def test_error_status_and_its_json_detail_pass_through(server: str, kind: str, code: int) -> None:
    response = run_with(kind, lambda c: c.get(f"{server}/status/{code}"))
    assert response.status_code == code
    assert response.json() == {"detail": f"status {code} as asked"}


@pytest.mark.parametrize("kind", KINDS)
def test_no_content_status_has_an_empty_body(server: str, kind: str) -> None:
    response = run_with(kind, lambda c: c.get(f"{server}/status/204"))
    assert response.status_code == 204 and response.content == b""


# ------------------------------------------------------------------------- connections


@pytest.mark.parametrize("kind", KINDS)
def test_sequential_requests_reuse_one_keep_alive_connection(server: str, kind: str) -> None:
    async def use(client: httpx.AsyncClient) -> list[str]:
        return [(await client.get(f"{server}/peer")).text for _ in range(3)]

    peers = run_with(kind, use)
    assert len(set(peers)) == 1


@pytest.mark.parametrize("kind", KINDS)
def test_requests_in_flight_together_each_hold_their_own_connection(server: str, kind: str) -> None:
    async def use(client: httpx.AsyncClient) -> list[str]:
        responses = await asyncio.gather(*(client.get(f"{server}/peer", params={"together": 4}) for _ in range(4)))
        return [r.text for r in responses]

    assert len(set(run_with(kind, use))) == 4


@pytest.mark.parametrize("kind", KINDS)
def test_server_that_says_connection_close_gets_a_new_connection_next_time(server: str, kind: str) -> None:
    async def use(client: httpx.AsyncClient) -> tuple[str, str, str]:
        before = (await client.get(f"{server}/peer")).text
        bye = (await client.get(f"{server}/close")).text
        after = (await client.get(f"{server}/peer")).text
        return before, bye, after

    before, bye, after = run_with(kind, use)
    assert bye == "bye" and before != after


@pytest.mark.parametrize("kind", KINDS)
def test_connection_the_server_closed_while_idle_is_not_reused(kind: str) -> None:
    with uvicorn_server(timeout_keep_alive=1) as served:
        url = served.url

        async def use(client: httpx.AsyncClient) -> list[str]:
            first = await client.get(f"{url}/peer")
            # Past the server's keep-alive it closes the idle connection; this loop runs meanwhile.
            await asyncio.to_thread(wait_until, lambda: served.connections() == 0, "the idle connection closed", 30)
            second = await client.get(f"{url}/peer")
            assert [first.status_code, second.status_code] == [200, 200]
            return [first.text, second.text]

        first, second = run_with(kind, use)
        assert first != second  # the second request came on a new connection


@pytest.mark.parametrize("kind", KINDS)
def test_concurrent_requests_to_several_servers_all_get_their_own_answers(kind: str) -> None:
    with uvicorn_server() as a, uvicorn_server() as b, uvicorn_server() as c:
        urls = [a.url, b.url, c.url]

        async def use(client: httpx.AsyncClient) -> list[tuple[str, int, bytes]]:
            jobs = [(url, 100_000 * (i + 1) + j) for i, url in enumerate(urls) for j in range(4)]
            responses = await asyncio.gather(*(client.get(f"{url}/bytes/{n}") for url, n in jobs))
            return [(url, n, r.content) for (url, n), r in zip(jobs, responses)]

        for url, n, content in run_with(kind, use):
            assert content == pattern(n), f"{url}/bytes/{n}"


# ------------------------------------------------------------------------ broken servers


@pytest.mark.parametrize("kind", KINDS)
def test_refused_connection_raises_connect_error(refusing_port: int, kind: str) -> None:
    with pytest.raises(httpx.ConnectError):
        run_with(kind, lambda c: c.get(f"http://127.0.0.1:{refusing_port}/"))


@pytest.mark.parametrize(
    "reply",
    [b"", b"NOT HTTP AT ALL\r\n\r\n", b"HTTP/1.1 200 OK\r\nContent-Length: 100\r\n\r\nonly this"],
    ids=["no-answer", "garbage", "truncated-body"],
)
@pytest.mark.parametrize("kind", KINDS)
def test_broken_answer_raises_remote_protocol_error(kind: str, reply: bytes) -> None:
    with raw_server(reply) as url, pytest.raises(httpx.RemoteProtocolError):
        run_with(kind, lambda c: c.get(f"{url}/"))


# ---------------------------------------------------------------------------- factories


def test_unknown_kind_is_refused_naming_it() -> None:
    with pytest.raises(ValueError, match="kind: 'grpc' is not one of"):
        make_transport("grpc")  # type: ignore[arg-type]


@pytest.mark.parametrize("kind", KINDS)
def test_transport_errors_name_the_request(refusing_port: int, kind: str) -> None:
    url = f"http://127.0.0.1:{refusing_port}/v1/step"
    with pytest.raises(httpx.ConnectError) as caught:
        run_with(kind, lambda c: c.post(url, content=b"x"))
    assert caught.value.request.url == url


def test_streamed_response_still_arrives_chunk_by_chunk(server: str) -> None:
    async def use(client: httpx.AsyncClient) -> list[bytes]:
        async with client.stream("GET", f"{server}/drip", params={"chunks": 3, "interval": 0, "size": 2}) as response:
            return [chunk async for chunk in response.aiter_raw()]

    assert b"".join(run_with(DEFAULT_KIND, use)) == b"\x00\x00\x01\x01\x02\x02"


def test_closed_client_refuses_requests(server: str) -> None:
    async def main() -> None:
        client = make_async_client()
        await client.aclose()
        await client.get(f"{server}/bytes/1")

    with pytest.raises(RuntimeError, match="client has been closed"):
        asyncio.run(main())


@pytest.mark.parametrize("kind", KINDS)
def test_an_answer_that_stalls_between_reads_raises_read_timeout(server: str, kind: str) -> None:
    with pytest.raises(httpx.ReadTimeout):
        run_with(
            kind,
            lambda c: c.get(f"{server}/drip", params={"chunks": 2, "interval": 3}),
            timeout=httpx.Timeout(10, read=0.3),
        )


# ------------------------------------------------------------------- answers under a cap


def read_with(kind: str, url: str, max_bytes: int) -> bytes:
    """GET ``url`` as the client asks a pod (``Transport.fetch`` of a transport of ``kind``, the
    answer read under ``max_bytes``, see :func:`transport_of`); return the body of a 200."""

    async def main() -> bytes:
        async with transport_of(kind) as transport:
            status, body = await transport.fetch("GET", url, (), b"", max_bytes)
        assert status == 200
        return body

    return asyncio.run(main())


# Each way an answer is read under a cap: every kind's, and httptools' through httpx's interface.
READ_KINDS = [*KINDS, "httptools/httpx"]


@pytest.mark.parametrize("kind", KINDS)
def test_an_answer_read_through_an_httpx_client_is_capped_alike(server: str, kind: str) -> None:
    async def use(client: httpx.AsyncClient) -> bytes:
        response = await client.send(client.build_request("GET", f"{server}/bytes/70000"), stream=True)
        return await read_answer(response, 69_999)

    with pytest.raises(AnswerTooLargeError, match="Content-Length 70000 exceeds the cap of 69999 bytes"):
        run_with(kind, use)


def gzip_reply(body: bytes, encoding: bytes = b"gzip") -> bytes:
    packed = gzip.compress(body) if encoding == b"gzip" else zlib.compress(body)
    return b"HTTP/1.1 200 OK\r\nContent-Encoding: %s\r\nContent-Length: %d\r\n\r\n%s" % (
        encoding,
        len(packed),
        packed,
    )


@pytest.mark.parametrize("kind", READ_KINDS)
def test_an_answer_exactly_at_the_cap_arrives_whole(server: str, kind: str) -> None:
    assert read_with(kind, f"{server}/bytes/70000", 70_000) == pattern(70_000)


@pytest.mark.parametrize("kind", READ_KINDS)
def test_a_content_length_over_the_cap_is_refused_before_the_body_is_read(kind: str) -> None:
    reply = b"HTTP/1.1 200 OK\r\nContent-Length: 100000000000\r\n\r\n" + bytes(1000)
    with raw_server(reply) as url, pytest.raises(AnswerTooLargeError, match="Content-Length 100000000000"):
        read_with(kind, f"{url}/", 1 << 20)


@pytest.mark.parametrize("length", [b"18446744073709551616", b"1" * 400, b"-1", b"12, 13"])
@pytest.mark.parametrize("kind", READ_KINDS)
def test_an_absurd_content_length_is_an_httpx_error(kind: str, length: bytes) -> None:
    with raw_server(b"HTTP/1.1 200 OK\r\nContent-Length: %s\r\n\r\n" % length) as url:
        with pytest.raises(httpx.HTTPError):
            read_with(kind, f"{url}/", 1 << 20)


@pytest.mark.parametrize("kind", READ_KINDS)
def test_a_chunk_size_past_2_64_is_an_httpx_error(kind: str) -> None:
    reply = b"HTTP/1.1 200 OK\r\nTransfer-Encoding: chunked\r\n\r\nffffffffffffffff\r\n" + bytes(1000)
    with raw_server(reply) as url, pytest.raises(httpx.HTTPError):
        read_with(kind, f"{url}/", 1 << 20)


@pytest.mark.parametrize("kind", READ_KINDS)
def test_a_chunked_answer_that_grows_past_the_cap_stops_there(server: str, kind: str) -> None:
    with pytest.raises(AnswerTooLargeError, match="exceeds the cap of 10000 bytes"):
        read_with(kind, f"{server}/drip?chunks=50&interval=0&size=3000", 10_000)


@pytest.mark.parametrize("encoding", [b"gzip", b"deflate"])
@pytest.mark.parametrize("kind", READ_KINDS)
def test_an_encoded_answer_is_decoded_once(kind: str, encoding: bytes) -> None:
    with raw_server(gzip_reply(pattern(300_000), encoding)) as url:
        assert read_with(kind, f"{url}/", 1 << 20) == pattern(300_000)


@pytest.mark.parametrize("kind", READ_KINDS)
def test_a_gzip_bomb_stops_at_the_cap(kind: str) -> None:
    with raw_server(gzip_reply(bytes(64 << 20))) as url:
        with pytest.raises(AnswerTooLargeError, match="decoded answer exceeds the cap of 1048576 bytes"):
            read_with(kind, f"{url}/", 1 << 20)


@pytest.mark.parametrize(
    ("reply", "what"),
    [
        (b"HTTP/1.1 200 OK\r\nContent-Encoding: gzip\r\nContent-Length: 8\r\n\r\nnot gzip", "corrupt gzip"),
        (b"HTTP/1.1 200 OK\r\nContent-Encoding: br\r\nContent-Length: 2\r\n\r\nxx", "unsupported Content-Encoding"),
        (b"HTTP/1.1 200 OK\r\nContent-Encoding: gzip, gzip\r\nContent-Length: 2\r\n\r\nxx", "stacked"),
    ],
    ids=["corrupt", "unsupported", "stacked"],
)
@pytest.mark.parametrize("kind", READ_KINDS)
def test_an_answer_that_cannot_be_decoded_is_a_decoding_error_naming_why(kind: str, reply: bytes, what: str) -> None:
    with raw_server(reply) as url, pytest.raises(httpx.DecodingError, match=what):
        read_with(kind, f"{url}/", 1 << 20)


@pytest.mark.parametrize("kind", READ_KINDS)
def test_a_gzip_body_cut_short_is_a_decoding_error(kind: str) -> None:
    packed = gzip.compress(pattern(100_000))[:-20]
    reply = b"HTTP/1.1 200 OK\r\nContent-Encoding: gzip\r\nContent-Length: %d\r\n\r\n%s" % (len(packed), packed)
    with raw_server(reply) as url, pytest.raises(httpx.DecodingError, match="truncated gzip"):
        read_with(kind, f"{url}/", 1 << 20)


# ---------------------------------------------------- httptools' lean path (the client's to a pod)


def fetch_with(
    url: str, method: str = "GET", headers: tuple[tuple[str, str], ...] = (), body: bytes = b"", times: int = 1
) -> list[tuple[int, bytes]]:
    """``times`` requests through one httptools transport's lean path; their (status, body)."""

    async def main() -> list[tuple[int, bytes]]:
        async with make_transport("httptools") as transport:
            return [await transport.fetch(method, url, headers, body, 64 << 20) for _ in range(times)]

    return asyncio.run(main())


def test_the_lean_path_carries_a_request_body_and_headers_byte_for_byte(server: str) -> None:
    body = pattern(300_000)
    headers = (("Content-Type", "application/x-test"), ("X-Test", "yes"))
    [(status, echoed)] = fetch_with(f"{server}/echo", "POST", headers, body)
    assert (status, echoed) == (200, body)


def test_the_lean_path_takes_an_answer_larger_than_its_read_buffer_whole(server: str) -> None:
    # 16 MiB: reading pauses at 4 MiB not yet taken and goes on once the reader takes them.
    [(status, body)] = fetch_with(f"{server}/bytes/{16 << 20}")
    assert status == 200 and body == pattern(16 << 20)


@app.get("/wire/{n}")
def get_wire(n: int) -> Response:
    return Response(content=pattern(n), media_type=wire.CONTENT_TYPE)


def test_the_lean_path_reads_a_big_wire_answer_into_one_buffer_byte_for_byte(server: str) -> None:
    # 5 MiB: read past the parser (over DIRECT_BYTES); a small wire answer is parsed, as any.
    [(status, body), (again, small)] = fetch_with(f"{server}/wire/{5 << 20}") + fetch_with(f"{server}/wire/1000")
    assert status == 200 and isinstance(body, memoryview) and body == pattern(5 << 20)
    assert again == 200 and small == pattern(1000)


def test_a_big_wire_answer_cut_short_of_its_length_is_a_remote_protocol_error() -> None:
    reply = b"HTTP/1.1 200 OK\r\nContent-Type: %s\r\nContent-Length: %d\r\n\r\n" % (
        wire.CONTENT_TYPE.encode(),
        2 << 20,
    )
    with (
        raw_server(reply + pattern(1 << 20)) as url,
        pytest.raises(httpx.RemoteProtocolError, match="inside the answer's body"),
    ):
        fetch_with(f"{url}/")


def test_bytes_after_a_big_wire_answer_leave_the_answer_and_drop_the_connection() -> None:
    head = b"HTTP/1.1 200 OK\r\nContent-Type: %s\r\nContent-Length: %d\r\n\r\n" % (wire.CONTENT_TYPE.encode(), 2 << 20)
    reply = head + pattern(2 << 20) + b"HTTP/1.1 500 No\r\nContent-Length: 3\r\n\r\nbad"
    with raw_server(reply) as url:
        answers = fetch_with(f"{url}/", times=2)
    assert [(status, bytes(body)) for status, body in answers] == [(200, pattern(2 << 20))] * 2


def test_a_big_wire_answer_over_the_cap_is_refused_before_its_body_is_read() -> None:
    reply = b"HTTP/1.1 200 OK\r\nContent-Type: %s\r\nContent-Length: %d\r\n\r\n" % (
        wire.CONTENT_TYPE.encode(),
        80 << 20,
    )
    with raw_server(reply + bytes(1000)) as url, pytest.raises(AnswerTooLargeError, match="Content-Length"):
        fetch_with(f"{url}/")


def test_the_lean_path_reuses_one_keep_alive_connection(server: str) -> None:
    peers = {body for _, body in fetch_with(f"{server}/peer", times=5)}
    assert len(peers) == 1


def test_the_lean_path_passes_error_statuses_and_bodies_through(server: str) -> None:
    [(status, body)] = fetch_with(f"{server}/status/409")
    assert status == 409 and b"status 409 as asked" in body


def test_a_body_that_runs_until_the_server_closes_arrives_whole() -> None:
    reply = b"HTTP/1.0 200 OK\r\nContent-Type: text/plain\r\n\r\n" + pattern(50_000)
    with raw_server(reply) as url:
        [(status, body)] = fetch_with(f"{url}/")
    assert status == 200 and body == pattern(50_000)


def test_a_second_answer_to_one_request_is_not_taken_for_the_first() -> None:
    # Both answers arrive in one piece: the first is the request's, whole; the second changes nothing.
    reply = b"HTTP/1.1 200 OK\r\nContent-Length: 2\r\n\r\nokHTTP/1.1 500 No\r\nContent-Length: 3\r\n\r\nbad"
    with raw_server(reply) as url:
        assert fetch_with(f"{url}/", times=2) == [(200, b"ok"), (200, b"ok")]


def test_an_informational_answer_before_the_real_one_is_skipped() -> None:
    reply = b"HTTP/1.1 100 Continue\r\n\r\nHTTP/1.1 200 OK\r\nContent-Length: 2\r\n\r\nok"
    with raw_server(reply) as url:
        assert fetch_with(f"{url}/") == [(200, b"ok")]


@pytest.mark.parametrize(
    ("reply", "what"),
    [
        (b"HTTP/1.1 200 OK\r\nContent-Length: 10\r\n\r\n01234", "closed the connection inside the answer's body"),
        (b"", "closed the connection before the answer's head"),
        (b"HTTP/1.1 101 Switching Protocols\r\nUpgrade: x\r\nConnection: upgrade\r\n\r\n", "switched protocols"),
        (b"HTTP/1.1 200 OK\r\nContent-Length: 2\r\nTransfer-Encoding: chunked\r\n\r\n", "malformed answer"),
    ],
    ids=["cut-body", "no-head", "upgrade", "length-and-chunked"],
)
def test_a_broken_answer_on_the_lean_path_is_a_remote_protocol_error_naming_why(reply: bytes, what: str) -> None:
    with raw_server(reply) as url, pytest.raises(httpx.RemoteProtocolError, match=what):
        fetch_with(f"{url}/")


@pytest.mark.parametrize("header", [("X-Test", "a\r\nInjected: yes"), ("X-Te\nst", "a"), ("X-Test", "a\x00")])
def test_a_header_that_would_split_the_request_is_refused_before_sending(server: str, header: tuple[str, str]) -> None:
    with pytest.raises(httpx.LocalProtocolError, match="cannot be sent"):
        fetch_with(f"{server}/echo", "POST", (header,), b"x")


def test_the_lean_path_refuses_a_connection_it_cannot_make(refusing_port: int) -> None:
    with pytest.raises(httpx.ConnectError, match=f"127.0.0.1:{refusing_port}"):
        fetch_with(f"http://127.0.0.1:{refusing_port}/v1/step", "POST", (), b"x")


def test_the_lean_path_refuses_a_url_that_is_not_http() -> None:
    with pytest.raises(httpx.UnsupportedProtocol, match="only http and https"):
        fetch_with("ftp://127.0.0.1/x")


@contextlib.contextmanager
def closing_after_one_answer(answers: list[int]) -> Iterator[str]:
    """A loopback server that answers the first request of each connection (kept alive), then
    reads the next one and closes without a byte: a server closing an idle connection as a
    request crosses its close. ``answers`` gets the number of the connection of each answer."""

    def answer_once(conn: socket.socket, number: int) -> None:
        conn.recv(65536)
        conn.sendall(b"HTTP/1.1 200 OK\r\nContent-Length: %d\r\n\r\n%d" % (len(str(number)), number))
        answers.append(number)
        conn.recv(65536)

    with socket_server(answer_once) as url:
        yield url


def test_a_kept_alive_connection_closed_as_the_request_went_out_is_retried_once_on_a_new_one() -> None:
    answers: list[int] = []
    with closing_after_one_answer(answers) as url:
        got = fetch_with(f"{url}/", times=3)
    assert got == [(200, b"1"), (200, b"2"), (200, b"3")] and answers == [1, 2, 3]


def test_the_httpx_interface_retries_a_closed_kept_alive_connection_alike() -> None:
    answers: list[int] = []
    with closing_after_one_answer(answers) as url:

        async def use(client: httpx.AsyncClient) -> list[bytes]:
            return [(await client.get(f"{url}/")).content for _ in range(3)]

        assert run_with("httptools", use) == [b"1", b"2", b"3"]


def test_a_new_connection_closed_before_its_answer_is_not_retried() -> None:
    requests: list[bytes] = []
    with raw_server(b"", requests) as url, pytest.raises(httpx.RemoteProtocolError, match="before the answer's head"):
        fetch_with(f"{url}/")
    assert len(requests) == 1


@pytest.mark.parametrize("lean", [True, False], ids=["lean", "httpx"])
def test_an_answer_head_larger_than_the_cap_is_refused_naming_it(lean: bool) -> None:
    reply = b"HTTP/1.1 200 OK\r\nX-Big: " + b"a" * (MAX_HEAD_BYTES + 1) + b"\r\nContent-Length: 2\r\n\r\nok"
    with (
        raw_server(reply) as url,
        pytest.raises(httpx.RemoteProtocolError, match=f"head is larger than {MAX_HEAD_BYTES} bytes"),
    ):
        if lean:
            fetch_with(f"{url}/")
        else:
            run_with("httptools", lambda c: c.get(f"{url}/"))


def test_an_answer_head_that_never_ends_is_refused_at_the_cap() -> None:
    reply = b"HTTP/1.1 200 OK\r\nX-Big: " + b"a" * (4 * MAX_HEAD_BYTES)  # and the server closes
    with (
        raw_server(reply) as url,
        pytest.raises(httpx.RemoteProtocolError, match=f"head is larger than {MAX_HEAD_BYTES} bytes"),
    ):
        fetch_with(f"{url}/")


def test_an_answer_head_just_under_the_cap_arrives() -> None:
    reply = b"HTTP/1.1 200 OK\r\nX-Big: " + b"a" * (MAX_HEAD_BYTES - 100) + b"\r\nContent-Length: 2\r\n\r\nok"
    with raw_server(reply) as url:
        assert fetch_with(f"{url}/") == [(200, b"ok")]


def test_idle_connections_beyond_the_bound_are_closed_as_they_come_back() -> None:
    with uvicorn_server() as served:

        async def main() -> None:
            async with HttptoolsTransport(max_idle_per_origin=2) as transport:
                url = f"{served.url}/peer?together=6"
                answers = await asyncio.gather(*(transport.fetch("GET", url, (), b"", 1 << 20) for _ in range(6)))
                assert len({body for _, body in answers}) == 6  # six connections at once
                await asyncio.to_thread(wait_until, lambda: served.connections() == 2, "4 of 6 connections closed", 10)

        asyncio.run(main())


def test_a_negative_idle_bound_is_refused_naming_it() -> None:
    with pytest.raises(ValueError, match="max_idle_per_origin must be >= 0"):
        HttptoolsTransport(max_idle_per_origin=-1)


@pytest.fixture(scope="module")
def tls_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, Path]]:
    """The test app over TLS on loopback, with a self-signed certificate for 127.0.0.1 made by
    the openssl command; yields its URL and the certificate."""
    if shutil.which("openssl") is None:
        pytest.skip("no openssl command to make a certificate with")
    folder = tmp_path_factory.mktemp("tls")
    key, cert = folder / "key.pem", folder / "cert.pem"
    subprocess.run(
        [
            "openssl",
            "req",
            "-x509",
            "-newkey",
            "rsa:2048",
            "-nodes",
            "-days",
            "1",
            "-subj",
            "/CN=127.0.0.1",
            "-addext",
            "subjectAltName=IP:127.0.0.1",
            "-keyout",
            str(key),
            "-out",
            str(cert),
        ],
        check=True,
        capture_output=True,
        timeout=60,
    )
    with uvicorn_server(ssl_keyfile=str(key), ssl_certfile=str(cert)) as served:
        yield served.url.replace("http://", "https://"), cert


def test_an_https_pod_is_reached_over_tls_with_its_certificate_checked(tls_server: tuple[str, Path]) -> None:
    url, cert = tls_server

    async def main(context: ssl.SSLContext | None) -> tuple[int, bytes]:
        transport = HttptoolsTransport(ssl_context=context)
        try:
            return await transport.fetch("GET", f"{url}/bytes/70000", (), b"", 1 << 20)
        finally:
            await transport.aclose()

    assert asyncio.run(main(ssl.create_default_context(cafile=str(cert)))) == (200, pattern(70_000))
    with pytest.raises(httpx.ConnectError, match="CERTIFICATE_VERIFY_FAILED"):
        asyncio.run(main(None))  # the system's trust store does not know this certificate


# ------------------------------------------------------------------------------ the seam


def test_the_one_kind_is_httptools_and_httpx_own_connections_are_refused_naming_why() -> None:
    assert isinstance(make_transport(), HttptoolsTransport) and DEFAULT_KIND == "httptools"
    with pytest.raises(ValueError, match="kind: 'httpx' is not one of"):
        make_transport("httpx")  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="AsyncHTTPTransport reaches pods without vecsim's bounds"):
        as_transport(httpx.AsyncHTTPTransport())


def test_a_plain_httpx_transport_is_wrapped_and_a_transport_kept_as_it_is() -> None:
    asgi = httpx.ASGITransport(app)
    wrapped = as_transport(asgi)
    assert isinstance(wrapped, HttpxTransport) and wrapped.wrapped is asgi
    ours = HttptoolsTransport()
    assert as_transport(ours) is ours
    assert isinstance(as_transport(None), HttptoolsTransport)


def test_something_that_is_no_transport_is_refused_naming_its_type() -> None:
    with pytest.raises(TypeError, match="got str"):
        as_transport("http://127.0.0.1:8100")  # type: ignore[arg-type]


def test_an_in_process_pod_is_fetched_through_the_same_interface() -> None:
    async def main() -> tuple[int, bytes]:
        async with as_transport(httpx.ASGITransport(app)) as transport:
            return await transport.fetch("GET", "http://pod/bytes/70000", (), b"", 1 << 20)

    assert asyncio.run(main()) == (200, pattern(70_000))


@pytest.mark.parametrize("lean", [True, False], ids=["fetch", "httpx-client"])
def test_failures_leave_the_transport_as_httpx_own_types(refusing_port: int, lean: bool) -> None:
    """One table maps the transport's failures: what a caller meets is httpx's exception itself
    (or ``AnswerTooLargeError``), whatever the transport named it inside."""
    replies = {
        httpx.RemoteProtocolError: b"NOT HTTP AT ALL\r\n\r\n",
        httpx.DecodingError: b"HTTP/1.1 200 OK\r\nContent-Encoding: gzip\r\nContent-Length: 8\r\n\r\nnot gzip",
        AnswerTooLargeError: b"HTTP/1.1 200 OK\r\nContent-Length: 100000000000\r\n\r\n",
    }

    def met(url: str) -> type[BaseException]:
        try:
            read_with("httptools" if lean else "httptools/httpx", url, 1 << 20)
        except httpx.HTTPError as exc:
            return type(exc)
        raise AssertionError("no failure")

    assert met(f"http://127.0.0.1:{refusing_port}/") is httpx.ConnectError
    for expected, reply in replies.items():
        with raw_server(reply) as url:
            assert met(f"{url}/") is expected


@pytest.mark.parametrize("kind", KINDS)
def test_a_connection_not_accepted_in_time_is_a_connect_timeout(kind: str) -> None:
    """A listener whose backlog is full drops further SYNs: the connect times out, and says so
    as httpx's ``ConnectTimeout`` (a ``TimeoutError`` is an ``OSError``: the map must not take
    it for a refused connection)."""
    with contextlib.ExitStack() as stack:
        listener = stack.enter_context(socket.socket())
        listener.bind(("127.0.0.1", 0))
        listener.listen(0)
        port = listener.getsockname()[1]
        for _ in range(8):  # fill the backlog; these are never accepted
            filler = stack.enter_context(socket.socket())
            filler.setblocking(False)
            with contextlib.suppress(BlockingIOError):
                filler.connect(("127.0.0.1", port))
        with pytest.raises(httpx.ConnectTimeout):
            run_with(kind, lambda c: c.get(f"http://127.0.0.1:{port}/"), timeout=httpx.Timeout(10, connect=0.3))
