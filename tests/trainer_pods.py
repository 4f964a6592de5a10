"""Sim pods as real subprocesses, for the trainer-side tests (client, vector env, rollout).

Standalone pods: ``vecsim pod --assignment <file> --port <free port>``; the helper waits (bounded)
until every pod's ``/readyz`` answers 200 and kills every pod it started on the way out. Whole
jobs: :func:`local_job` runs ``service.runner.LocalJob`` (controller + pods) on free ports.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import httpx

from service.runner.job import LocalJob
from vecsim.config import Assignment, CameraConfig, RenderPreset, RunnerConfig, TaskBlock

READY_TIMEOUT_S = 240.0
NO_CAMERA = CameraConfig(names=(), height=8, width=8)


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def free_port_block(n: int, attempts: int = 50) -> int:
    """The first of ``n`` consecutive free ports on 127.0.0.1 (a job's pods use base_port + ordinal)."""
    for _ in range(attempts):
        base = free_port()
        if base + n > 65000:
            continue
        try:
            with contextlib.ExitStack() as stack:
                for port in range(base, base + n):
                    sock = stack.enter_context(socket.socket())
                    sock.bind(("127.0.0.1", port))
            return base
        except OSError:
            continue
    raise RuntimeError(f"no {n} consecutive free ports found")


def job_config(job: dict, replicas: int) -> RunnerConfig:
    """A RunnerConfig for ``job`` with ``replicas`` pods, every port free, heartbeats quick."""
    return RunnerConfig.model_validate(
        {
            "job": job,
            "pods": {"replicas": replicas, "base_port": free_port_block(replicas), "max_envs": 16},
            "controller": {
                "port": free_port(),
                "heartbeat_interval_s": 0.5,
                "heartbeat_ttl_s": 3.0,
                "reconcile_interval_s": 0.25,
            },
        }
    )


@contextlib.contextmanager
def local_job(config: RunnerConfig, workdir: Path) -> Iterator[LocalJob]:
    """Run the job (controller + pods), wait until its routing is ready, yield it, stop it all."""
    job = LocalJob(config, log_dir=workdir, grace_s=10)
    try:
        job.start()
        job.wait_ready(timeout=READY_TIMEOUT_S)
        yield job
    finally:
        job.stop()


def wait_for_generation(controller_url: str, after: int, timeout_s: float = 120.0) -> int:
    """Block until the controller's routing table is ready at a generation above ``after``."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        with contextlib.suppress(httpx.TransportError):
            table = httpx.get(f"{controller_url}/v1/routing", timeout=5).json()
            if table["generation"] > after and table["ready"]:
                return table["generation"]
        time.sleep(0.25)
    raise RuntimeError(f"routing at {controller_url} did not move past generation {after} in {timeout_s} s")


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
        blocks, start = [], 0
        for task_id, n in self.tasks:
            blocks.append(TaskBlock(task_id=task_id, env_start=start, num_envs=n))
            start += n
        return Assignment(
            generation=self.generation,
            job_id="trainer-tests",
            pod=self.name,
            stage_id=self.stage_id,
            tasks=tuple(blocks),
            camera=self.camera,
            render=self.render,
            max_episode_steps=self.max_episode_steps,
            envs_per_worker=self.envs_per_worker,
            make_kwargs=self.make_kwargs,
        )


@dataclass
class RunningPod:
    spec: PodSpec
    url: str
    process: subprocess.Popen
    log: Path
    extra: dict = field(default_factory=dict)

    def stop(self) -> None:
        """SIGTERM the pod's process group, then SIGKILL it if it lingers."""
        if self.process.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.process.pid, signal.SIGTERM)
            try:
                self.process.wait(timeout=15)
            except subprocess.TimeoutExpired:
                pass
        # Env worker processes share the group; make sure none outlives the pod.
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.process.pid, signal.SIGKILL)
        with contextlib.suppress(subprocess.TimeoutExpired):
            self.process.wait(timeout=5)


def _log_tail(path: Path, lines: int = 30) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])
    except OSError:
        return "<no log>"


@contextlib.contextmanager
def standalone_pods(specs: Sequence[PodSpec], workdir: Path) -> Iterator[list[RunningPod]]:
    """Start one pod process per spec, wait until all are ready, yield them, kill them all."""
    workdir.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    # The pods import the tests' own env package (gym_custom_env) as a user's pods would theirs.
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(Path(__file__).parent), env.get("PYTHONPATH")) if p)
    for var in ("CONTROLLER_URL", "POD_IP", "VECSIM_ADVERTISE_URL"):
        env.pop(var, None)
    pods: list[RunningPod] = []
    try:
        for spec in specs:
            path = workdir / f"{spec.name}.json"
            path.write_text(json.dumps(spec.assignment().model_dump(mode="json")))
            port = free_port()
            log = workdir / f"{spec.name}.log"
            with log.open("wb") as out:
                process = subprocess.Popen(
                    [
                        sys.executable,
                        "-m",
                        "vecsim.cli",
                        "pod",
                        "--assignment",
                        str(path),
                        "--name",
                        spec.name,
                        "--host",
                        "127.0.0.1",
                        "--port",
                        str(port),
                        "--log-level",
                        "warning",
                    ],
                    stdout=out,
                    stderr=subprocess.STDOUT,
                    env=env,
                    start_new_session=True,
                )
            pods.append(RunningPod(spec, f"http://127.0.0.1:{port}", process, log))
        wait_ready(pods)
        yield pods
    finally:
        for pod in pods:
            pod.stop()


def wait_ready(pods: Sequence[RunningPod], timeout_s: float = READY_TIMEOUT_S) -> None:
    """Block until every pod's /readyz is 200; raise naming the first pod that is not."""
    deadline = time.monotonic() + timeout_s
    for pod in pods:
        while True:
            if pod.process.poll() is not None:
                raise RuntimeError(f"pod {pod.spec.name} exited with {pod.process.returncode}:\n{_log_tail(pod.log)}")
            with contextlib.suppress(httpx.TransportError):
                if httpx.get(f"{pod.url}/readyz", timeout=5).status_code == 200:
                    break
            if time.monotonic() > deadline:
                raise RuntimeError(f"pod {pod.spec.name} not ready after {timeout_s} s:\n{_log_tail(pod.log)}")
            time.sleep(0.25)
