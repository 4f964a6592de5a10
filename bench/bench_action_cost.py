"""What a LIBERO env-step costs under the action streams the chunks bench's contenders apply.

``bench_chunks.py`` compares each contender with a ceiling of bare processes stepping the same
scenes. The scenes are the same; the states are not: the ceiling's processes apply uniform
random actions within +-0.3 (a table of 64 per env, as :func:`bench_chunks.ceiling_worker`
does), the service alone a slow sine over half of each dimension's range
(:func:`lib.measure.scripted_actions`), and the loop a policy's action with a small sine
around it (``lib.policies.ChunkedPolicy``; an untrained policy's action is near constant, here
zero). If a step's physics depends on where the actions take the arm, a contender can pass the
ceiling in a round; this bench measures that apart.

One process on one core (``--cpu``) builds an env of each task (default LIBERO-10's ten, no
cameras drawn). Each round and stream (the order rotating each round): every env is reset to
the round's state id, then stepped ``--actions`` actions of that stream; the figure is the
physics milliseconds per env-step (the steps alone, not the resets), summed over the envs.
Ratios are per round against the ``policy`` stream (the loop's), medians over the rounds.

Commands::

    python bench/bench_action_cost.py --rounds 3 --cpu 1          # here: LIBERO-10, 64 actions
    python bench/bench_action_cost.py --quick                     # smoke: 2 tasks, 8 actions, 1 round

Writes out/bench/bench_action_cost[_quick].json and prints one ``RESULT {json}`` line.
"""

from __future__ import annotations

import argparse
import logging
import os
import statistics
import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from lib.measure import scripted_actions
from lib.policies import PIPELINE_K, chunk_offsets, random_actions
from lib.pods import interleaved, paired_ratio, rate_spread, setup_logging
from lib.records import write_result

log = logging.getLogger("bench.action_cost")

LIBERO_10 = [f"libero_10/{i}" for i in range(10)]


def random_stream(space: Any, seed: int) -> Callable[[int], np.ndarray]:
    """The ceiling's actions (:func:`lib.policies.random_actions`), cycled."""
    table = random_actions(np.random.default_rng(seed), space.shape)
    return lambda step: table[step % len(table)]


def sine_stream(space: Any) -> Callable[[int], np.ndarray]:
    """The service's actions: :func:`lib.measure.scripted_actions`, half of each dimension's range."""
    return lambda step: scripted_actions(space, step, 1)[0]


def policy_stream(space: Any, k: int = PIPELINE_K) -> Callable[[int], np.ndarray]:
    """The loop's actions from a near-constant policy: zero, with :func:`bench_chunks.chunk_offsets`
    around it within each chunk of ``k``, within the bounds."""
    low, high = np.asarray(space.low, np.float32), np.asarray(space.high, np.float32)
    offsets = chunk_offsets(space, k).numpy()
    return lambda step: np.clip(offsets[step % k], low, high)


def measure(
    envs: list[Any], streams: dict[str, list[Callable[[int], np.ndarray]]], actions: int, rounds: int
) -> tuple[dict[str, list[float]], dict[str, list[float]], list[float]]:
    """Per stream and round: physics ms per env-step over all envs; also per task (ms per step,
    per stream, over the rounds) and the reset seconds of every round."""
    per_task: dict[str, list[float]] = {name: [0.0] * len(envs) for name in streams}
    resets: list[float] = []
    turn = {"round": 0}

    def run(name: str) -> Callable[[], float]:
        def once() -> float:
            state_id = turn["round"] // len(streams)
            turn["round"] += 1
            begun = time.perf_counter()
            for env in envs:
                env.reset(options={"state_id": state_id})
            resets.append(time.perf_counter() - begun)
            total, steps = 0.0, 0
            for e, (env, act) in enumerate(zip(envs, streams[name], strict=True)):
                started = time.perf_counter()
                applied = 0
                for step in range(actions):
                    _, _, terminated, truncated, _ = env.step(act(step))
                    applied += 1
                    if terminated or truncated:
                        break
                spent = time.perf_counter() - started
                per_task[name][e] += 1000 * spent / max(applied, 1)
                total, steps = total + spent, steps + applied
            return 1000 * total / max(steps, 1)

        return once

    for e, env in enumerate(envs):  # warm-up, untimed: what a first step or reset compiles or loads
        env.reset(options={"state_id": 0})
        for stream in streams.values():
            env.step(stream[e](0))
    figures = interleaved({name: run(name) for name in streams}, rounds)
    return figures, {name: [v / rounds for v in values] for name, values in per_task.items()}, resets


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tasks", help="comma-separated task ids (default: LIBERO-10's ten)")
    parser.add_argument("--actions", type=int, help="actions per env and stream in a round (default 64)")
    parser.add_argument("--rounds", type=int, help="rounds (default 3)")
    parser.add_argument("--cpu", type=int, help="the core to pin this process to (default: unpinned)")
    parser.add_argument("--quick", action="store_true", help="smoke: 2 tasks, 8 actions, 1 round")
    args = parser.parse_args()
    setup_logging()
    tasks = args.tasks.split(",") if args.tasks else LIBERO_10[:2] if args.quick else LIBERO_10
    actions = args.actions or (8 if args.quick else 64)
    rounds = args.rounds or (1 if args.quick else 3)
    if actions < 1 or rounds < 1:
        parser.error(f"--actions and --rounds must be >= 1, got {actions} and {rounds}")
    if args.cpu is not None:
        if args.cpu not in os.sched_getaffinity(0):
            parser.error(f"--cpu {args.cpu}: this process may run on {sorted(os.sched_getaffinity(0))} only")
        os.sched_setaffinity(0, {args.cpu})
    from vecsim.config import CameraConfig
    from vecsim.engine.tasks import make_env

    started = time.perf_counter()
    # No cameras are drawn: the images are deferred and never asked for.
    envs = [make_env(task, CameraConfig(height=16, width=16)) for task in tasks]
    for env in envs:
        env.defer_images = True
    log.info("%d envs built in %.0f s", len(envs), time.perf_counter() - started)
    streams = {
        "random": [random_stream(env.action_space, seed) for seed, env in enumerate(envs)],
        "sine": [sine_stream(env.action_space) for env in envs],
        "policy": [policy_stream(env.action_space) for env in envs],
    }
    figures, per_task, resets = measure(envs, streams, actions, rounds)
    for env in envs:
        env.close()
    ms = {name: rate_spread(values) for name, values in figures.items()}
    ratios = {name: paired_ratio(figures[name], figures["policy"]) for name in ("random", "sine")}
    summary = {
        "baseline": "the loop's near-constant policy actions (ms per env-step of each stream over this one's, by round)",
        "ratio": ratios["random"]["median"],
        "ratio_by_stream": {name: r["median"] for name, r in ratios.items()},
        "ratio_spread": ratios,
        "physics_ms_per_env_step": ms,
        "per_task_ms_per_env_step": {
            task: {name: round(per_task[name][i], 3) for name in streams} for i, task in enumerate(tasks)
        },
        "reset_s_per_env": round(statistics.median(resets) / len(envs), 4),
        "quick": args.quick,
        "setup": {
            "tasks": tasks,
            "actions": actions,
            "rounds": rounds,
            "cpu": args.cpu,
            "streams": {
                "random": "uniform within +-0.3, a table of 64 per env (bench_chunks' ceiling)",
                "sine": "lib.measure.scripted_actions: half of each dimension's range (the service alone)",
                "policy": "zero plus ChunkedPolicy's 2% sine within chunks of 8 (the loop, an untrained policy)",
            },
        },
    }
    path = write_result("bench_action_cost" + ("_quick" if args.quick else ""), summary, {"per_round": figures})
    log.info("wrote %s", path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
