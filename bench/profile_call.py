"""Where the time of one ``HTTPVectorEnv.step`` goes: 16 HalfCheetah-v5 envs on one pod, layer by layer.

A diagnosis, not a benchmark with a target. One run starts two real pods of the same assignment
(16 ``gym/HalfCheetah-v5`` envs, no camera, ``envs_per_worker: auto``), each a ``vecsim pod``
started through this file (``--serve-pod``) so that timers can be put around the pod's own
functions before it serves:

- the *timed* pod wraps its layers in wall-clock timers (a few microseconds each) and writes
  per-call sums when asked (SIGUSR1);
- the *profiled* pod runs its main thread (where cheap scenes are stepped, ``state.inline``)
  under cProfile.

Contenders, each timed per call, interleaved in rounds with the order rotating, medians reported:

- ``http_vector_env``: ``HTTPVectorEnv.step`` on the timed pod (the whole client);
- ``raw_httpx``: ``POST /v1/step`` of a body encoded once, through a sync ``httpx.Client``;
- ``raw_http_client``: the same through the standard library's ``http.client`` (keep-alive);
- ``raw_healthz``: ``GET /healthz`` through ``http.client``: HTTP + uvicorn + FastAPI, no work;
- ``bare_http_client``: the same ``POST /v1/step`` through ``http.client`` to a *bare* server
  (``--serve-bare``): the same worker pool stepped on an asyncio event loop (uvloop where
  installed) that parses requests with httptools and writes the answer (``wire.encode``) itself:
  no uvicorn, FastAPI, validation, thread hop, auth or limits. What serving this call over HTTP
  from Python costs at the least; not a product, a floor;
- ``in_process``: ``TaskGroupedVectorEnv.step_envs`` in this process (same workers, no HTTP);
- ``in_process_answer``: the same plus what the route adds (answer dict, ``batch_infos``,
  ``wire.encode``);
- ``async_vector_env``: gymnasium's ``AsyncVectorEnv`` of 16 envs, one process each;
- ``sync_vector_env``: the 16 envs in this one process (the ceiling).

Then the client's layers (timers in this process around ``HTTPVectorEnv``/``StageClient``/
``PodConnection``), the pod's layers (from the timed pod), and cProfile tops of the client (main
thread and its event-loop thread) and of the profiled pod.

    python bench/profile_call.py [--quick] [--calls 100] [--rounds 3] [--envs 16] [--envs-per-worker 0] [--profile-calls 300]
        [--task libero_10/0 --cameras agentview,robot0_eye_in_hand --size 64]

Prints a report on stdout and writes out/bench/profile_call.json.
"""

from __future__ import annotations

import argparse
import asyncio
import concurrent.futures
import contextlib
import cProfile
import functools
import http.client
import inspect
import io
import json
import logging
import os
import pstats
import signal
import statistics
import sys
import tempfile
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger("bench.profile_call")

TASK = "gym/HalfCheetah-v5"  # the default --task
# Long episodes: no truncation inside the measured calls, so every call is a plain step.
EPISODE_CAP = 1_000_000


class Timers:
    """Per-call sums of wall-clock time spent in wrapped functions (inclusive), by label.

    ``begin()`` opens a call, ``end()`` closes it and keeps its sums; time spent outside an open
    call is dropped. Calls do not overlap in this use (one step in flight at a time).
    """

    def __init__(self) -> None:
        self.calls: list[dict[str, float]] = []
        self._current: dict[str, float] | None = None

    def begin(self) -> None:
        self._current = defaultdict(float)

    def end(self, keep: bool = True) -> None:
        if keep and self._current is not None:
            self.calls.append(dict(self._current))
        self._current = None

    def add(self, label: str, seconds: float) -> None:
        if self._current is not None:
            self._current[label] += seconds

    def wrap(self, owner: Any, name: str, label: str | None = None) -> None:
        """Replace ``owner.name`` (a function, method or coroutine function) with a timed one."""
        label = label or name
        if not hasattr(owner, name):
            # The code under study moves on (the worker protocol is being rewritten): time what is left.
            log.warning("not timed: %s.%s no longer exists", getattr(owner, "__name__", owner), name)
            return
        original = inspect.getattr_static(owner, name)
        is_static = isinstance(original, staticmethod)
        fn = getattr(owner, name) if is_static else original
        if inspect.iscoroutinefunction(fn):

            @functools.wraps(fn)
            async def timed_async(*args: Any, **kwargs: Any) -> Any:
                started = time.perf_counter()
                try:
                    return await fn(*args, **kwargs)
                finally:
                    self.add(label, time.perf_counter() - started)

            wrapper: Any = timed_async
        else:

            @functools.wraps(fn)
            def timed(*args: Any, **kwargs: Any) -> Any:
                started = time.perf_counter()
                try:
                    return fn(*args, **kwargs)
                finally:
                    self.add(label, time.perf_counter() - started)

            wrapper = timed
        setattr(owner, name, staticmethod(wrapper) if is_static else wrapper)

    def medians_ms(self, skip: int = 0) -> dict[str, float]:
        """Median ms per call of each label over the kept calls (0 for a call that missed it)."""
        calls = self.calls[skip:]
        labels = sorted({label for call in calls for label in call})
        return {label: round(1e3 * statistics.median(c.get(label, 0.0) for c in calls), 3) for label in labels}


# -- the pod side (runs in the pod process, started with --serve-pod) -------------------------


def _instrument_pod(timers: Timers) -> None:
    """Put timers around the pod's layers, before its app is made."""
    import fastapi.routing

    import service.pod.main as pod_main
    import service.pod.routers.envs as routes
    from service.http import BearerTokenMiddleware, BodyLimitMiddleware
    from vecsim import wire
    from vecsim.engine import checks, pool, vector_env

    timers.wrap(BearerTokenMiddleware, "__call__", "pod.auth_middleware (incl. all below)")
    timers.wrap(BodyLimitMiddleware, "__call__", "pod.body_limit_middleware (incl. routing+route)")
    timers.wrap(fastapi.routing, "run_endpoint_function", "pod.route_function (incl. below)")
    timers.wrap(routes, "parse_body", "pod.parse_body (wire.decode+pydantic)")
    timers.wrap(wire, "decode", "pod.wire.decode")
    timers.wrap(routes, "_simulate", "pod.simulate (work(): step + answer + encode)")
    timers.wrap(vector_env.TaskGroupedVectorEnv, "step_envs", "pod.step_envs")
    timers.wrap(checks, "actions", "pod.step_envs.validate_actions")
    timers.wrap(vector_env.TaskGroupedVectorEnv, "_run", "pod.step_envs._run (lock+pipes+gather)")
    timers.wrap(pool.WorkerPool, "send", "pod.worker_pool.send (an order to one worker's pipe)")
    timers.wrap(pool.WorkerPool, "receive", "pod.worker_pool.receive (the workers' replies)")
    timers.wrap(vector_env.TaskGroupedVectorEnv, "_per_row", "pod.step_envs._per_row (info rows)")
    timers.wrap(routes, "batch_infos", "pod.batch_infos")
    timers.wrap(routes, "encode_answer", "pod.encode_answer (wire.encode + Response)")
    timers.wrap(wire, "encode", "pod.wire.encode")

    make_app = pod_main.create_app

    def create_timed_app(settings: Any) -> Any:
        app = make_app(settings)

        async def timed_app(scope: dict[str, Any], receive: Any, send: Any) -> None:
            timed = scope["type"] == "http" and scope["path"] == "/v1/step"
            if not timed:
                await app(scope, receive, send)
                return
            timers.begin()
            started = time.perf_counter()
            try:
                await app(scope, receive, send)
            finally:
                timers.add("pod.asgi_app (all of the app)", time.perf_counter() - started)
                physics = getattr(app.state.pod.env, "last_timing", None)
                if physics is not None:
                    timers.add("pod.workers_physics_s (sum over workers)", physics.physics_s)
                timers.end()

        timed_app.state = app.state  # type: ignore[attr-defined]
        return timed_app

    pod_main.create_app = create_timed_app  # type: ignore[assignment]


def serve_pod(mode: str, out: Path, pod_argv: list[str]) -> int:
    """Run ``vecsim pod`` with ``pod_argv``; ``mode`` "timed" (timers, written to ``out`` on
    SIGUSR1) or "profiled" (cProfile of the main thread, written to ``out`` on SIGUSR1)."""
    from service.pod import main as pod_main
    from vecsim.files import write_whole

    if mode == "timed":
        timers = Timers()
        _instrument_pod(timers)

        def dump(_signum: int, _frame: Any) -> None:
            record = {"calls": len(timers.calls), "median_ms": timers.medians_ms(skip=min(20, len(timers.calls) // 2))}
            write_whole(out, lambda tmp: tmp.write_text(json.dumps(record)))

        signal.signal(signal.SIGUSR1, dump)
        return pod_main.main(pod_argv)
    profile = cProfile.Profile()

    def dump_profile(_signum: int, _frame: Any) -> None:
        profile.disable()
        write_whole(out, lambda tmp: profile.dump_stats(str(tmp)))

    def clear_profile(_signum: int, _frame: Any) -> None:
        profile.clear()
        profile.enable()

    signal.signal(signal.SIGUSR1, dump_profile)
    signal.signal(signal.SIGUSR2, clear_profile)
    return pod_main.main(pod_argv)


def serve_bare(port: int) -> int:
    """A bare HTTP service of ``_assignment``'s worker pool, the floor the pod is measured against
    (``bare_http_client``): ``POST /v1/step`` with a wire body steps the envs on the event loop
    and answers what the pod answers; ``GET`` of anything answers 200 (the readiness probe). One
    process, one event loop, requests handled one at a time in arrival order."""
    import httptools

    from service.pod.routers.envs import step_answer
    from vecsim import wire
    from vecsim.engine import TaskGroupedVectorEnv

    env = TaskGroupedVectorEnv(_assignment("bare"))
    # A pod never resets a gym env it builds (the env starts as its factory left it), and a gym
    # env steps only after a reset: reset every env once, as the pod's clients do.
    every = np.arange(env.num_envs)
    env.reset_envs(every, every)
    head = "HTTP/1.1 {status}\r\nContent-Type: {kind}\r\nContent-Length: {length}\r\n\r\n"

    def answer(method: bytes, url: bytes, body: bytes) -> bytes:
        if method != b"POST":
            return head.format(status="200 OK", kind="text/plain", length=2).encode() + b"ok"
        if url != b"/v1/step":
            return head.format(status="404 Not Found", kind="text/plain", length=0).encode()
        request = wire.decode(body)
        ids = np.asarray(request["env_indices"])
        payload = wire.encode(step_answer(ids, env.step_envs(ids, request["actions"])))
        return head.format(status="200 OK", kind=wire.CONTENT_TYPE, length=len(payload)).encode() + payload

    class BareProtocol(asyncio.Protocol):
        def connection_made(self, transport: Any) -> None:
            self.transport = transport
            self.parser = httptools.HttpRequestParser(self)
            self.url = b""
            self.body: list[bytes] = []

        def data_received(self, data: bytes) -> None:
            try:
                self.parser.feed_data(data)
            except httptools.HttpParserError:
                self.transport.close()

        def on_url(self, url: bytes) -> None:
            self.url = url

        def on_body(self, body: bytes) -> None:
            self.body.append(body)

        def on_message_complete(self) -> None:
            body, self.body = b"".join(self.body), []
            self.transport.write(answer(self.parser.get_method(), self.url, body))

    async def serve() -> None:
        server = await asyncio.get_running_loop().create_server(BareProtocol, "127.0.0.1", port)
        async with server:
            await server.serve_forever()

    try:
        import uvloop

        runner: Callable[[Any], Any] = uvloop.run
    except ImportError:
        runner = asyncio.run
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    try:
        runner(serve())
    finally:
        env.close()
    return 0


@contextlib.contextmanager
def bare_process(workdir: Path) -> Iterator[Any]:
    """The bare server (:func:`serve_bare`) in its own process; stopped on exit."""
    from lib.pods import READY_TIMEOUT_S, Server, clean_env, free_port, running

    port = free_port()
    argv = ["--serve-bare", str(port), *sys.argv[1:]]
    server = Server("bare", argv, port, clean_env(), workdir / "bare.log", program=(sys.executable, __file__))
    with running(server):
        server.wait_ready(READY_TIMEOUT_S)
        yield server


# -- the client side -----------------------------------------------------------------------------


def _assignment(pod: str) -> Any:
    from vecsim.config import AUTO_ENVS_PER_WORKER, Assignment, CameraConfig, TaskBlock

    return Assignment(
        generation=0,
        job_id="profile",
        pod=pod,
        stage_id=0,
        tasks=(TaskBlock(task_id=ARGS.task, env_start=0, num_envs=ARGS.envs),),
        camera=CameraConfig(names=tuple(c for c in ARGS.cameras.split(",") if c), height=ARGS.size, width=ARGS.size),
        render="lean",
        envs_per_worker=ARGS.envs_per_worker or AUTO_ENVS_PER_WORKER,
        max_episode_steps=EPISODE_CAP,
    )


@contextlib.contextmanager
def pod_process(mode: str, workdir: Path) -> Iterator[Any]:
    """One pod of ``_assignment`` started through ``--serve-pod`` (a ``Server`` whose record
    goes beside its log, as ``<name>.out``: :func:`collect`); stopped on exit."""
    from lib.pods import READY_TIMEOUT_S, Server, clean_env, free_port, running

    name = f"sim-{mode}"
    path = workdir / f"{name}.json"
    path.write_text(json.dumps(_assignment(name).model_dump(mode="json")))
    port = free_port()
    log_path = workdir / f"{name}.log"
    argv = [
        "--serve-pod",
        mode,
        "--serve-out",
        str(log_path.with_suffix(".out")),
        "--",
        "--assignment",
        str(path),
        "--name",
        name,
        "--host",
        "127.0.0.1",
        "--port",
        str(port),
        "--log-level",
        "warning",
    ]
    server = Server(name, argv, port, clean_env(), log_path, program=(sys.executable, __file__))
    with running(server):
        server.wait_ready(READY_TIMEOUT_S)
        yield server


def collect(process: Any, timeout_s: float = 60.0) -> Path:
    """Ask a ``--serve-pod`` process for its record (SIGUSR1); return the file once written."""
    out: Path = process.log_path.with_suffix(".out")
    with contextlib.suppress(FileNotFoundError):
        out.unlink()
    os.kill(process.pid, signal.SIGUSR1)
    deadline = time.monotonic() + timeout_s
    while not out.exists():
        if time.monotonic() > deadline:
            raise RuntimeError(f"pod {process.url} wrote no record to {out}")
        time.sleep(0.1)
    return out


def cpu_snapshot(timed_pod: int, other_pod: int) -> dict[str, float]:
    """CPU seconds (user + system) used so far by: this process (``client``: all its threads),
    the timed pod's own process (``pod``), its env workers (``pod_workers``), and this process's
    other descendants (``local_workers``: the in-process contenders' worker processes)."""
    import psutil

    def used(process: psutil.Process) -> float:
        with contextlib.suppress(psutil.Error):
            times = process.cpu_times()
            return times.user + times.system
        return 0.0

    me = psutil.Process()
    pod = psutil.Process(timed_pod)
    pod_children = pod.children(recursive=True)
    skip = {timed_pod, other_pod, *(p.pid for p in pod_children)}
    with contextlib.suppress(psutil.Error):
        skip |= {p.pid for p in psutil.Process(other_pod).children(recursive=True)}
    return {
        "client": used(me),
        "pod": used(pod),
        "pod_workers": sum(used(p) for p in pod_children),
        "local_workers": sum(used(p) for p in me.children(recursive=True) if p.pid not in skip),
    }


def _instrument_client(timers: Timers) -> None:
    from vecsim import transport, wire
    from vecsim.client import HTTPVectorEnv
    from vecsim.client import calls, stage
    from vecsim.client.pods import PodConnection
    from vecsim.client.stage import StageClient
    from vecsim.client.vector_results import EnvResults

    timers.wrap(HTTPVectorEnv, "_send_step", "client._send_step (main thread: checks, submit)")
    timers.wrap(StageClient, "_submit", "client.StageClient._submit (checks, hand to loop)")
    timers.wrap(stage, "step_actions", "client.step_actions")
    timers.wrap(HTTPVectorEnv, "_take", "client._take (main thread waits for the loop)")
    timers.wrap(stage, "run_call", "client.run_call (on the loop thread)")
    timers.wrap(PodConnection, "call", "client.PodConnection.call (encode+HTTP+decode+checks)")
    timers.wrap(PodConnection, "_request", "client.PodConnection._request (HTTP round trip via transport)")
    timers.wrap(
        transport.HttptoolsTransport,
        "fetch",
        "client.HttptoolsTransport.fetch (request out, answer in, read under the cap)",
    )
    timers.wrap(wire, "encode", "client.wire.encode")
    timers.wrap(wire, "decode", "client.wire.decode")
    timers.wrap(calls, "fill_batch", "client.fill_batch (answer into batch)")
    timers.wrap(EnvResults, "take_step", "client.EnvResults.take_step (batch -> gymnasium step result, info merge)")
    timers.wrap(EnvResults, "_add_env_info", "client.EnvResults._add_env_info (merge_rows of env_info)")


def per_call(fn: Callable[[int], Any], calls: int, timers: Timers | None = None) -> list[float]:
    """Run ``fn(t)`` ``calls`` times; return each call's seconds."""
    times = []
    for t in range(calls):
        if timers is not None:
            timers.begin()
        started = time.perf_counter()
        fn(t)
        times.append(time.perf_counter() - started)
        if timers is not None:
            timers.end()
    return times


def top_costs(stats: pstats.Stats, total_s: float, n: int = 18) -> list[dict[str, Any]]:
    """The ``n`` functions with the most own time (tottime), with their share of ``total_s``."""
    rows = []
    for (path, line, func), (_cc, ncalls, tottime, cumtime, _callers) in stats.stats.items():  # type: ignore[attr-defined]
        rows.append((tottime, cumtime, ncalls, f"{Path(path).name}:{line}({func})"))
    rows.sort(reverse=True)
    return [
        {
            "where": where,
            "own_ms_per_call": tot,
            "cum_ms_per_call": cum,
            "calls": ncalls,
            "share": round(tot / total_s, 3),
        }
        for tot, cum, ncalls, where in rows[:n]
    ]


def cumulative(stats: pstats.Stats, needles: list[str]) -> dict[str, float]:
    """Cumulative seconds of the functions whose name contains each needle (largest match)."""
    found: dict[str, float] = {}
    for (path, line, func), (_cc, _nc, _tt, cumtime, _callers) in stats.stats.items():  # type: ignore[attr-defined]
        where = f"{Path(path).name}:{line}({func})"
        for needle in needles:
            if needle in where:
                found[needle] = max(found.get(needle, 0.0), cumtime)
    return found


def scale(rows: list[dict[str, Any]], calls: int) -> list[dict[str, Any]]:
    for row in rows:
        row["own_ms_per_call"] = round(1e3 * row["own_ms_per_call"] / calls, 3)
        row["cum_ms_per_call"] = round(1e3 * row["cum_ms_per_call"] / calls, 3)
    return rows


def main() -> None:
    import httpx
    from lib.pods import setup_logging
    from lib.records import write_result
    from gymnasium.vector import AsyncVectorEnv, AutoresetMode, SyncVectorEnv

    from service.pod.bodies import encode_answer
    from service.pod.routers.envs import step_answer
    from vecsim import wire
    from vecsim.client import HTTPVectorEnv
    from vecsim.client.pods import EventLoopThread
    from vecsim.engine import TaskGroupedVectorEnv, available_cores, resolve_envs_per_worker
    from vecsim.engine.tasks import make_env

    setup_logging()
    n, calls, rounds = ARGS.envs, ARGS.calls, ARGS.rounds
    workdir = Path(tempfile.mkdtemp(prefix="vecsim-profile-call-"))
    assignment = _assignment("in-process")
    per_worker = resolve_envs_per_worker(assignment)
    load_before = os.getloadavg()
    log.info("%d x %s, %d envs per worker, %d cores, load %s", n, ARGS.task, per_worker, available_cores(), load_before)
    rng = np.random.default_rng(0)
    action_space = make_env(ARGS.task, assignment.camera, "lean", EPISODE_CAP).action_space
    actions = rng.uniform(-1, 1, (calls, n, *action_space.shape)).astype(action_space.dtype)
    env_indices = np.arange(n, dtype=np.int64)
    client_timers = Timers()
    _instrument_client(client_timers)
    camera = assignment.camera
    makers = [functools.partial(make_env, ARGS.task, camera, "lean", EPISODE_CAP) for _ in range(n)]

    with contextlib.ExitStack() as stack:
        timed = stack.enter_context(pod_process("timed", workdir))
        profiled = stack.enter_context(pod_process("profiled", workdir))
        bare = stack.enter_context(bare_process(workdir))
        vec = HTTPVectorEnv(pod_urls=[timed.url])
        stack.callback(vec.close)
        vec.reset(seed=0)
        local = TaskGroupedVectorEnv(assignment)
        stack.callback(local.close)
        local.reset_envs(np.arange(local.num_envs), np.arange(local.num_envs))
        async_env = AsyncVectorEnv(makers, context="forkserver", autoreset_mode=AutoresetMode.NEXT_STEP)
        stack.callback(async_env.close)
        async_env.reset(seed=0)
        sync_env = SyncVectorEnv(makers, autoreset_mode=AutoresetMode.NEXT_STEP)
        stack.callback(sync_env.close)
        sync_env.reset(seed=0)
        raw = stack.enter_context(httpx.Client(base_url=timed.url, timeout=30))
        conn = http.client.HTTPConnection("127.0.0.1", timed.port, timeout=30)
        stack.callback(conn.close)
        bare_conn = http.client.HTTPConnection("127.0.0.1", bare.port, timeout=30)
        stack.callback(bare_conn.close)
        # The two thread hops of a call, alone: the client's sync caller to its event-loop thread
        # (EventLoopThread, as HTTPVectorEnv uses) and an event loop to a worker thread (the
        # pod's state.run, used for robot scenes; cheap scenes run inline).
        hop_loop = EventLoopThread("hop")
        stack.callback(hop_loop.close)
        hop_pool = concurrent.futures.ThreadPoolExecutor(max_workers=1)
        stack.callback(hop_pool.shutdown)
        headers = {"Content-Type": wire.CONTENT_TYPE, "Accept": wire.CONTENT_TYPE}
        bodies = [wire.encode({"generation": 0, "env_indices": env_indices, "actions": a}) for a in actions]

        def raw_httpx(t: int) -> None:
            response = raw.post("/v1/step", content=bodies[t], headers=headers)
            assert response.status_code == 200, response.text

        def exchange(
            method: str, path: str, body: bytes | None = None, conn: http.client.HTTPConnection = conn
        ) -> None:
            for attempt in (0, 1):
                try:
                    conn.request(method, path, body=body, headers=headers)
                    response = conn.getresponse()
                    break
                except (http.client.HTTPException, ConnectionError):
                    # The pod closed the kept-alive connection between rounds: open a new one.
                    conn.close()
                    if attempt:
                        raise
            assert response.status == 200
            response.read()

        def raw_http_client(t: int) -> None:
            exchange("POST", "/v1/step", bodies[t])

        def raw_healthz(_t: int) -> None:
            exchange("GET", "/healthz")

        def bare_http_client(t: int) -> None:
            exchange("POST", "/v1/step", bodies[t], bare_conn)

        def in_process_answer(t: int) -> None:
            encode_answer(step_answer(env_indices, local.step_envs(env_indices, actions[t])), False)

        # The bare server answers what the pod answers: the same arrays, shapes and dtypes.
        layouts = {}
        for name, connection in (("pod", conn), ("bare", bare_conn)):
            connection.request("POST", "/v1/step", body=bodies[0], headers=headers)
            response = connection.getresponse()
            assert response.status == 200, f"{name}: {response.status} {response.read()[:200]!r}"
            layouts[name] = _layout(wire.decode(response.read()))
        assert layouts["bare"] == layouts["pod"], f"the bare server's answer differs from the pod's: {layouts}"

        contenders: dict[str, Callable[[int], Any]] = {
            "http_vector_env": lambda t: vec.step(actions[t % calls]),
            "raw_httpx": raw_httpx,
            "raw_http_client": raw_http_client,
            "raw_healthz": raw_healthz,
            "bare_http_client": bare_http_client,
            "in_process": lambda t: local.step_envs(env_indices, actions[t]),
            "in_process_answer": in_process_answer,
            "thread_hop_loop": lambda _t: hop_loop.run(_noop()),
            "thread_hop_executor": lambda _t: hop_pool.submit(int).result(),
            "async_vector_env": lambda t: async_env.step(actions[t]),
            "sync_vector_env": lambda t: sync_env.step(actions[t]),
        }
        for name, fn in contenders.items():  # warm-up
            per_call(fn, min(20, calls))
        times: dict[str, list[float]] = {name: [] for name in contenders}
        cpu: dict[str, dict[str, float]] = {name: defaultdict(float) for name in contenders}
        names = list(contenders)
        for r in range(rounds):
            shift = r % len(names)
            for name in names[shift:] + names[:shift]:
                timers = client_timers if name == "http_vector_env" else None
                before = cpu_snapshot(timed.pid, profiled.pid)
                times[name] += per_call(contenders[name], calls, timers)
                after = cpu_snapshot(timed.pid, profiled.pid)
                for group in after:
                    cpu[name][group] += after[group] - before.get(group, 0.0)
            log.info(
                "round %d/%d: %s", r + 1, rounds, {k: round(1e3 * statistics.median(v), 2) for k, v in times.items()}
            )
        pod_layers = json.loads(collect(timed).read_text())
        client_layers = client_timers.medians_ms()

        # cProfile: the client (main thread and its loop thread) against the timed pod; then the
        # profiled pod's main thread serving HTTPVectorEnv calls.
        pcalls = ARGS.profile_calls
        main_profile, loop_profile = cProfile.Profile(), cProfile.Profile()
        loop = vec.client._loop.loop
        # From Python 3.12 cProfile sits on sys.monitoring, one profiler per process: the loop
        # thread's profile is left empty there (its time shows as the main thread's wait).
        profile_loop = sys.version_info < (3, 12)
        if profile_loop:
            asyncio.run_coroutine_threadsafe(_enable(loop_profile), loop).result()
        else:
            log.warning("Python %d.%d: profiling the client's main thread only", *sys.version_info[:2])
        main_profile.enable()
        started = time.perf_counter()
        per_call(contenders["http_vector_env"], pcalls)
        client_wall = time.perf_counter() - started
        main_profile.disable()
        if profile_loop:
            asyncio.run_coroutine_threadsafe(_disable(loop_profile), loop).result()

        vec_p = HTTPVectorEnv(pod_urls=[profiled.url])
        stack.callback(vec_p.close)
        vec_p.reset(seed=0)
        per_call(lambda t: vec_p.step(actions[t]), min(20, calls))
        os.kill(profiled.pid, signal.SIGUSR2)  # start profiling from here
        time.sleep(0.5)
        started = time.perf_counter()
        per_call(lambda t: vec_p.step(actions[t % calls]), pcalls)
        pod_wall = time.perf_counter() - started
        pod_stats = pstats.Stats(str(collect(profiled)))

    medians = {name: round(1e3 * statistics.median(v), 3) for name, v in times.items()}
    cpu_ms = {
        name: {group: round(1e3 * seconds / len(times[name]), 3) for group, seconds in groups.items()}
        for name, groups in cpu.items()
    }
    main_stats = pstats.Stats(main_profile)
    # An empty profile (the loop thread's, from Python 3.12) cannot make a Stats object.
    loop_stats = pstats.Stats(loop_profile) if profile_loop else None
    pod_total = sum(v[2] for v in pod_stats.stats.values())  # type: ignore[attr-defined]
    result = {
        "quick": ARGS.quick,
        "setup": {
            "envs": n,
            "task": ARGS.task,
            "cameras": ARGS.cameras,
            "size": ARGS.size,
            "envs_per_worker": per_worker,
            "cores": available_cores(),
            "calls_per_round": calls,
            "rounds": rounds,
            "load_avg_before": load_before,
            "load_avg_after": os.getloadavg(),
        },
        "median_ms_per_call": medians,
        "ratio_to_in_process": {k: round(v / medians["in_process"], 2) for k, v in medians.items()},
        "cpu_ms_per_call": cpu_ms,
        "client_layers_median_ms": client_layers,
        "pod_layers_median_ms": pod_layers,
        "client_profile": {
            "wall_ms_per_call": round(1e3 * client_wall / pcalls, 3),
            "main_thread_top": scale(top_costs(main_stats, client_wall), pcalls),
            "loop_thread_top": [] if loop_stats is None else scale(top_costs(loop_stats, client_wall), pcalls),
        },
        "pod_profile": {
            "wall_ms_per_call": round(1e3 * pod_wall / pcalls, 3),
            "profiled_own_ms_per_call": round(1e3 * pod_total / pcalls, 3),
            "main_thread_top": scale(top_costs(pod_stats, pod_wall, 25), pcalls),
            "cumulative_ms_per_call": {
                k: round(1e3 * v / pcalls, 3)
                for k, v in cumulative(
                    pod_stats,
                    [
                        "select",
                        "_run_once",
                        "(step)",
                        "(step_envs)",
                        "(send)",
                        "(receive)",
                        "(_per_row)",
                        "(batch_infos)",
                        "(encode_answer)",
                        "(parse_body)",
                        "(decode)",
                        "(encode)",
                        "(run_endpoint_function)",
                        "(solve_dependencies)",
                        "(_receive)",
                        "(_send)",
                        "(loads)",
                        "(dumps)",
                        "(model_validate)",
                        "(app)",
                    ],
                ).items()
            },
        },
    }
    _report(result)
    profiles = {k: result.pop(k) for k in ("client_profile", "pod_profile")}
    write_result("profile_call", result, profiles)


def _layout(tree: Any, path: str = "") -> dict[str, tuple[tuple[int, ...], str]]:
    """``{path: (shape, dtype)}`` of every array in a decoded answer."""
    if isinstance(tree, dict):
        return {k: v for key, sub in tree.items() for k, v in _layout(sub, f"{path}/{key}").items()}
    array = np.asarray(tree)
    return {path: (array.shape, array.dtype.str)}


async def _noop() -> None:
    return None


async def _enable(profile: cProfile.Profile) -> None:
    profile.enable()


async def _disable(profile: cProfile.Profile) -> None:
    profile.disable()


def _report(result: dict[str, Any]) -> None:
    out = io.StringIO()
    out.write(f"setup: {result['setup']}\n\nmedian ms per call (ratio to in_process):\n")
    for name, ms in result["median_ms_per_call"].items():
        out.write(f"  {name:22s} {ms:8.3f}  ({result['ratio_to_in_process'][name]}x)\n")
    out.write("\nCPU ms per call (client process, pod process, pod workers, in-process workers):\n")
    for name, groups in result["cpu_ms_per_call"].items():
        out.write(f"  {name:22s} " + "  ".join(f"{g} {v:7.3f}" for g, v in groups.items()) + "\n")
    for part in ("client_layers_median_ms", "pod_layers_median_ms"):
        out.write(f"\n{part}:\n")
        layers = result[part].get("median_ms", result[part])
        for name, ms in layers.items():
            out.write(f"  {ms:8.3f}  {name}\n")
    for part in ("client_profile", "pod_profile"):
        profile = result[part]
        out.write(f"\n{part}: wall {profile['wall_ms_per_call']} ms/call\n")
        for key in ("main_thread_top", "loop_thread_top"):
            for row in profile.get(key, []):
                out.write(
                    f"  [{key[:4]}] own {row['own_ms_per_call']:7.3f} cum {row['cum_ms_per_call']:7.3f} "
                    f"{100 * row['share']:5.1f}%  {row['where']}\n"
                )
        for key, ms in profile.get("cumulative_ms_per_call", {}).items():
            out.write(f"  [cum ] {ms:7.3f}  {key}\n")
    log.info("report\n%s", out.getvalue())


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--envs", type=int, default=16)
    parser.add_argument("--task", default=TASK, help="every env's task (e.g. libero_10/0)")
    parser.add_argument("--cameras", default="", help="comma-separated camera names (none by default)")
    parser.add_argument("--size", type=int, default=64, help="the cameras' height and width")
    parser.add_argument(
        "--envs-per-worker", type=int, default=0, help="the pods' and in_process's envs_per_worker (0: auto)"
    )
    parser.add_argument("--calls", type=int, default=100, help="calls per contender per round")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--profile-calls", type=int, default=300, help="calls under cProfile (client, then pod)")
    parser.add_argument("--serve-pod", choices=["timed", "profiled"], help=argparse.SUPPRESS)
    parser.add_argument("--serve-out", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--serve-bare", type=int, metavar="PORT", help=argparse.SUPPRESS)
    parser.add_argument("--quick", action="store_true", help="4 envs, a few calls: for the smoke test")
    ARGS, rest = parser.parse_known_args()
    if ARGS.quick:
        ARGS.envs, ARGS.calls, ARGS.rounds, ARGS.profile_calls = 4, 5, 1, 5
    if ARGS.serve_bare:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        sys.exit(serve_bare(ARGS.serve_bare))
    if ARGS.serve_pod:
        sys.exit(serve_pod(ARGS.serve_pod, ARGS.serve_out, [a for a in rest if a != "--"]))
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    main()
