"""The one set of helpers for what tests and benchmarks run on loopback: the one bounded
:func:`wait_until`, `vecsim pod` and `vecsim controller` processes (:class:`Server`; standalone
pods from a :class:`PodSpec` or an assignment with :func:`standalone_pods`; whole jobs with
:func:`local_job`), ASGI apps served by uvicorn in a thread (:class:`AppThread`) and raw socket
servers that send what no pod would (:func:`raw_server`); free ports come from
``service.runner.ports``. Test modules import these from here, never from each other;
``conftest.py`` exposes the common ones as fixtures; ``bench/`` imports them too.

Every process runs in a session of its own, so that the pod, its forkserver and its env workers
share one process group; :meth:`Server.stop` ends the whole group, and every helper here stops
what it started in a ``finally``. Every wait is bounded.
"""

from __future__ import annotations

import contextlib
import functools
import ipaddress
import os
import secrets
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import uvicorn

from service.runner.job import LocalJob
from service.runner.ports import free_port, free_port_block
from vecsim import wire
from vecsim.config import Assignment, CameraConfig, JobConfig, RenderPreset, TaskBlock
from vecsim.lifetime import exit_with_parent

START_TIMEOUT_S = 120.0
READY_TIMEOUT_S = 240.0
NO_CAMERA = CameraConfig(names=(), height=8, width=8)
TESTS_DIR = Path(__file__).resolve().parents[1]
# Variables of the caller's shell that would make a test pod something else than it asks for.
_INHERITED = ("CONTROLLER_URL", "POD_IP", "POD_NAME", "VECSIM_ADVERTISE_URL", "VECSIM_PORT", "VECSIM_TOKEN")


def wait_until(predicate: Callable[[], Any], what: str, timeout_s: float = START_TIMEOUT_S, every: float = 0.1) -> Any:
    """Poll ``predicate`` until it returns something truthy; return that, or fail naming ``what``."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s:.0f} s waiting for {what}")
        time.sleep(every)


def loopback_socket(port: int = 0) -> socket.socket:
    """A TCP socket bound to ``127.0.0.1:port`` (a free one by default), not yet listening."""
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind(("127.0.0.1", port))
    return sock


def log_tail(path: Path, chars: int = 3000) -> str:
    """The end of the log at ``path``, for a failure message."""
    try:
        return path.read_text(errors="replace")[-chars:]
    except OSError:
        return f"<no log at {path}>"


def clean_env(**extra: str) -> dict[str, str]:
    """The test process's environment without vecsim's identity variables, plus ``extra``.

    The tests' own directory is on ``PYTHONPATH``: pods import the tests' env package
    (support.gym_custom_env) as a user's pods would theirs."""
    env = {k: v for k, v in os.environ.items() if k not in _INHERITED}
    env.setdefault("MUJOCO_GL", "egl")
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(TESTS_DIR), env.get("PYTHONPATH")) if p)
    env["PYTHONUNBUFFERED"] = "1"
    env.update(extra)
    return env


# The program a Server runs by default: the ``vecsim`` command.
VECSIM_CLI = (sys.executable, "-m", "service.cli")


class Server:
    """One ``python -m service.cli <argv>`` process (``program`` in place of ``python -m
    service.cli``, when given) serving on ``<host>:<port>``; nothing runs before :meth:`start`
    (use :func:`running`, which always stops it)."""

    def __init__(
        self,
        name: str,
        argv: Sequence[str],
        port: int,
        env: Mapping[str, str],
        log_path: Path,
        *,
        host: str = "127.0.0.1",
        wrap: Sequence[str] = (),
        program: Sequence[str] = VECSIM_CLI,
    ) -> None:
        self.name = name
        # ``wrap`` runs the command through another one that execs it (``ip netns exec <ns>``,
        # ``taskset -c <cpus>``).
        self.argv = [*wrap, *program, *argv]
        self.env = dict(env)
        self.port = port
        self.url = f"http://{host}:{port}"
        self.log_path = log_path
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        """Start the process (again, after :meth:`stop`: the same command, port and log)."""
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        # Its own process group, so stop() reaches its workers too; and on Linux it dies with the
        # test process, however that ends. The kernel ties it to the thread that forks it, so only
        # a process started from the main thread (which lives as long as the test run) is tied.
        tie = threading.current_thread() is threading.main_thread()
        with self.log_path.open("ab") as log:
            self.proc = subprocess.Popen(
                self.argv,
                env=self.env,
                stdout=log,
                stderr=subprocess.STDOUT,
                start_new_session=True,
                preexec_fn=functools.partial(exit_with_parent, os.getpid()) if tie else None,
            )

    @property
    def pid(self) -> int:
        assert self.proc is not None, f"{self.name} was never started"
        return self.proc.pid

    def log_text(self) -> str:
        return self.log_path.read_text(errors="replace")

    def log_tail(self) -> str:
        return log_tail(self.log_path)

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def answers(self, path: str, status: int = 200) -> bool:
        """Whether ``GET path`` answers ``status`` now (fails at once if the process exited)."""
        assert self.proc is not None, f"{self.name} was never started"
        if self.proc.poll() is not None:
            raise AssertionError(f"{self.name} exited with {self.proc.returncode}:\n{self.log_tail()}")
        try:
            return httpx.get(f"{self.url}{path}", timeout=5).status_code == status
        except httpx.TransportError:
            return False

    def wait_alive(self, timeout_s: float = START_TIMEOUT_S) -> None:
        wait_until(lambda: self.answers("/healthz"), f"{self.name} to answer /healthz", timeout_s)

    def wait_ready(self, timeout_s: float = START_TIMEOUT_S) -> None:
        try:
            wait_until(lambda: self.answers("/readyz"), f"{self.name} to be ready", timeout_s)
        except AssertionError as e:
            raise AssertionError(f"{e}\n{self.log_tail()}") from None

    def signal_group(self, sig: int) -> None:
        """Send ``sig`` to the process and everything it started (its env workers)."""
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.pid, sig)

    def stop(self) -> None:
        """SIGTERM the process group, wait a bounded time, then SIGKILL whatever is left."""
        if self.proc is None:
            return
        self.signal_group(signal.SIGCONT)  # a stopped process cannot act on SIGTERM
        self.signal_group(signal.SIGTERM)
        with contextlib.suppress(subprocess.TimeoutExpired):
            self.proc.wait(timeout=15)
        self.signal_group(signal.SIGKILL)
        with contextlib.suppress(subprocess.TimeoutExpired):
            self.proc.wait(timeout=10)


@contextlib.contextmanager
def running(server: Server, ready: bool = False) -> Iterator[Server]:
    """Start ``server``, wait until it answers (and is ready, if asked), yield it, and stop it
    whatever happens."""
    try:
        server.start()
        if ready:
            server.wait_ready()
        else:
            server.wait_alive()
        yield server
    finally:
        server.stop()


def pod_server(
    name: str,
    workdir: Path,
    *,
    args: Sequence[str] = (),
    token: str | None = None,
    host: str = "127.0.0.1",
    port: int | None = None,
    wrap: Sequence[str] = (),
    log_level: str = "info",
    **env: str,
) -> Server:
    """A ``vecsim pod`` process named ``name`` on ``host:port`` (a free loopback port by default),
    standalone unless ``args`` or ``env`` say otherwise, with the shared ``token`` if given."""
    port = free_port() if port is None else port
    extra = {"POD_NAME": name, **env}
    if token is not None:
        extra["VECSIM_TOKEN"] = token
    argv = ["pod", "--host", host, "--port", str(port), "--log-level", log_level, *args]
    return Server(name, argv, port, clean_env(**extra), workdir / f"{name}.log", host=host, wrap=wrap)


def controller_server(
    workdir: Path,
    *,
    args: Sequence[str] = (),
    token: str | None = None,
    host: str = "127.0.0.1",
    wrap: Sequence[str] = (),
    **env: str,
) -> Server:
    """A ``vecsim controller`` process on a free port of ``host`` (loopback by default; another
    address of this machine, e.g. a veth's, for pods in other network namespaces), with the
    shared ``token`` if given."""
    port = free_port(host)
    extra = dict(env)
    if token is not None:
        extra["VECSIM_TOKEN"] = token
    argv = ["controller", "--host", host, "--port", str(port), *args]
    return Server("controller", argv, port, clean_env(**extra), workdir / "controller.log", host=host, wrap=wrap)


def assignment(pod: str, tasks: Sequence[tuple[str, int]], **fields: Any) -> Assignment:
    """An assignment of blocks ``[(task_id, num_envs), ...]``, laid out from env index 0, for
    ``pod``; ``fields`` are the Assignment's other fields (stage 0, generation 0 by default)."""
    blocks, start = [], 0
    for task_id, n in tasks:
        blocks.append(TaskBlock(task_id=task_id, env_start=start, num_envs=n))
        start += n
    return Assignment.model_validate({"generation": 0, "stage_id": 0, **fields, "pod": pod, "tasks": tuple(blocks)})


def assignment_file(
    workdir: Path,
    pod: str,
    tasks: Sequence[tuple[str, int]],
    *,
    camera: CameraConfig = NO_CAMERA,
    max_episode_steps: int = 50,
    generation: int = 0,
    stage_id: int = 0,
) -> Path:
    """Write an assignment of blocks ``[(task_id, num_envs), ...]`` for ``pod`` on stage
    ``stage_id``; return its path."""
    path = workdir / f"{pod}-assignment.json"
    path.write_text(
        assignment(
            pod,
            tasks,
            generation=generation,
            job_id="reliability",
            stage_id=stage_id,
            camera=camera,
            render="lean",
            max_episode_steps=max_episode_steps,
        ).model_dump_json()
    )
    return path


@dataclass
class PodSpec:
    """One standalone pod: its name, stage and task blocks ``[(task_id, num_envs), ...]``."""

    name: str
    stage_id: int
    tasks: Sequence[tuple[str, int]]
    camera: CameraConfig = NO_CAMERA
    max_episode_steps: int | None = 300
    envs_per_worker: int = 1
    generation: int = 0
    render: RenderPreset | None = "lean"
    make_kwargs: dict = field(default_factory=dict)

    def assignment(self) -> Assignment:
        return assignment(
            self.name,
            self.tasks,
            generation=self.generation,
            job_id="trainer-tests",
            stage_id=self.stage_id,
            camera=self.camera,
            render=self.render,
            max_episode_steps=self.max_episode_steps,
            envs_per_worker=self.envs_per_worker,
            make_kwargs=self.make_kwargs,
        )


class RunningPod(Server):
    """A standalone ``vecsim pod`` process serving ``spec``'s assignment (``spec`` itself, when
    it is one), through ``wrap`` if given (``taskset -c <cpus>``), run by ``program`` (another
    venv's ``python -m service.cli``) with ``env`` added to its environment."""

    def __init__(
        self,
        spec: PodSpec | Assignment,
        workdir: Path,
        wrap: Sequence[str] = (),
        *,
        program: Sequence[str] = VECSIM_CLI,
        env: Mapping[str, str] | None = None,
    ) -> None:
        self.assignment = spec.assignment() if isinstance(spec, PodSpec) else spec
        name = self.assignment.pod
        path = workdir / f"{name}.json"
        path.write_text(self.assignment.model_dump_json())
        port = free_port()
        argv = [
            "pod",
            "--host",
            "127.0.0.1",
            "--port",
            str(port),
            "--log-level",
            "warning",
            "--assignment",
            str(path),
            "--name",
            name,
        ]
        environment = clean_env(POD_NAME=name, **(env or {}))
        super().__init__(name, argv, port, environment, workdir / f"{name}.log", wrap=wrap, program=program)


@contextlib.contextmanager
def standalone_pods(
    specs: Sequence[PodSpec | Assignment],
    workdir: Path | None = None,
    *,
    cores: Sequence[str | None] | None = None,
    ready_timeout_s: float = READY_TIMEOUT_S,
) -> Iterator[list[RunningPod]]:
    """Start one pod process per spec (in a fresh temporary ``workdir`` if none is given), wait
    until all are ready, yield them, stop them all.

    ``cores``, when given, pins pod ``i`` (its workers included) to the CPU list ``cores[i]``
    (``taskset -c``; None leaves it free), as a CPU limit confines a Kubernetes pod.
    """
    workdir = Path(workdir or tempfile.mkdtemp(prefix="vecsim-pods-"))
    workdir.mkdir(parents=True, exist_ok=True)
    pods: list[RunningPod] = []
    try:
        for i, spec in enumerate(specs):
            pin = cores[i] if cores is not None else None
            pods.append(RunningPod(spec, workdir, wrap=("taskset", "-c", pin) if pin is not None else ()))
            pods[-1].start()
        for pod in pods:
            pod.wait_ready(ready_timeout_s)
        yield pods
    finally:
        for pod in pods:
            pod.stop()


def job_config(job: Mapping[str, Any], replicas: int, *, max_envs: int = 16, heartbeat_ttl_s: float = 3.0) -> JobConfig:
    """A JobConfig for ``job`` with ``replicas`` pods, every port free, heartbeats quick."""
    controller_port = free_port()
    return JobConfig.model_validate(
        {
            "job": dict(job),
            "pods": {
                "replicas": replicas,
                "base_port": free_port_block(replicas, avoid={controller_port}),
                "max_envs": max_envs,
            },
            "controller": {
                "port": controller_port,
                "heartbeat_interval_s": 0.5,
                "heartbeat_ttl_s": heartbeat_ttl_s,
                "reconcile_interval_s": 0.25,
            },
        }
    )


@contextlib.contextmanager
def local_job(
    config: JobConfig, workdir: Path | None = None, *, ready_timeout_s: float = READY_TIMEOUT_S
) -> Iterator[LocalJob]:
    """Run the job (controller + pods; logs in a fresh temporary ``workdir`` if none is given),
    wait until its routing is ready, yield it, stop it all."""
    job = LocalJob(config, log_dir=workdir or tempfile.mkdtemp(prefix="vecsim-job-"), grace_s=10)
    try:
        job.start()
        job.wait_ready(timeout=ready_timeout_s)
        yield job
    finally:
        job.stop()


def wait_for_generation(controller_url: str, after: int, timeout_s: float = 120.0) -> int:
    """Block until the controller's routing table is ready at a generation above ``after``."""

    def moved_on() -> int | None:
        with contextlib.suppress(httpx.TransportError):
            table = httpx.get(f"{controller_url}/v1/routing", timeout=5).json()
            if table["generation"] > after and table["ready"]:
                return table["generation"]
        return None

    return wait_until(moved_on, f"routing at {controller_url} to be ready past generation {after}", timeout_s, 0.25)


class AppThread:
    """An ASGI app served by uvicorn on a loopback socket (``sock``, or a free port), in a thread
    of this process; started when made, stopped by :meth:`stop` or on leaving a ``with``."""

    def __init__(self, app: Any, sock: socket.socket | None = None, **config: Any) -> None:
        self.sock = loopback_socket() if sock is None else sock
        self.port = self.sock.getsockname()[1]
        self.url = f"http://127.0.0.1:{self.port}"
        self.server = uvicorn.Server(uvicorn.Config(app, **{"log_level": "warning", **config}))
        self.thread = threading.Thread(target=self.server.run, kwargs={"sockets": [self.sock]}, daemon=True)
        self.thread.start()
        wait_until(lambda: self.server.started or not self.thread.is_alive(), f"uvicorn on port {self.port}", 30)
        assert self.server.started, f"uvicorn on port {self.port} did not start"

    def connections(self) -> int:
        """How many client connections the server holds open now."""
        return len(self.server.server_state.connections)

    def stop(self) -> None:
        self.server.should_exit = True
        self.thread.join(timeout=15)
        self.sock.close()

    def __enter__(self) -> AppThread:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


@contextlib.contextmanager
def socket_server(handle: Callable[[socket.socket, int], None]) -> Iterator[str]:
    """A TCP server on loopback that calls ``handle(connection, number)`` for each connection it
    accepts (numbered from 1; a 5 s timeout set, closed after; an ``OSError`` in it ends that
    connection only), one at a time; yields its URL."""
    listener = loopback_socket()
    listener.listen(16)
    listener.settimeout(0.1)
    stop = threading.Event()

    def serve() -> None:
        number = 0
        while not stop.is_set():
            try:
                conn, _ = listener.accept()
            except TimeoutError:
                continue
            number += 1
            with conn:
                conn.settimeout(5)
                with contextlib.suppress(OSError):
                    handle(conn, number)

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{listener.getsockname()[1]}"
    finally:
        stop.set()
        thread.join(5)
        listener.close()


@contextlib.contextmanager
def raw_server(reply: bytes, requests: list[bytes] | None = None) -> Iterator[str]:
    """A TCP server on loopback that reads one request per connection, sends ``reply`` and
    closes; yields its URL. Each request it answered is appended to ``requests``, if given."""

    def answer(conn: socket.socket, _number: int) -> None:
        request = conn.recv(65536)
        conn.sendall(reply)
        if requests is not None:
            requests.append(request)

    with socket_server(answer) as url:
        yield url


def post_wire(url: str, op: str, body: dict[str, Any], token: str | None, timeout: float = 60) -> httpx.Response:
    """``POST url/v1/<op>`` with ``body`` as wire, the token (if any) in the header."""
    headers = {"Content-Type": wire.CONTENT_TYPE, "Accept": wire.CONTENT_TYPE}
    if token is not None:
        headers["Authorization"] = f"Bearer {token}"
    return httpx.post(f"{url}/v1/{op}", content=wire.encode(body), headers=headers, timeout=timeout)


def reset_body(generation: int, env_indices: Sequence[int], state_ids: Sequence[int]) -> dict[str, Any]:
    return {
        "generation": generation,
        "env_indices": np.asarray(env_indices, np.int64),
        "state_ids": np.asarray(state_ids, np.int64),
    }


def step_body(generation: int, env_indices: Sequence[int], actions: np.ndarray) -> dict[str, Any]:
    return {"generation": generation, "env_indices": np.asarray(env_indices, np.int64), "actions": actions}


def ip(*args: str) -> None:
    """Run ``ip <args>`` (iproute2), failing on error."""
    subprocess.run(["ip", *args], check=True, capture_output=True, text=True, timeout=30)


def unused_subnet() -> ipaddress.IPv4Network:
    """A 10.x.y.0/24 that no address or route of this machine touches."""
    used = subprocess.run(["ip", "-o", "addr"], capture_output=True, text=True, timeout=30).stdout
    used += subprocess.run(["ip", "route"], capture_output=True, text=True, timeout=30).stdout
    for _ in range(100):
        net = ipaddress.ip_network(f"10.{secrets.randbelow(200) + 50}.{secrets.randbelow(250) + 1}.0/24")
        if f"{str(net.network_address).rsplit('.', 1)[0]}." not in used:
            return net
    raise RuntimeError("no unused 10.x.y.0/24 found")


class HostLink:
    """A network namespace wired to this one by a veth pair on a private /24: this side is .1,
    the namespace's side .2. :meth:`cut` and :meth:`heal` take the namespace's side down and up,
    so packets to it go nowhere, as in a network partition."""

    def __init__(self) -> None:
        tag = secrets.token_hex(3)
        self.namespace = f"vsf{tag}"
        self.subnet = unused_subnet()
        self.address = str(self.subnet.network_address + 2)
        self._ours, self._theirs = f"vsf{tag}h", f"vsf{tag}p"
        self._made = False

    def wrap(self) -> list[str]:
        """The command prefix that runs a command inside the namespace."""
        return ["ip", "netns", "exec", self.namespace]

    def create(self) -> None:
        """Make the namespace and the link. Raises CalledProcessError when not permitted."""
        ip("netns", "add", self.namespace)
        self._made = True
        ip("link", "add", self._ours, "type", "veth", "peer", "name", self._theirs)
        ip("link", "set", self._theirs, "netns", self.namespace)
        ip("addr", "add", f"{self.subnet.network_address + 1}/24", "dev", self._ours)
        ip("link", "set", self._ours, "up")
        ip("-n", self.namespace, "link", "set", "lo", "up")
        ip("-n", self.namespace, "addr", "add", f"{self.address}/24", "dev", self._theirs)
        ip("-n", self.namespace, "link", "set", self._theirs, "up")

    def cut(self) -> None:
        ip("-n", self.namespace, "link", "set", self._theirs, "down")

    def heal(self) -> None:
        ip("-n", self.namespace, "link", "set", self._theirs, "up")

    def delete(self) -> None:
        """Remove the link (the veth takes its peer along) and the namespace; idempotent."""
        subprocess.run(["ip", "link", "del", self._ours], capture_output=True, timeout=30)
        if self._made:
            subprocess.run(["ip", "netns", "del", self.namespace], capture_output=True, timeout=30)
            self._made = False
