"""Answer benchmark: how fast a pod's big wire answers (camera frames) leave it, old path against new.

A real uvicorn + FastAPI server (its own process, loopback, the pod's own uvicorn protocol and
limits) answers ``POST /{path}/{envs}`` with a step's answer for ``envs`` envs of two 256x256
cameras (uint8 frames, as an ``mjwarp`` pod's chunk step), encoded on a worker thread as the pod
does it, by one of three answer paths:

- ``old``: the whole message joined into one ``bytes`` (``wire.encode``) and handed to
  ``Response`` in one piece, as the pod answered before (uvicorn's transport then keeps a copy
  of what the socket did not take at once); labelled ``application/octet-stream``, so that the
  client's transport reads it as it read every answer before: pieces kept, joined at the end;
- ``new-pod``: the pod's own answer (``service.pod.bodies.Answer``: the encoded parts, views of
  the arrays, sent in slices of ``SLICE_BYTES`` under uvicorn's flow control), labelled as
  ``old`` is: the pod's side of the change alone;
- ``new``: the pod's own ``service.pod.bodies.encode_answer``, labelled as the wire: the client's
  transport reads its body past the parser, straight into one buffer of its length.

The client is the trainer's transport (``vecsim.transport.make_transport().fetch``, the
answer read whole under a cap) and, with ``--httpx``, a synchronous ``httpx.Client`` (what
``bench_mjwarp.py side`` reads answers with; it reads every path alike). Every answer of the warm-up is decoded and checked
bit for bit against the arrays. Rounds interleave the paths (order rotating); ratios new/old are
taken within a round, the median over rounds reported.

    python bench/bench_answer.py [--rounds 5] [--envs 2 162 325 1024] [--httpx]

Prints ``RESULT {json}`` and writes out/bench/bench_answer.json.
"""

from __future__ import annotations

import argparse
import asyncio
import socket
import sys
import time
from typing import Any

import httpx
import numpy as np
import psutil
from lib.served import server_process
from lib.records import spread, write_result

from vecsim import wire
from vecsim.transport import make_transport

CAMERAS = ("agentview", "robot0_eye_in_hand")
SIZE = 256
K = 8
PATHS = ("old", "new-pod", "new")
# How the old path's answers are labelled: a type the client's transport reads as it did before.
OLD_TYPE = "application/octet-stream"
MAX_ENVS = 2048
MAX_ANSWER = 1 << 31

Table = dict[str, dict[int, list[float]]]


def answer_of(envs: int) -> dict[str, Any]:
    """A chunk step's answer for ``envs`` envs (frames random: nothing to compress), as the pod's
    step route builds it before encoding."""
    rng = np.random.default_rng(envs)
    return {
        "env_indices": np.arange(envs, dtype=np.int32),
        "obs": {
            "images": {name: rng.integers(0, 256, (envs, SIZE, SIZE, 3), dtype=np.uint8) for name in CAMERAS},
            "state": rng.standard_normal((envs, 8)).astype(np.float32),
        },
        "reward": np.zeros((envs, K)),
        "terminated": np.zeros((envs, K), dtype=bool),
        "truncated": np.zeros((envs, K), dtype=bool),
        "num_steps": np.full(envs, K, dtype=np.int32),
        "info": {"success": np.zeros((envs, K), dtype=bool)},
    }


def serve(fd: int) -> None:
    """Run the answer server on the listening socket ``fd`` (in the child process)."""
    import uvicorn
    from fastapi import FastAPI, HTTPException, Response
    from starlette.concurrency import run_in_threadpool

    from service.pod.bodies import Answer, encode_answer
    from service.serving import uvicorn_limits
    from service.settings import ServerSettings

    app = FastAPI()
    answers: dict[int, dict[str, Any]] = {}

    def encode_old(obj: dict[str, Any]) -> Response:
        return Response(content=wire.encode(obj), media_type=OLD_TYPE)

    def encode_new_pod(obj: dict[str, Any]) -> Answer:
        return Answer(encode_answer(obj, False).parts, OLD_TYPE)

    @app.post("/{path}/{envs}")
    async def step(path: str, envs: int) -> Response:
        if path not in PATHS or not 0 < envs <= MAX_ENVS:
            raise HTTPException(422, f"path: one of {PATHS}; envs: 1..{MAX_ENVS}")
        if envs not in answers:
            answers[envs] = answer_of(envs)
        if path == "old":
            return await run_in_threadpool(encode_old, answers[envs])
        if path == "new-pod":
            return await run_in_threadpool(encode_new_pod, answers[envs])
        return await run_in_threadpool(encode_answer, answers[envs], False)

    limits = ServerSettings.model_fields
    # The pod's limits, but a keep-alive of a minute: the old path's answer ends for uvicorn once
    # it is buffered, seconds before the client has read it, and its 5 s would close connections
    # the client is about to reuse between rounds.
    config = uvicorn.Config(
        app,
        log_level="warning",
        access_log=False,
        **uvicorn_limits(limits["header_timeout_s"].default, 60.0, limits["max_connections"].default),
    )
    uvicorn.Server(config).run(sockets=[socket.socket(fileno=fd)])


def check(body: bytes, envs: int, expected: dict[str, Any]) -> None:
    """The answer decodes to the arrays the server encoded, bit for bit."""
    got = wire.decode(body)
    for name in CAMERAS:
        if not np.array_equal(got["obs"]["images"][name], expected["obs"]["images"][name]):
            raise SystemExit(f"{envs} envs: camera {name} differs from what was encoded")
    if not np.array_equal(got["obs"]["state"], expected["obs"]["state"]):
        raise SystemExit(f"{envs} envs: state differs from what was encoded")


def _cpu(process: psutil.Process) -> float:
    times = process.cpu_times()
    return times.user + times.system


async def measure(
    url: str, server: psutil.Process, sizes: list[int], rounds: int, clients: list[str]
) -> tuple[Table, Table, Table, dict[int, int]]:
    """Per contender (``client/path``) per env count, one figure a round: GB/s received, and the
    server's and this process's CPU milliseconds per answer."""
    transport = make_transport()
    sync = httpx.Client(timeout=600)

    async def fetch(client: str, path: str, envs: int) -> bytes:
        if client == "vecsim":
            status, body = await transport.fetch("POST", f"{url}/{path}/{envs}", (), b"", MAX_ANSWER)
        else:
            response = sync.post(f"{url}/{path}/{envs}")
            status, body = response.status_code, response.content
        if status != 200:
            raise SystemExit(f"{client}/{path}/{envs}: status {status}")
        return body

    contenders = [(client, path) for client in clients for path in PATHS]
    gbps = {f"{c}/{p}": {n: [] for n in sizes} for c, p in contenders}
    server_ms = {f"{c}/{p}": {n: [] for n in sizes} for c, p in contenders}
    client_ms = {f"{c}/{p}": {n: [] for n in sizes} for c, p in contenders}
    me = psutil.Process()
    nbytes: dict[int, int] = {}
    try:
        for n in sizes:  # warm-up: every path's answer checked bit for bit
            expected = answer_of(n)
            for client, path in contenders:
                body = await fetch(client, path, n)
                check(body, n, expected)
                nbytes[n] = len(body)
            del expected, body
        for r in range(rounds):
            for n in sizes:
                reps = max(2, -(-(64 << 20) // nbytes[n]))
                order = contenders[r % len(contenders) :] + contenders[: r % len(contenders)]
                for client, path in order:
                    before, mine = _cpu(server), _cpu(me)
                    start = time.perf_counter()
                    for _ in range(reps):
                        if len(await fetch(client, path, n)) != nbytes[n]:
                            raise SystemExit(f"{client}/{path}/{n}: short answer")
                    gbps[f"{client}/{path}"][n].append(reps * nbytes[n] / (time.perf_counter() - start) / 1e9)
                    server_ms[f"{client}/{path}"][n].append((_cpu(server) - before) / reps * 1e3)
                    client_ms[f"{client}/{path}"][n].append((_cpu(me) - mine) / reps * 1e3)
            print(f"round {r + 1}/{rounds} done", file=sys.stderr, flush=True)
    finally:
        await transport.aclose()
        sync.close()
    return gbps, server_ms, client_ms, nbytes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=5, help="interleaved rounds (default 5)")
    parser.add_argument("--envs", type=int, nargs="+", default=[2, 162, 325, 1024], help="envs of 2x256x256 per answer")
    parser.add_argument("--httpx", action="store_true", help="also read answers with a synchronous httpx.Client")
    parser.add_argument("--name", default="bench_answer", help="the record's name (out/bench/NAME.json)")
    parser.add_argument("--serve-fd", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.serve_fd is not None:
        serve(args.serve_fd)
        return
    clients = ["vecsim", "httpx"] if args.httpx else ["vecsim"]
    with server_process(__file__, "POST", "/new/1", "answer server") as (url, server):
        gbps, server_ms, client_ms, nbytes = asyncio.run(measure(url, server, args.envs, args.rounds, clients))

    def label(n: int) -> str:
        return f"{nbytes[n] / 1e6:.3g} MB"

    summary = {
        "envs": args.envs,
        "answer_mb": {str(n): round(nbytes[n] / 1e6, 2) for n in args.envs},
        "rounds": args.rounds,
        "gbps_median": {c: {label(n): round(spread(v[n])["median"], 3) for n in args.envs} for c, v in gbps.items()},
        # GB/s of each new path over the old one's, medians of per-round ratios.
        "over_old": {
            f"{client}/{path}": {
                label(n): round(
                    spread([a / b for a, b in zip(gbps[f"{client}/{path}"][n], gbps[f"{client}/old"][n])])["median"],
                    2,
                )
                for n in args.envs
            }
            for client in clients
            for path in PATHS[1:]
        },
        # CPU time in clock ticks of 10 ms: means over all rounds.
        "server_cpu_ms_per_answer": {
            c: {label(n): round(float(np.mean(v[n])), 1) for n in args.envs} for c, v in server_ms.items()
        },
        "client_cpu_ms_per_answer": {
            c: {label(n): round(float(np.mean(v[n])), 1) for n in args.envs} for c, v in client_ms.items()
        },
    }
    details = {
        "gbps": {c: {label(n): v[n] for n in args.envs} for c, v in gbps.items()},
        "server_cpu_ms": {c: {label(n): v[n] for n in args.envs} for c, v in server_ms.items()},
        "client_cpu_ms": {c: {label(n): v[n] for n in args.envs} for c, v in client_ms.items()},
    }
    write_result(args.name, summary, details)


if __name__ == "__main__":
    main()
