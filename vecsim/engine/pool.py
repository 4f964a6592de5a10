"""The pod's worker pool: its worker processes, their pipes and their shared memory, and how many
envs each worker hosts.

One process per :class:`~vecsim.engine.worker.WorkerSpec`, started with ``forkserver`` by default
(the default fork context hangs once the parent holds an EGL context), in the manner of
gymnasium's ``AsyncVectorEnv``: one pipe per worker for orders and replies
(:mod:`vecsim.engine.protocol`) and one shared-memory block of every worker's observations and
result rows. A call messages only the workers that host an env it names and waits for those
alone, up to the step timeout: a hung worker is found when it has work, a dead one on any call,
since every call first and last polls every worker's pipe and process, one ``poll`` for all.
"""

from __future__ import annotations

import logging
import math
import multiprocessing
import multiprocessing.connection
import os
import select
import time
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from gymnasium.vector.utils import create_shared_memory, read_from_shared_memory

from vecsim.config import AUTO_ENVS_PER_WORKER, Assignment
from vecsim.engine import protocol
from vecsim.engine.errors import SimBuildError
from vecsim.engine.worker import WorkerSpec, results_space, worker_process
from vecsim.lifetime import exit_with_parent

log = logging.getLogger("vecsim.engine.pool")

_PROGRESS_EVERY_S = 10.0


class WorkerFailure(RuntimeError):
    """A worker process answered an order with an exception (it then exits)."""

    def __init__(self, worker: int, type_name: str, message: str) -> None:
        super().__init__(f"{type_name}: {message}")
        self.worker, self.type_name, self.message = worker, type_name, message


class WorkerPool:
    """The pod's worker processes: one per :class:`WorkerSpec`, each with its own pipe for
    orders and replies, and one shared-memory block of every worker's observations and result
    rows (``results``, ``[workers, local index, ...]``, :func:`results_space`). Only workers sent an
    order are waited for."""

    def __init__(self, specs: Sequence[WorkerSpec], context: str) -> None:
        ctx = multiprocessing.get_context(context)
        if context == "forkserver":
            # Takes effect when the pod's forkserver starts (before its first worker), not after.
            ctx.set_forkserver_preload(["__main__", "vecsim.forkserver_tie"])
        space = results_space(specs[0])
        shared = create_shared_memory(space, n=len(specs), ctx=ctx)
        # Held for the pool's life: a worker process attaches to it after start() returns.
        self._shared = shared
        self.results: dict[str, Any] = read_from_shared_memory(space, shared, n=len(specs))
        self.pipes: list[multiprocessing.connection.Connection] = []
        self.processes: list[Any] = []
        for index, spec in enumerate(specs):
            parent, child = ctx.Pipe()
            process = ctx.Process(
                target=_worker_main,
                name=f"vecsim-worker-{index}",
                args=(os.getpid(), index, spec, child, shared, len(specs)),
                daemon=True,
            )
            process.start()
            child.close()
            self.pipes.append(parent)
            self.processes.append(process)
        self._fds = [pipe.fileno() for pipe in self.pipes]
        self._worker_of = {fd: index for index, fd in enumerate(self._fds)}
        # Every worker's pipe and process sentinel, watched at once: one poll finds any that ended.
        self._ended = select.poll()
        for index, process in enumerate(self.processes):
            for fd in (self._fds[index], process.sentinel):
                self._ended.register(fd, select.POLLIN)
                self._worker_of[fd] = index

    def send(self, worker: int, order: str, *args: Any) -> None:
        """Send worker ``worker`` an order (a :class:`Worker` method) and its arguments: a ``run``
        of one :class:`Order` in binary where it can be (:func:`~vecsim.engine.protocol.encode_run`), else pickled."""
        message = protocol.encode_run(args[0]) if order == "run" and len(args) == 1 else None
        if message is None:
            protocol.send_object(self.pipes[worker], (order, args))
        else:
            protocol.send(self.pipes[worker], message)

    def receive(self, workers: Sequence[int], timeout_s: float | None) -> dict[int, Any]:
        """Wait for the reply of each of ``workers``; return ``{worker: result}``.

        Raises:
            multiprocessing.TimeoutError: not every one answered within ``timeout_s``.
            WorkerFailure: a worker answered with an exception.
            EOFError, OSError: a worker's pipe closed (it died).
        """
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        pending = {self._fds[worker]: worker for worker in workers}
        waiting = select.poll()
        for fd in pending:
            waiting.register(fd, select.POLLIN)
        replies: dict[int, Any] = {}
        while pending:
            wait_ms = None if deadline is None else max(math.ceil(1e3 * (deadline - time.monotonic())), 0)
            ready = waiting.poll(wait_ms)
            if not ready:
                raise multiprocessing.TimeoutError(f"{len(pending)} of {len(workers)} workers did not answer")
            for fd, _events in ready:
                worker = pending.pop(fd)
                waiting.unregister(fd)
                replies[worker] = self._decode_reply(worker, self.pipes[worker])
        return replies

    @staticmethod
    def _decode_reply(worker: int, pipe: multiprocessing.connection.Connection) -> Any:
        """Read a worker's reply (an object read by multiprocessing itself); return its result.
        Raises WorkerFailure for a failure."""
        ok, result = pipe.recv()
        if not ok:
            type_name, text, trace = result
            log.error("worker %d failed:\n%s", worker, trace)
            raise WorkerFailure(worker, type_name, text)
        return result

    def dead(self) -> int | None:
        """The first worker whose process has ended, or None (one poll of every pipe and process).

        Between calls no reply is due, so a worker's pipe that can be read is one that closed:
        the process has ended, seen before its parent learns its exit code."""
        ended = self._ended.poll(0)
        if not ended:
            return None
        return min(self._worker_of[fd] for fd, _events in ended)

    def close(self) -> None:
        """End every worker process (terminating cannot hang on a stuck one). Returns None."""
        for process in self.processes:
            if process.is_alive():
                process.terminate()
        for pipe in self.pipes:
            pipe.close()
        for process in self.processes:
            process.join()


def start_pool(specs: Sequence[WorkerSpec], context: str, build_timeout_s: float | None) -> WorkerPool:
    """Start one worker per spec and wait until each has built, reset and warmed its envs,
    logging each worker as it lands and the build's progress every 10 s.

    Raises:
        SimBuildError: a worker failed to build, or the build took over ``build_timeout_s``
            (every worker is ended then).
    """
    task_ids = [task for spec in specs for task in spec.task_ids]
    log.info(
        "building %d envs (%s) in %d worker processes, %d envs per worker",
        len(task_ids),
        ", ".join(f"{task} x{n}" for task, n in Counter(task_ids).items()),
        len(specs),
        specs[0].envs_per_worker,
    )
    started = time.monotonic()
    pool = WorkerPool(specs, context)
    try:
        for worker in range(len(specs)):
            pool.send(worker, "build")
        took = _wait_for_build(pool, specs, started, build_timeout_s)
    except SimBuildError:
        pool.close()
        raise
    except WorkerFailure as exc:
        pool.close()
        if exc.type_name == SimBuildError.__name__:
            raise SimBuildError(exc.message) from None
        raise SimBuildError(f"building envs failed: {exc}") from None
    except Exception as exc:
        pool.close()
        raise SimBuildError(f"building envs failed: {type(exc).__name__}: {exc}") from exc
    log.info("built %d envs in %.1f s", len(task_ids), time.monotonic() - started)
    if took:
        # The warm-up, in one line: what a trainer's first call would otherwise have paid.
        log.info(
            "warm-up done: first step (step path, compiled kernels) %.1f s, first render of "
            "every camera %.1f s (slowest worker's)",
            max(t["warm"] for t in took),
            max(t["render"] for t in took),
        )
    return pool


def _wait_for_build(
    pool: WorkerPool, specs: Sequence[WorkerSpec], started: float, build_timeout_s: float | None
) -> list[dict[str, float]]:
    """Wait for every worker's build, logging each as it lands; return their timings."""
    pipes = {pipe: index for index, pipe in enumerate(pool.pipes)}
    pending = set(pipes)
    timings: list[dict[str, float]] = []
    last_report = started
    while pending:
        elapsed = time.monotonic() - started
        if build_timeout_s is not None and elapsed > build_timeout_s:
            raise SimBuildError(
                f"building envs took over {build_timeout_s} s; "
                f"{len(pipes) - len(pending)} of {len(pipes)} workers were ready"
            )
        wait_s = _PROGRESS_EVERY_S
        if build_timeout_s is not None:
            wait_s = min(wait_s, max(build_timeout_s - elapsed, 0.0))
        for pipe in multiprocessing.connection.wait(list(pending), timeout=wait_s):
            pending.discard(pipe)
            index = pipes[pipe]
            took = pool.receive([index], timeout_s=None)[index]
            timings.append(took)
            log.info(
                "worker %d/%d ready: %s (%.1f s: made %.1f s, reset %.1f s, warmed the first step %.1f s, "
                "warmed the cameras %.1f s)",
                index + 1,
                len(pipes),
                specs[index].describe(),
                time.monotonic() - started,
                took["make"],
                took["reset"],
                took["warm"],
                took["render"],
            )
        if pending and time.monotonic() - last_report >= _PROGRESS_EVERY_S:
            last_report = time.monotonic()
            log.info(
                "still building: %d of %d workers ready after %.0f s",
                len(pipes) - len(pending),
                len(pipes),
                last_report - started,
            )
    return timings


def _worker_main(pod_pid: int, *args: Any) -> None:
    """A worker process: ends with its parent, then serves orders (:func:`worker_process`).

    Its parent is the forkserver (tied to the pod: :mod:`vecsim.forkserver_tie`) or, in
    the other start methods, the pod's sim thread, which lives as long as the pool; either way
    a SIGKILLed pod leaves no worker behind, even one stuck in a step."""
    exit_with_parent(pod_pid)
    worker_process(*args)


def available_cores() -> int:
    """Return how many cores this process may use: its CPU affinity, capped by a cgroup v2
    CPU quota (a Kubernetes CPU limit) when one is set. At least 1."""
    cores = len(os.sched_getaffinity(0))
    try:
        quota, period = Path("/sys/fs/cgroup/cpu.max").read_text().split()
        if quota != "max":
            cores = min(cores, math.ceil(int(quota) / int(period)))
    except (OSError, ValueError):
        pass
    return max(cores, 1)


def auto_envs_per_worker(block_sizes: Sequence[int], cores: int) -> int:
    """Return the fewest envs per worker that keep a pod's workers within ``cores``.

    A worker hosts consecutive envs whatever their tasks, so the blocks pack as one run:
    ``ceil(envs / cores)`` envs per worker, ``ceil(envs / that)`` workers (at most ``cores``).
    No envs at all: 1.
    """
    envs = sum(max(n, 0) for n in block_sizes)
    return max(1, math.ceil(envs / max(cores, 1)))


def resolve_envs_per_worker(assignment: Assignment, cores: int | None = None) -> int:
    """Return the envs per worker a pod runs ``assignment`` with.

    Its ``envs_per_worker``, or for 0 (auto) :func:`auto_envs_per_worker` over its task blocks and
    ``cores`` (default :func:`available_cores`): at most one worker per core, whatever the scenes.
    Cheap gym scenes gain most (a worker costs ~0.1 ms of pipe and shared-memory traffic per call,
    more than their physics); robot scenes with cameras step about as fast as with one env per
    worker (the cores are busy either way) in a fraction of the memory, since most of a worker's
    memory is paid once per process (``docs/pod.md``: a LIBERO worker ~1.2 GB, ~0.3 GB per env).
    """
    if assignment.envs_per_worker != AUTO_ENVS_PER_WORKER:
        return assignment.envs_per_worker
    return auto_envs_per_worker([b.num_envs for b in assignment.tasks], cores or available_cores())
