"""`vecsim pod` and `vecsim controller` as real processes on loopback, for the reliability and
security tests (test_auth, test_fuzz_api, test_faults, the soak).

Every process runs in a session of its own, so that the pod, its forkserver and its env workers
share one process group; :meth:`Server.stop` ends the whole group, and every helper here stops
what it started in a ``finally``. Every wait is bounded.
"""

from __future__ import annotations

import contextlib
import ipaddress
import os
import secrets
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import httpx
import numpy as np
from trainer_pods import free_port

from vecsim import wire
from vecsim.config import Assignment, CameraConfig, TaskBlock

START_TIMEOUT_S = 120.0
NO_CAMERA = CameraConfig(names=(), height=8, width=8)
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


def clean_env(**extra: str) -> dict[str, str]:
    """The test process's environment without vecsim's identity variables, plus ``extra``."""
    env = {k: v for k, v in os.environ.items() if k not in _INHERITED}
    env.setdefault("MUJOCO_GL", "egl")
    env["PYTHONUNBUFFERED"] = "1"
    env.update(extra)
    return env


class Server:
    """One ``python -m vecsim.cli <argv>`` process serving on ``127.0.0.1:<port>``; nothing runs
    before :meth:`start` (use :func:`running`, which always stops it)."""

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
    ) -> None:
        self.name = name
        # ``wrap`` runs the command through another one that execs it (``ip netns exec <ns>``).
        self.argv = [*wrap, sys.executable, "-m", "vecsim.cli", *argv]
        self.env = dict(env)
        self.port = port
        self.url = f"http://{host}:{port}"
        self.log_path = log_path
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        """Start the process (again, after :meth:`stop`: the same command, port and log)."""
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        with self.log_path.open("ab") as log:
            self.proc = subprocess.Popen(
                self.argv, env=self.env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True
            )

    @property
    def pid(self) -> int:
        assert self.proc is not None, f"{self.name} was never started"
        return self.proc.pid

    def log_text(self) -> str:
        return self.log_path.read_text(errors="replace")

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def answers(self, path: str, status: int = 200) -> bool:
        """Whether ``GET path`` answers ``status`` now (fails at once if the process exited)."""
        assert self.proc is not None, f"{self.name} was never started"
        if self.proc.poll() is not None:
            raise AssertionError(f"{self.name} exited with {self.proc.returncode}:\n{self.log_text()[-3000:]}")
        try:
            return httpx.get(f"{self.url}{path}", timeout=5).status_code == status
        except httpx.TransportError:
            return False

    def wait_alive(self, timeout_s: float = START_TIMEOUT_S) -> None:
        wait_until(lambda: self.answers("/healthz"), f"{self.name} to answer /healthz", timeout_s)

    def wait_ready(self, timeout_s: float = START_TIMEOUT_S) -> None:
        wait_until(lambda: self.answers("/readyz"), f"{self.name} to be ready", timeout_s)

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
    **env: str,
) -> Server:
    """A ``vecsim pod`` process named ``name`` on ``host:port`` (a free loopback port by default),
    standalone unless ``args`` or ``env`` say otherwise, with the shared ``token`` if given."""
    port = free_port() if port is None else port
    extra = {"POD_NAME": name, **env}
    if token is not None:
        extra["VECSIM_TOKEN"] = token
    argv = ["pod", "--host", host, "--port", str(port), "--log-level", "info", *args]
    return Server(name, argv, port, clean_env(**extra), workdir / f"{name}.log", host=host, wrap=wrap)


def controller_server(workdir: Path, *, args: Sequence[str] = (), token: str | None = None, **env: str) -> Server:
    """A ``vecsim controller`` process on a free port, with the shared ``token`` if given."""
    port = free_port()
    extra = dict(env)
    if token is not None:
        extra["VECSIM_TOKEN"] = token
    argv = ["controller", "--host", "127.0.0.1", "--port", str(port), *args]
    return Server("controller", argv, port, clean_env(**extra), workdir / "controller.log")


def controller_server_on(
    host: str, workdir: Path, *, args: Sequence[str] = (), token: str | None = None, **env: str
) -> Server:
    """A ``vecsim controller`` process listening on ``host`` (an address of this machine other
    than loopback, e.g. a veth's, for pods in other network namespaces), on a free port."""
    port = free_port()
    extra = dict(env)
    if token is not None:
        extra["VECSIM_TOKEN"] = token
    argv = ["controller", "--host", host, "--port", str(port), *args]
    return Server("controller", argv, port, clean_env(**extra), workdir / "controller.log", host=host)


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
    blocks, start = [], 0
    for task_id, n in tasks:
        blocks.append(TaskBlock(task_id=task_id, env_start=start, num_envs=n))
        start += n
    assignment = Assignment(
        generation=generation,
        job_id="reliability",
        pod=pod,
        stage_id=stage_id,
        tasks=tuple(blocks),
        camera=camera,
        render="lean",
        max_episode_steps=max_episode_steps,
    )
    path = workdir / f"{pod}-assignment.json"
    path.write_text(assignment.model_dump_json())
    return path


def post_wire(url: str, op: str, body: dict[str, Any], token: str | None, timeout: float = 60) -> httpx.Response:
    """``POST url/v1/<op>`` with ``body`` as wire, the token (if any) in the header."""
    headers = {"Content-Type": wire.CONTENT_TYPE, "Accept": wire.CONTENT_TYPE}
    if token is not None:
        headers["Authorization"] = f"Bearer {token}"
    return httpx.post(f"{url}/v1/{op}", content=wire.encode(body), headers=headers, timeout=timeout)


def reset_body(generation: int, env_ids: Sequence[int], state_ids: Sequence[int]) -> dict[str, Any]:
    return {
        "generation": generation,
        "env_ids": np.asarray(env_ids, np.int64),
        "state_ids": np.asarray(state_ids, np.int64),
    }


def step_body(generation: int, env_ids: Sequence[int], actions: np.ndarray) -> dict[str, Any]:
    return {"generation": generation, "env_ids": np.asarray(env_ids, np.int64), "actions": actions}


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
