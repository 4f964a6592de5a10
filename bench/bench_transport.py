"""Transport benchmark: how fast large response bodies reach the client, per HTTP client stack.

A real uvicorn server (FastAPI, in its own process, on a loopback port the kernel picked) serves
0.1 (a pod's answer of four LIBERO envs with two 64x64 cameras), 1, 4 and 16 MiB bodies. The
contenders fetch them one after another over a keep-alive connection, on one event loop:

- ``httpx``: httpx's default ``AsyncClient()`` (the baseline),
- ``aiohttp``: a plain ``aiohttp.ClientSession()``,
- ``vecsim-httptools`` and ``vecsim-httpx``: how the trainer's client reads an answer,
  ``Transport.fetch``, the answer read under a cap (httptools: vecsim's HTTP/1.1 client on
  llhttp, ``make_transport()``; httpx: ``HttpxTransport`` handing the request straight to
  ``httpx.AsyncHTTPTransport``, a kind of vecsim's until it failed the hostile-answer tests),
- ``old-handwritten`` (with ``--old-transport PATH``): the hand-written HTTP/1.1 client vecsim
  used before (``git show <rev>:vecsim/transport.py > PATH``), its ``make_async_client("fast")``.

Rounds interleave the contenders (and rotate their order) so that load from other processes
hits all alike; ratios are taken within each round and the median over rounds is reported.

    python bench/bench_transport.py [--rounds 8] [--loop asyncio|uvloop] [--profile] [--old-transport PATH]

Prints ``RESULT {json}``, writes out/bench/bench_transport[_uvloop].json and the plot
docs/img/bench_transport[_uvloop].png. ``--profile`` also writes a cProfile of the fast
transport on 16 MiB bodies to out/bench/bench_transport_profile.txt.
"""

from __future__ import annotations

import argparse
import asyncio
import cProfile
import importlib.util
import io
import math
import pstats
import socket
import statistics
import sys
import time
from collections.abc import Awaitable, Callable

import aiohttp
import httpx
import numpy as np
import psutil
from lib.served import server_process
from lib.records import img_dir, machine_info, out_dir, spread, write_result

from vecsim.transport import DEFAULT_KIND, HttpxTransport, make_transport

MIB = 1 << 20
SIZES = (MIB // 10, 1 * MIB, 4 * MIB, 16 * MIB)
MAX_BODY = 64 * MIB
FAST = f"vecsim-{DEFAULT_KIND}"

Fetch = Callable[[str], Awaitable[bytes]]


def _label(n: int, space: str = " ") -> str:
    """A body size as the results name it: ``0.1 MiB``, ``16 MiB``."""
    return f"{n / MIB:.3g}{space}MiB"


def body_of(n: int) -> bytes:
    """The ``n`` bytes the server sends for ``/bytes/n`` (random: nothing to compress)."""
    return np.random.default_rng(n).integers(0, 256, n, dtype=np.uint8).tobytes()


def serve(fd: int) -> None:
    """Run the benchmark server on the listening socket ``fd`` (in the child process)."""
    import uvicorn
    from fastapi import FastAPI, HTTPException
    from fastapi.responses import Response

    app = FastAPI()
    bodies: dict[int, bytes] = {}

    @app.get("/bytes/{n}")
    def get_bytes(n: int) -> Response:
        if not 0 <= n <= MAX_BODY:
            raise HTTPException(422, f"n must be in 0..{MAX_BODY}")
        if n not in bodies:
            bodies[n] = body_of(n)
        return Response(bodies[n], media_type="application/octet-stream")

    # Not uvicorn's fd=: it takes the socket for AF_UNIX, so accepted connections miss
    # TCP_NODELAY and small answers stall on Nagle + delayed ACK (40 ms each).
    config = uvicorn.Config(app, log_level="warning", access_log=False)
    uvicorn.Server(config).run(sockets=[socket.socket(fileno=fd)])


Table = dict[str, dict[int, list[float]]]


def _cpu(process: psutil.Process) -> float:
    times = process.cpu_times()
    return times.user + times.system


def load_old_transport(path: str) -> object:
    """The module at ``path`` (an old ``vecsim/transport.py``), imported under its own name."""
    spec = importlib.util.spec_from_file_location("vecsim_old_transport", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


async def measure(
    url: str, server: psutil.Process, sizes: tuple[int, ...], rounds: int, min_bytes: int, old: object | None
) -> tuple[Table, Table, Table]:
    """Per contender per body size, one figure per round: GB/s, and the CPU milliseconds per
    request spent by the client process and by the server process (these in clock ticks of
    10 ms: average them over all rounds, not per round)."""
    httpx_default = httpx.AsyncClient()
    aiohttp_plain = aiohttp.ClientSession()
    ours = {"httptools": make_transport(), "httpx": HttpxTransport(httpx.AsyncHTTPTransport(trust_env=False))}
    old_client = old.make_async_client("fast") if old is not None else None

    async def via_httpx(target: str) -> bytes:
        return (await httpx_default.get(target)).content

    async def via_aiohttp(target: str) -> bytes:
        async with aiohttp_plain.get(target) as response:
            return await response.read()

    def via_ours(kind: str) -> Fetch:
        async def get(target: str) -> bytes:
            return (await ours[kind].fetch("GET", target, (), b"", MAX_BODY))[1]

        return get

    async def via_old(target: str) -> bytes:
        return (await old_client.get(target)).content

    contenders: dict[str, Fetch] = {
        "httpx": via_httpx,
        "aiohttp": via_aiohttp,
        "vecsim-httptools": via_ours("httptools"),
        "vecsim-httpx": via_ours("httpx"),
    }
    if old_client is not None:
        contenders["old-handwritten"] = via_old
    expected = {n: body_of(n) for n in sizes}
    gbps: Table = {name: {n: [] for n in sizes} for name in contenders}
    client_ms: Table = {name: {n: [] for n in sizes} for name in contenders}
    server_ms: Table = {name: {n: [] for n in sizes} for name in contenders}
    me = psutil.Process()
    names = list(contenders)
    try:
        for n in sizes:  # warm-up: connections open, server bodies built, every answer checked
            for name, get in contenders.items():
                if await get(f"{url}/bytes/{n}") != expected[n]:
                    raise SystemExit(f"{name}: wrong body for {n} bytes")
        for r in range(rounds):
            for n in sizes:
                reps = max(2, math.ceil(min_bytes / n))
                for name in names[r % len(names) :] + names[: r % len(names)]:
                    get = contenders[name]
                    cpu_client, cpu_server = _cpu(me), _cpu(server)
                    start = time.perf_counter()
                    for _ in range(reps):
                        if len(await get(f"{url}/bytes/{n}")) != n:
                            raise SystemExit(f"{name}: short body for {n} bytes")
                    gbps[name][n].append(reps * n / (time.perf_counter() - start) / 1e9)
                    client_ms[name][n].append((_cpu(me) - cpu_client) / reps * 1e3)
                    server_ms[name][n].append((_cpu(server) - cpu_server) / reps * 1e3)
            print(f"round {r + 1}/{rounds} done", file=sys.stderr, flush=True)
    finally:
        await httpx_default.aclose()
        await aiohttp_plain.close()
        for transport in ours.values():
            await transport.aclose()
        if old_client is not None:
            await old_client.aclose()
    return gbps, client_ms, server_ms


async def profile_fast(url: str, sizes: tuple[int, ...], reps: int) -> str:
    """cProfile of the fast client fetching each body size, top functions by own time."""
    text = io.StringIO()
    async with make_transport() as transport:

        async def get(n: int) -> bytes:
            return (await transport.fetch("GET", f"{url}/bytes/{n}", (), b"", MAX_BODY))[1]

        for n in sizes:
            await get(n)
            profiler = cProfile.Profile()
            profiler.enable()
            for _ in range(reps):
                await get(n)
            profiler.disable()
            text.write(f"==== {FAST}, {reps} x {_label(n)} ====\n")
            pstats.Stats(profiler, stream=text).sort_stats("tottime").print_stats(15)
    return text.getvalue()


def plot(medians: dict[str, dict[int, dict[str, float]]], sizes: tuple[int, ...], path: str, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(medians)
    width = 0.8 / len(names)
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for i, name in enumerate(names):
        xs = [j + (i - (len(names) - 1) / 2) * width for j in range(len(sizes))]
        mid = [medians[name][n]["median"] for n in sizes]
        low = [m - medians[name][n]["min"] for m, n in zip(mid, sizes)]
        high = [medians[name][n]["max"] - m for m, n in zip(mid, sizes)]
        ax.bar(xs, mid, width, yerr=[low, high], capsize=3, label=name)
    ax.set_xticks(range(len(sizes)), [_label(n) for n in sizes])
    ax.set_xlabel("response body")
    ax.set_ylabel("GB/s received (median over rounds, bars: min-max)")
    ax.set_title(title, fontsize=10)
    ax.legend()
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=8, help="interleaved rounds (default 8)")
    parser.add_argument("--min-mib", type=int, default=48, help="MiB fetched per contender per size per round")
    parser.add_argument("--sizes-mib", type=float, nargs="+", default=[n / MIB for n in SIZES], help="body sizes")
    parser.add_argument("--loop", choices=("asyncio", "uvloop"), default="asyncio", help="client event loop")
    parser.add_argument("--profile", action="store_true", help="also profile the fast transport")
    parser.add_argument("--old-transport", help="an old vecsim/transport.py to measure beside (git show)")
    parser.add_argument("--serve-fd", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.serve_fd is not None:
        serve(args.serve_fd)
        return

    if args.loop == "uvloop":
        import uvloop

        runner: Callable[..., object] = uvloop.run
    else:
        runner = asyncio.run
    name = "bench_transport" if args.loop == "asyncio" else f"bench_transport_{args.loop}"

    sizes = tuple(round(n * MIB) for n in args.sizes_mib)
    with server_process(__file__, "GET", "/bytes/1", "benchmark server") as (url, server):
        old = load_old_transport(args.old_transport) if args.old_transport else None
        gbps, client_ms, server_ms = runner(measure(url, server, sizes, args.rounds, args.min_mib * MIB, old))
        profile = runner(profile_fast(url, sizes, 6)) if args.profile else None

    medians = {c: {n: spread(v) for n, v in per_size.items()} for c, per_size in gbps.items()}

    def per_size(table: Table, reduce: Callable[[list[float]], float], digits: int = 2) -> dict[str, dict[str, float]]:
        return {c: {_label(n, ""): round(reduce(v[n]), digits) for n in sizes} for c, v in table.items()}

    def ratio(a: str, b: str) -> dict[str, float]:
        return {
            _label(n, ""): round(spread([x / y for x, y in zip(gbps[a][n], gbps[b][n])])["median"], 2) for n in sizes
        }

    summary = {
        "loop": args.loop,
        "default_kind": DEFAULT_KIND,
        "GBps_median": per_size(gbps, statistics.median, digits=3),
        "default_vs_httpx": ratio(FAST, "httpx"),
        "default_vs_aiohttp": ratio(FAST, "aiohttp"),
        "vecsim_httptools_vs_vecsim_httpx": ratio("vecsim-httptools", "vecsim-httpx"),
        "aiohttp_vs_httpx": ratio("aiohttp", "httpx"),
        # CPU per request (ms), mean over all rounds: where the time goes on shared cores.
        "client_cpu_ms": per_size(client_ms, statistics.fmean),
        "server_cpu_ms": per_size(server_ms, statistics.fmean),
        "target": f"{FAST} >= 0.9x plain aiohttp at every size (the library's own speed, kept)",
    }
    if old is not None:
        summary["default_vs_old_handwritten"] = ratio(FAST, "old-handwritten")
    summary["target_met"] = all(v >= 0.9 for v in summary["default_vs_aiohttp"].values())
    machine = machine_info()
    png = img_dir() / f"{name}.png"
    plot(
        medians,
        sizes,
        str(png),
        f"Response bodies from uvicorn on loopback, {args.loop} client loop\n"
        f"{machine['cores']} cores ({machine['cpu']}), {machine['date'][:10]}, load {machine['load_avg_1m']}",
    )
    summary["plot"] = str(png.relative_to(img_dir().parent.parent))
    if profile is not None:
        (out_dir() / f"{name}_profile.txt").write_text(profile)
    details = {
        "rounds": args.rounds,
        "min_mib_per_round": args.min_mib,
        "GBps_per_round": {c: {_label(n, ""): v for n, v in per_size.items()} for c, per_size in gbps.items()},
    }
    write_result(name, summary, details)


if __name__ == "__main__":
    main()
