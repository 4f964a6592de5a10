"""MuJoCo physics alone in pinned processes, no vecsim in between: the machine's own scaling, the
baseline that serving is measured against (``bench_physics_scaling.py``, ``bench_chunks.py``).
"""

from __future__ import annotations

import logging
import os
import time
import traceback
from typing import Any

import numpy as np


def physics_worker(
    index: int,
    cpu: int,
    tasks: list[str],
    counts: list[int],
    paths: list[str],
    rounds: int,
    seconds: float,
    barrier: Any,
    results: Any,
) -> None:
    """Pin to ``cpu``, build the envs, then measure each (round, P) in lockstep with the others."""
    logging.basicConfig(level=logging.WARNING)
    try:
        os.sched_setaffinity(0, {cpu})
        from vecsim.config import CameraConfig
        from vecsim.engine.tasks import make_env

        envs = [make_env(task, CameraConfig(names=()), "lean") for task in tasks]
        for env in envs:
            env.reset(options={"state_id": 0})
        rng = np.random.default_rng(index)
        actions = [rng.uniform(-0.3, 0.3, (64, *env.action_space.shape)).astype(np.float32) for env in envs]

        def step_all(turn: int) -> None:
            for env, table in zip(envs, actions):
                _, _, terminated, truncated, _ = env.step(table[turn % len(table)])
                if terminated or truncated:
                    env.reset(options={"state_id": 0})

        step_all(0)  # warm-up
        results.put(("built", index, None))
        for round_ in range(rounds):
            for count in counts:
                for path in paths:
                    for env in envs:
                        if hasattr(env, "set_step_path"):  # robot tasks only
                            env.set_step_path(path)
                    barrier.wait(timeout=900)
                    if index < count:
                        turns, started = 0, time.perf_counter()
                        while time.perf_counter() - started < seconds:
                            step_all(turns)
                            turns += 1
                        rate = turns * len(envs) / (time.perf_counter() - started)
                        results.put(("rate", index, (round_, count, path, rate)))
                    barrier.wait(timeout=900)
    except Exception:
        results.put(("error", index, traceback.format_exc()))
        barrier.abort()
