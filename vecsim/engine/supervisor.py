"""The worker pool's life: its workers built, sent orders one call at a time, watched, closed.

:class:`WorkerSupervisor` starts a :class:`~vecsim.engine.pool.WorkerPool` and waits for every
worker to build its envs, logging each as it lands and the warm-up it paid. After that it is the
one way to the workers: a call's orders go out and their replies come back under one lock, and
the pool's shared memory is read under the same lock, so one call's results are never the next
call's. A worker that died, hung past the step timeout or failed breaks the supervisor for good
(:class:`~vecsim.engine.errors.SimCrashedError`, naming the worker and the envs it hosted): the
pod must rebuild.

Example::

    supervisor = WorkerSupervisor(specs, "forkserver", timeout_s=60.0, build_timeout_s=600.0)
    # Worker 0's first env to state 3; then its observation and result rows.
    reset = Order(local_indices=np.array([0]), state_ids=np.array([3]))
    obs, rows, replies = supervisor.run({0: reset}, workers=np.array([0]), local_indices=np.array([0]))
    supervisor.close()
"""

from __future__ import annotations

import logging
import multiprocessing
import multiprocessing.connection
import threading
import time
from collections import Counter
from collections.abc import Sequence
from typing import Any

import numpy as np

from vecsim.engine.errors import SimBuildError, SimCrashedError
from vecsim.engine.pool import WorkerFailure, WorkerPool
from vecsim.engine.protocol import Order, Reply
from vecsim.engine.worker import WorkerSpec

log = logging.getLogger("vecsim.engine.supervisor")

_PROGRESS_EVERY_S = 10.0


def gather(tree: Any, workers: np.ndarray, local_indices: np.ndarray) -> Any:
    """The rows ``(workers[i], local_indices[i])`` of a tree of ``[worker, local index, ...]`` arrays."""
    # Fancy indexing copies, so results never alias the shared memory the next call overwrites.
    if isinstance(tree, dict):
        return {key: gather(sub, workers, local_indices) for key, sub in tree.items()}
    if isinstance(tree, tuple):
        return tuple(gather(sub, workers, local_indices) for sub in tree)
    return tree[workers, local_indices]


class WorkerSupervisor:
    """The workers of ``specs``, built and then spoken to one call at a time (thread-safe).

    Args:
        specs: one per worker, in worker order (none: no process is started).
        context: multiprocessing start method for the workers.
        timeout_s: longest wait for the workers on one call; None waits forever.
        build_timeout_s: longest wait for the workers to build; None waits forever.

    Raises:
        SimBuildError: a worker failed to build its envs or the build outlasted ``build_timeout_s``
            (every worker is then stopped).
    """

    def __init__(
        self, specs: Sequence[WorkerSpec], context: str, *, timeout_s: float | None, build_timeout_s: float | None
    ) -> None:
        self._specs = list(specs)
        self._timeout_s = timeout_s
        self._lock = threading.Lock()
        self._broken: str | None = None
        self._closed = False
        self._pool: WorkerPool | None = None
        if self._specs:
            counts = Counter(task for spec in self._specs for task in spec.task_ids)
            log.info(
                "building %d envs (%s) in %d worker processes, %d envs per worker",
                sum(counts.values()),
                ", ".join(f"{task} x{n}" for task, n in counts.items()),
                len(self._specs),
                self._specs[0].envs_per_worker,
            )
            self._pool = WorkerPool(self._specs, context)
            self._build(build_timeout_s)

    @property
    def pids(self) -> list[int]:
        """Process ids of the workers, in worker order."""
        return [] if self._pool is None else [process.pid for process in self._pool.processes]

    def run(
        self, orders: dict[int, Order | tuple[Order, ...]], workers: np.ndarray, local_indices: np.ndarray
    ) -> tuple[Any, np.ndarray, dict[int, Reply]]:
        """Send each worker of ``orders`` its ``run`` order (a tuple: several, run in turn; no other
        worker hears of the call); return the observations of envs ``(workers[i],
        local_indices[i])``, their result rows ``[n, max_chunk, 4]`` and the replies.

        Raises:
            SimCrashedError: a worker died, did not answer within the timeout, or failed.
        """
        with self._lock:
            replies: dict[int, Reply] = self._exchange("run", orders)
            assert self._pool is not None
            obs = gather(self._pool.results["obs"], workers, local_indices)
            rows = self._pool.results["flags"][workers, local_indices]
        return obs, rows, replies

    def ask(self, order: str, args: dict[int, Any]) -> dict[int, Any]:
        """Send ``order`` to each worker in ``args`` (worker -> its one argument), and to no other;
        return each one's reply.

        Raises:
            SimCrashedError: a worker died, did not answer within the timeout, or failed.
        """
        with self._lock:
            return self._exchange(order, args)

    def observations(self, workers: np.ndarray, local_indices: np.ndarray) -> Any:
        """A copy of the observations of envs ``(workers[i], local_indices[i])`` as they stand,
        without a worker call.

        Raises:
            SimCrashedError: a worker died or failed, or the workers are closed.
        """
        with self._lock:
            self._check_usable()
            assert self._pool is not None
            return gather(self._pool.results["obs"], workers, local_indices)

    def close(self) -> None:
        """Stop the worker processes. Idempotent. Returns None."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            if self._pool is not None:
                # Terminating cannot hang on a stuck worker, and the workers hold nothing to save.
                self._pool.close()
                log.info("closed %d worker processes", len(self._specs))

    # Building.

    def _build(self, build_timeout_s: float | None) -> None:
        assert self._pool is not None
        started = time.monotonic()
        try:
            for worker in range(len(self._specs)):
                self._pool.send(worker, "build")
            took = self._wait_for_build(started, build_timeout_s)
        except SimBuildError:
            self._pool.close()
            raise
        except WorkerFailure as exc:
            self._pool.close()
            if exc.type_name == SimBuildError.__name__:
                raise SimBuildError(exc.message) from None
            raise SimBuildError(f"building envs failed: {exc}") from None
        except Exception as exc:
            self._pool.close()
            raise SimBuildError(f"building envs failed: {type(exc).__name__}: {exc}") from exc
        log.info("built %d envs in %.1f s", sum(len(s.env_indices) for s in self._specs), time.monotonic() - started)
        # The warm-up, in one line: what a trainer's first call would otherwise have paid.
        log.info(
            "warm-up done: first step (step path, compiled kernels) %.1f s, first render of "
            "every camera %.1f s (slowest worker's)",
            max(t["warm"] for t in took),
            max(t["render"] for t in took),
        )

    def _wait_for_build(self, started: float, build_timeout_s: float | None) -> list[dict[str, float]]:
        """Wait for every worker's build, logging each as it lands; return their timings."""
        assert self._pool is not None
        pipes = {pipe: index for index, pipe in enumerate(self._pool.pipes)}
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
                took = self._pool.receive([index], timeout_s=None)[index]
                timings.append(took)
                log.info(
                    "worker %d/%d ready: %s (%.1f s: made %.1f s, reset %.1f s, warmed the first step %.1f s, "
                    "warmed the cameras %.1f s)",
                    index + 1,
                    len(pipes),
                    self._specs[index].describe(),
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

    # Calls and their failures.

    def _exchange(self, order: str, args: dict[int, Any]) -> dict[int, Any]:
        """:meth:`ask` with the lock held. Any worker found dead, before or after, breaks the pool."""
        self._check_usable()
        assert self._pool is not None
        try:
            for worker, arg in args.items():
                # A tuple is several orders for one worker (a reset and a step of one call).
                self._pool.send(worker, order, *(arg if isinstance(arg, tuple) else (arg,)))
            replies = self._pool.receive(list(args), self._timeout_s)
        except multiprocessing.TimeoutError as exc:
            self._broken = f"the workers did not answer within {self._timeout_s} s ({exc})"
            raise SimCrashedError(self._broken) from exc
        except Exception as exc:
            self._broken = self._failure(exc)
            raise SimCrashedError(self._broken) from exc
        # A worker that died while others worked breaks the pod as surely as one that had work.
        self._check_usable()
        return replies

    def _check_usable(self) -> None:
        if self._closed:
            raise SimCrashedError("the envs are closed")
        if self._broken is None:
            self._broken = self._dead_worker()
        if self._broken is not None:
            raise SimCrashedError(self._broken)

    def _dead_worker(self) -> str | None:
        assert self._pool is not None
        index = self._pool.dead()
        if index is None:
            return None
        hosted = self._specs[index].describe()
        process = self._pool.processes[index]
        process.join(timeout=0.5)  # its exit code, when its end is a matter of moments
        return f"worker {index} hosting {hosted} died with exit code {process.exitcode}"

    def _failure(self, exc: Exception) -> str:
        if isinstance(exc, WorkerFailure):
            hosted = self._specs[exc.worker].describe()
            return f"worker {exc.worker} hosting {hosted} failed: {exc}"
        # A worker whose pipe closed is exiting; give it a moment so the message can name it.
        deadline = time.monotonic() + 1.0
        dead = self._dead_worker()
        while dead is None and time.monotonic() < deadline:
            time.sleep(0.05)
            dead = self._dead_worker()
        return f"{dead or 'a worker failed'}: {type(exc).__name__}: {exc}"
