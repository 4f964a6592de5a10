"""Helpers of the serving benchmarks: interleaved rounds, paired ratios, memory of process
trees, and a bounded wait for a quiet machine.

Pods, controllers and whole jobs on free loopback ports are started by the tests' helpers
(``tests/support/service_procs.py``: ``standalone_pods``, ``controller_server``, ``Server``,
``job_config``, ``local_job``), which this module puts on ``sys.path`` (the checkout's
``tests/``) and re-exports, so benchmarks and tests run their processes one way. Every process started there runs in its own session and is killed,
with its whole process group, when its context manager exits, whatever happened inside.
"""

from __future__ import annotations

import contextlib
import logging
import os
import statistics
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from .records import spread

import service
from service.runner.ports import free_port, free_port_block

# The checkout's tests/, beside the service package (a copy of bench/ elsewhere finds it too).
sys.path.insert(0, str(Path(service.__file__).resolve().parents[1] / "tests"))
from support.service_procs import (  # found through the path just added
    Server,
    clean_env,
    controller_server,
    job_config,
    local_job,
    running,
    standalone_pods,
)

__all__ = [
    "READY_TIMEOUT_S",
    "PeakRSS",
    "Server",
    "clean_env",
    "controller_server",
    "free_port",
    "free_port_block",
    "interleaved",
    "job_config",
    "local_job",
    "paired_ratio",
    "rate_spread",
    "running",
    "setup_logging",
    "standalone_pods",
    "stepper",
    "wait_for_quiet",
]

log = logging.getLogger("bench")

# LIBERO scenes take minutes to build on a CPU: the benchmarks wait longer than the tests do.
READY_TIMEOUT_S = 600.0


def process_trees(roots: Sequence[int]) -> dict[int, Any]:
    """The live processes of the trees rooted at ``roots`` (each root and its descendants), each
    once by pid however many trees hold it: ``{pid: psutil.Process}``."""
    import psutil  # here, not at the top: the scaling bench also runs where psutil is missing

    seen: dict[int, psutil.Process] = {}
    for pid in roots:
        with contextlib.suppress(psutil.Error):
            root = psutil.Process(pid)
            for process in [root, *root.children(recursive=True)]:
                seen[process.pid] = process
    return seen


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

        seen = process_trees(self._roots() if callable(self._roots) else self._roots)
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
    """Return ``records.spread`` of per-round figures (median, min, max, n), rounded for the record."""
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
