"""Benchmark 7, cheap scenes: a pod that hosts several envs per worker process, against gymnasium's
own AsyncVectorEnv of the same envs on the same cores.

For a scene whose physics costs ~0.05 ms a step (gymnasium's HalfCheetah-v5), one process per
env spends more on the inter-process hop than on the physics. A pod's workers each host a batch
of envs (``envs_per_worker``); with ``envs_per_worker: auto`` (0, the default) the pod picks the
split itself (``vecsim.engine.resolve_envs_per_worker``): for cheap scenes the fewest envs per worker
that keep its workers within its cores, for robot scenes or cameras one env per worker.

Contenders, each stepping all N envs once per call with NEXT_STEP autoreset, same episode cap:

- ``async``: ``gymnasium.vector.AsyncVectorEnv`` over ``vecsim.engine.tasks.make_env``, one process per
  env, in this process (the baseline);
- ``pod_auto``: one pod (``vecsim pod``) with ``envs_per_worker: auto``, reached over HTTP by
  ``HTTPVectorEnv``;
- ``pod_1``: the same pod with one env per worker (the old default);
- ``sync`` (cheap scenes only): every env stepped in this one process, the ceiling without any
  process hop.

Two scene sets: ``cheap`` (HalfCheetah-v5, no camera, at several env counts: the pod pays a fixed
cost per call, AsyncVectorEnv one per env) and ``robosuite`` (the tiny suite, two cameras).
``--quick`` (the smoke test) runs 4 HalfCheetahs only. Everything is built first, then the
contenders take turns, the order rotating each round, so that load from other processes falls on
all alike; every figure is a ratio to the baseline in the same round.

    python bench/bench_cheap_scenes.py [--quick] [--rounds 5] [--envs 8,32,64]

Prints ``RESULT {json}`` and writes out/bench/bench_cheap_scenes.json.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
from typing import Any

import gymnasium
from lib.pods import (
    READY_TIMEOUT_S,
    interleaved,
    paired_ratio,
    rate_spread,
    setup_logging,
    standalone_pods,
    stepper,
    wait_for_quiet,
)
from lib.records import write_result
from gymnasium.vector import AsyncVectorEnv, AutoresetMode, SyncVectorEnv

from vecsim.client import HTTPVectorEnv
from vecsim.config import AUTO_ENVS_PER_WORKER, Assignment, CameraConfig, TaskBlock
from vecsim.engine import available_cores, resolve_envs_per_worker
from vecsim.engine.tasks import make_env

log = logging.getLogger("bench.cheap_scenes")

TARGET_CHEAP = 3.0  # pod_auto / async on cheap scenes
TARGET_ROBOSUITE = 1.0  # pod_auto / async on robosuite: no slower


def _assignment(
    name: str, blocks: list[tuple[str, int]], camera: CameraConfig, per_worker: int, cap: int
) -> Assignment:
    tasks, start = [], 0
    for task_id, n in blocks:
        tasks.append(TaskBlock(task_id=task_id, env_start=start, num_envs=n))
        start += n
    return Assignment(
        generation=0,
        job_id="bench",
        pod=name,
        stage_id=0,
        tasks=tuple(tasks),
        camera=camera,
        render="lean",
        envs_per_worker=per_worker,
        max_episode_steps=cap,
    )


def measure(
    blocks: list[tuple[str, int]], camera: CameraConfig, steps: int, rounds: int, cap: int, with_sync: bool
) -> dict[str, Any]:
    """Build every contender for one scene set, run the interleaved rounds; return the figures."""
    num_envs = sum(n for _, n in blocks)
    assignments = [
        _assignment("sim-auto", blocks, camera, AUTO_ENVS_PER_WORKER, cap),
        _assignment("sim-one", blocks, camera, 1, cap),
    ]
    per_worker = resolve_envs_per_worker(assignments[0])
    makers = [
        (lambda task_id=task_id: make_env(task_id, camera, "lean", cap)) for task_id, n in blocks for _ in range(n)
    ]
    log.info("%s: %d envs; auto picks %d envs per worker on %d cores", blocks, num_envs, per_worker, available_cores())
    with contextlib.ExitStack() as stack:
        pods = stack.enter_context(standalone_pods(assignments, ready_timeout_s=READY_TIMEOUT_S))
        envs: dict[str, gymnasium.vector.VectorEnv] = {
            "async": AsyncVectorEnv(makers, context="forkserver", autoreset_mode=AutoresetMode.NEXT_STEP),
            "pod_auto": HTTPVectorEnv(pod_urls=[pods[0].url]),
            "pod_1": HTTPVectorEnv(pod_urls=[pods[1].url]),
        }
        if with_sync:
            envs["sync"] = SyncVectorEnv(makers, autoreset_mode=AutoresetMode.NEXT_STEP)
        for env in envs.values():
            stack.callback(env.close)
        contenders = {name: stepper(env, steps, seed=i) for i, (name, env) in enumerate(envs.items())}
        for run in contenders.values():
            run()  # warm-up: first calls pay for connections, caches and page faults
        figures = interleaved(contenders, rounds)
    return {
        "blocks": [list(b) for b in blocks],
        "num_envs": num_envs,
        "camera": camera.model_dump(mode="json"),
        "steps_per_round": steps,
        "auto_envs_per_worker": per_worker,
        "env_steps_per_s": {name: rate_spread(values) for name, values in figures.items()},
        "ratio_pod_auto_vs_async": paired_ratio(figures["pod_auto"], figures["async"]),
        "ratio_pod_1_vs_async": paired_ratio(figures["pod_1"], figures["async"]),
        "ratio_pod_auto_vs_pod_1": paired_ratio(figures["pod_auto"], figures["pod_1"]),
        **({"ratio_pod_auto_vs_sync": paired_ratio(figures["pod_auto"], figures["sync"])} if with_sync else {}),
        "per_round": figures,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="tiny sizes, for the smoke test")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--envs", default="8,32,64", help="HalfCheetah env counts (cheap scenes), comma-separated")
    parser.add_argument("--wait-quiet-s", type=float, default=0.0, help="wait up to this long for load < 1.5")
    args = parser.parse_args()
    setup_logging()
    load_before = wait_for_quiet(timeout_s=args.wait_quiet_s)
    if args.quick:
        env_counts, cheap_steps, rounds = [4], 20, 2
    else:
        env_counts, cheap_steps, rounds = [int(n) for n in args.envs.split(",")], 200, args.rounds
    no_camera = CameraConfig(names=(), height=8, width=8)
    cheap = {
        n: measure([("gym/HalfCheetah-v5", n)], no_camera, cheap_steps, rounds, cap=1000, with_sync=True)
        for n in env_counts
    }
    robot: dict[str, Any] = {}
    if not args.quick:  # the same code as the cheap set; the smoke test keeps to cheap scenes
        blocks = [("tiny/lift", 2), ("tiny/stack", 2), ("tiny/door", 2)]
        robot = measure(blocks, CameraConfig(height=32, width=32), 10, rounds, cap=50, with_sync=False)
    cheap_ratios = {n: result["ratio_pod_auto_vs_async"]["median"] for n, result in cheap.items()}
    robot_ratio = robot["ratio_pod_auto_vs_async"]["median"] if robot else None
    # The headline is the largest env count: the regime where a pod of cheap scenes runs.
    headline = cheap_ratios[max(cheap_ratios)]
    summary = {
        "baseline": "gymnasium AsyncVectorEnv, one process per env",
        "ratio": headline,
        "ratio_by_envs": cheap_ratios,
        "ratio_robosuite": robot_ratio,
        "target": f">= {TARGET_CHEAP}x on cheap scenes; >= {TARGET_ROBOSUITE}x on robosuite",
        "met": headline >= TARGET_CHEAP and (robot_ratio is None or robot_ratio >= TARGET_ROBOSUITE),
        "quick": args.quick,
        "load_avg_before": round(load_before, 2),
        "cheap": {n: {k: v for k, v in result.items() if k != "per_round"} for n, result in cheap.items()},
        "robosuite": {k: v for k, v in robot.items() if k != "per_round"},
    }
    write_result("bench_cheap_scenes", summary, {"cheap": cheap, "robosuite": robot})


if __name__ == "__main__":
    main()
