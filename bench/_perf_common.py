"""Helpers of the serving benchmarks (3-7): real pods and jobs on free ports, interleaved rounds,
memory of process trees, and a bounded wait for a quiet machine.

Every process started here runs in its own session and is killed, with its whole process group,
when its context manager exits, whatever happened inside.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import httpx

from common import spread

from vecsim.config import Assignment, RunnerConfig

log = logging.getLogger("bench")

READY_TIMEOUT_S = 600.0


def free_port() -> int:
    """Return a TCP port on 127.0.0.1 that nothing listens on right now."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def free_port_block(n: int, attempts: int = 50) -> int:
    """Return the first of ``n`` consecutive free ports (a job's pods listen on base_port + ordinal).

    Raises:
        RuntimeError: no such block was found in ``attempts`` tries.
    """
    for _ in range(attempts):
        base = free_port()
        if base + n > 65000:
            continue
        try:
            with contextlib.ExitStack() as stack:
                for port in range(base, base + n):
                    stack.enter_context(socket.socket()).bind(("127.0.0.1", port))
            return base
        except OSError:
            continue
    raise RuntimeError(f"no {n} consecutive free ports found")


def _log_tail(path: Path, lines: int = 20) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])
    except OSError:
        return "<no log>"


def kill_group(process: subprocess.Popen[bytes]) -> None:
    """SIGTERM the process group, then SIGKILL whatever of it is left (env workers included)."""
    if process.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(process.pid, signal.SIGTERM)
        with contextlib.suppress(subprocess.TimeoutExpired):
            process.wait(timeout=15)
    with contextlib.suppress(ProcessLookupError):
        os.killpg(process.pid, signal.SIGKILL)
    with contextlib.suppress(subprocess.TimeoutExpired):
        process.wait(timeout=5)


def wait_until_ready(url: str, process: subprocess.Popen[bytes], log_path: Path, timeout_s: float) -> None:
    """Block until ``url``/readyz answers 200.

    Raises:
        RuntimeError: the process exited, or was not ready within ``timeout_s`` (log tail included).
    """
    deadline = time.monotonic() + timeout_s
    while True:
        if process.poll() is not None:
            raise RuntimeError(f"{url} exited with {process.returncode}:\n{_log_tail(log_path)}")
        with contextlib.suppress(httpx.TransportError):
            if httpx.get(f"{url}/readyz", timeout=5).status_code == 200:
                return
        if time.monotonic() > deadline:
            raise RuntimeError(f"{url} not ready after {timeout_s:.0f} s:\n{_log_tail(log_path)}")
        time.sleep(0.2)


@contextlib.contextmanager
def standalone_pods(
    assignments: Sequence[Assignment], workdir: Path | None = None, cores: Sequence[str | None] | None = None
) -> Iterator[list[Any]]:
    """Run one ``vecsim pod`` process per assignment (no controller, no token) on free ports.

    ``cores``, when given, pins pod ``i`` (its workers included) to the CPU list ``cores[i]``
    (``taskset -c``; None leaves it free), as a CPU limit would confine a Kubernetes pod.

    Yields:
        one :class:`subprocess.Popen` per pod, each with ``.url`` set; all are killed on exit.
    """
    workdir = Path(workdir or tempfile.mkdtemp(prefix="vecsim-bench-"))
    workdir.mkdir(parents=True, exist_ok=True)
    env = {k: v for k, v in os.environ.items() if k not in ("CONTROLLER_URL", "POD_IP", "VECSIM_ADVERTISE_URL")}
    env.pop("VECSIM_TOKEN", None)
    env.setdefault("MUJOCO_GL", "egl")
    pods: list[Any] = []
    try:
        for i, assignment in enumerate(assignments):
            pin = cores[i] if cores is not None else None
            path = workdir / f"{assignment.pod}.json"
            path.write_text(json.dumps(assignment.model_dump(mode="json")))
            port = free_port()
            log_path = workdir / f"{assignment.pod}.log"
            argv = [sys.executable, "-m", "vecsim.cli", "pod", "--assignment", str(path), "--name", assignment.pod,
                    "--host", "127.0.0.1", "--port", str(port), "--log-level", "warning"]  # fmt: skip
            if pin is not None:
                argv = ["taskset", "-c", pin, *argv]
            with log_path.open("wb") as out:
                process = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, env=env, start_new_session=True)
            process.url = f"http://127.0.0.1:{port}"  # type: ignore[attr-defined]
            process.log_path = log_path  # type: ignore[attr-defined]
            pods.append(process)
        for process in pods:
            wait_until_ready(process.url, process, process.log_path, READY_TIMEOUT_S)
        yield pods
    finally:
        for process in pods:
            kill_group(process)


def job_config(job: Mapping[str, Any], replicas: int, max_envs: int = 256) -> RunnerConfig:
    """Return a RunnerConfig for ``job`` with ``replicas`` pods, every port free, quick heartbeats."""
    return RunnerConfig.model_validate(
        {
            "job": dict(job),
            "pods": {"replicas": replicas, "base_port": free_port_block(replicas), "max_envs": max_envs},
            "controller": {
                "port": free_port(),
                "heartbeat_interval_s": 0.5,
                "heartbeat_ttl_s": 5.0,
                "reconcile_interval_s": 0.25,
            },
        }
    )


@contextlib.contextmanager
def local_job(config: RunnerConfig, workdir: Path | None = None) -> Iterator[Any]:
    """Run a whole job (controller + pods, ``service.runner.LocalJob``) until it is ready.

    Yields:
        the started :class:`LocalJob` (``controller_url``, ``token``, ``processes``); stopped on exit.
    """
    from service.runner.job import LocalJob

    job = LocalJob(config, log_dir=workdir or tempfile.mkdtemp(prefix="vecsim-bench-job-"), grace_s=10)
    try:
        job.start()
        job.wait_ready(timeout=READY_TIMEOUT_S)
        yield job
    finally:
        job.stop()


class PeakRSS:
    """Samples the summed memory of process trees in a background thread; keeps the peaks.

    ``roots`` are pids (or a callable returning them, read at each sample); each root's
    descendants count too. RSS counts a page shared by several processes (the forkserver's
    imports, copied on write into every worker) once per process; PSS splits it among them, so
    PSS is the fair sum for many workers forked from one server. Use as a context manager.
    """

    def __init__(self, roots: Sequence[int] | Callable[[], Sequence[int]], every_s: float = 0.25) -> None:
        self._roots = roots
        self._every_s = every_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample_loop, name="peak-rss", daemon=True)
        self.peak_bytes = 0
        self.peak_pss_bytes = 0
        self.processes = 0

    def sample(self) -> int:
        """Return the summed RSS of the trees now (and update the peaks)."""
        import psutil  # here, not at the top: the scaling bench also runs where psutil is missing

        roots = self._roots() if callable(self._roots) else self._roots
        seen: dict[int, psutil.Process] = {}
        for pid in roots:
            with contextlib.suppress(psutil.Error):
                root = psutil.Process(pid)
                for process in [root, *root.children(recursive=True)]:
                    seen[process.pid] = process
        rss = pss = 0
        for process in seen.values():
            with contextlib.suppress(psutil.Error):
                memory = process.memory_full_info()
                rss, pss = rss + memory.rss, pss + memory.pss
        if rss > self.peak_bytes:
            self.peak_bytes, self.processes = rss, len(seen)
        self.peak_pss_bytes = max(self.peak_pss_bytes, pss)
        return rss

    def _sample_loop(self) -> None:
        while not self._stop.wait(self._every_s):
            self.sample()

    def __enter__(self) -> PeakRSS:
        self.sample()
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        self.sample()


def stepper(env: Any, steps: int, seed: int) -> Callable[[], float]:
    """Reset a gymnasium vector env; return a callable that steps it ``steps`` times with random
    actions (drawn here, up front) and returns the env-steps per second it reached."""
    import numpy as np

    rng = np.random.default_rng(seed)
    space = env.single_action_space
    actions = rng.uniform(space.low, space.high, (steps, env.num_envs, *space.shape)).astype(space.dtype)
    env.reset(seed=seed)

    def run() -> float:
        started = time.perf_counter()
        for t in range(steps):
            env.step(actions[t])
        return steps * env.num_envs / (time.perf_counter() - started)

    return run


def interleaved(contenders: Mapping[str, Callable[[], float]], rounds: int) -> dict[str, list[float]]:
    """Run every contender once per round, the order rotating each round; return its figures.

    Each contender is a callable that runs one measured stretch and returns its figure (e.g.
    env-steps/s). Rotating the order spreads warm-up and drifting load over all of them alike.
    """
    names = list(contenders)
    figures: dict[str, list[float]] = {name: [] for name in names}
    for r in range(rounds):
        shift = r % len(names)
        for name in names[shift:] + names[:shift]:
            figures[name].append(contenders[name]())
        log.info("round %d/%d: %s", r + 1, rounds, {n: round(v[-1], 1) for n, v in figures.items()})
    return figures


def paired_ratio(numerator: Sequence[float], denominator: Sequence[float]) -> dict[str, float]:
    """Return the median, min and max of per-round ratios ``numerator[r] / denominator[r]``.

    Rounds are paired because they ran in the same minute, under the same load.
    """
    ratios = [a / b for a, b in zip(numerator, denominator) if b > 0]
    return {
        "median": round(statistics.median(ratios), 3),
        "min": round(min(ratios), 3),
        "max": round(max(ratios), 3),
        "n": len(ratios),
    }


def rate_spread(values: Sequence[float]) -> dict[str, float]:
    """Return ``common.spread`` of per-round figures (median, min, max, n), rounded for the record."""
    return {key: round(value, 2) for key, value in spread(values).items()}


def wait_for_quiet(max_load: float = 1.5, timeout_s: float = 0.0, poll_s: float = 10.0) -> float:
    """Wait (at most ``timeout_s``) until the 1-minute load average is below ``max_load``.

    Returns:
        the load average when the wait ended (quiet or not).
    """
    deadline = time.monotonic() + timeout_s
    load = os.getloadavg()[0]
    while load >= max_load and time.monotonic() < deadline:
        time.sleep(poll_s)
        load = os.getloadavg()[0]
    if load >= max_load:
        log.info("load average %.2f (>= %.1f): figures will be noisier; ratios stay paired per round", load, max_load)
    return load


def setup_logging() -> None:
    """Log progress to stderr, so stdout holds the RESULT line only."""
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s", stream=sys.stderr)
    # One line per request would drown the progress lines.
    logging.getLogger("httpx").setLevel(logging.WARNING)
