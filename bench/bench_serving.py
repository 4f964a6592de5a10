"""Benchmark 3, serving overhead: the same envs through HTTP (controller + pod) or in process.

Contenders, for one set of envs, each stepping all of them once per call with NEXT_STEP
autoreset and random actions:

- ``http``: ``HTTPVectorEnv`` over a whole local job (``service.runner.LocalJob``: controller +
  one pod, token on), the pod running one env per worker process;
- ``inproc`` (the baseline): ``gymnasium.vector.AsyncVectorEnv`` in this process over the same
  envs (``vecsim.engine.tasks.make_env``), one worker process per env: the same number of workers;
- ``http_auto`` (cheap scenes only): the same job with ``envs_per_worker: auto``, the pod packing
  the envs into one worker per core (benchmark 7 looks at that split in detail);
- ``pool`` (a diagnosis, not a target): the pod's own worker pool (``vecsim.engine.TaskGroupedVectorEnv``,
  one env per worker) in this process, no HTTP: ``http`` / ``pool`` is what serving costs,
  ``pool`` / ``inproc`` what vecsim's workers cost against gymnasium's.

Beside each rate, the CPU seconds per env-step of the contender's processes other than this one
(the pod's server and workers; the in-process runs' workers).

Scene sets: ``libero`` (two libero_10 tasks x 2 envs, two 64x64 cameras, lean preset: the
simulation dominates) and ``cheap`` (gym HalfCheetah-v5 x 32, no camera: the simulator is nearly
free and the serving cost shows). ``--quick`` (the smoke test): 2 HalfCheetahs only.

Memory: the peak RSS of the pod's process tree (server, forkserver, workers) per env, against
the in-process run's workers (and their forkserver) per env, sampled through the rounds; and
the peak PSS, which counts pages the workers share with their forkserver once.

Everything is built first; then the contenders take turns, the order rotating each round, and
each figure is a ratio to the baseline of the same round.

    python bench/bench_serving.py [--quick] [--rounds 5] [--libero-steps 40] [--sets libero cheap] [--no-pool]

Prints ``RESULT {json}`` and writes out/bench/bench_serving.json.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
from typing import Any

import numpy as np
import psutil
from lib.pods import (
    READY_TIMEOUT_S,
    PeakRSS,
    interleaved,
    job_config,
    local_job,
    paired_ratio,
    process_trees,
    rate_spread,
    setup_logging,
    stepper,
    wait_for_quiet,
)
from lib.records import write_result
from gymnasium.vector import AsyncVectorEnv, AutoresetMode

from vecsim.client import HTTPVectorEnv
from vecsim.config import AUTO_ENVS_PER_WORKER, Assignment, CameraConfig, TaskBlock
from vecsim.engine import TaskGroupedVectorEnv
from vecsim.engine.tasks import make_env

log = logging.getLogger("bench.serving")

TARGETS = {"libero": 0.9, "cheap": 0.7}
MIB = 1024 * 1024
CAP = 300  # max_episode_steps of every env, served or in process


def _workers_and_forkserver(env: AsyncVectorEnv) -> list[int]:
    """The pids of an AsyncVectorEnv's workers and of the forkserver that started them."""
    pids = [process.pid for process in env.processes]
    with contextlib.suppress(psutil.Error):
        parent = psutil.Process(pids[0]).ppid()
        if parent != os.getpid():
            pids.append(parent)
    return pids


def _job(name: str, tasks: list[str], per_task: int, camera: CameraConfig, envs_per_worker: int) -> dict[str, Any]:
    return {
        "job_id": f"serving-{name}",
        "tasks": tasks,
        "group_size": per_task,
        "num_stages": 1,
        "pods_per_stage": 1,
        "camera": camera.model_dump(mode="json"),
        "render": "lean",
        "envs_per_worker": envs_per_worker,
        "max_episode_steps": CAP,
    }


class _PoolVectorEnv:
    """The pod's worker pool in this process, stepped like a vector env (all envs each step)."""

    def __init__(self, tasks: list[str], per_task: int, camera: CameraConfig) -> None:
        blocks, start = [], 0
        for task in tasks:
            blocks.append(TaskBlock(task_id=task, env_start=start, num_envs=per_task))
            start += per_task
        assignment = Assignment(
            generation=0,
            job_id="serving-pool",
            pod="pool",
            stage_id=0,
            tasks=tuple(blocks),
            camera=camera,
            render="lean",
            envs_per_worker=1,
            max_episode_steps=CAP,
        )
        # Spawned, not from this process's forkserver: that one is the in-process run's, and its
        # children (the memory and CPU counted for ``inproc``) must stay that run's workers.
        self.env = TaskGroupedVectorEnv(assignment, context="spawn")
        self.num_envs = start
        self.single_action_space = self.env.single_action_space
        self._all = np.arange(start, dtype=np.int64)
        self._ended = np.zeros(start, dtype=bool)

    def reset(self, seed: int) -> None:
        self.env.reset_envs(self._all, np.zeros(self.num_envs, dtype=np.int64))

    def step(self, actions: np.ndarray) -> None:
        # NEXT_STEP autoreset, as the other contenders: an env that ended is reset instead of stepped.
        ended = self._ended
        if ended.any():
            self.env.reset_envs(self._all[ended], np.zeros(int(ended.sum()), dtype=np.int64))
        going = self._all[~ended]
        _, _, terminated, truncated, _ = self.env.step_envs(going, actions[~ended])
        self._ended = np.zeros(self.num_envs, dtype=bool)
        self._ended[going] = np.asarray(terminated) | np.asarray(truncated)

    def close(self) -> None:
        self.env.close()


def _tree_cpu_s(pids: list[int]) -> float:
    """CPU seconds (user + system) used so far by the process trees of ``pids``, each process
    counted once (the in-process run's workers are both named and its forkserver's children)."""
    total = 0.0
    for process in process_trees(pids).values():
        with contextlib.suppress(psutil.Error):
            times = process.cpu_times()
            total += times.user + times.system
    return total


def _with_cpu(run: Any, pids: list[int], per_call: int, sink: list[float]) -> Any:
    """``run``, also appending to ``sink`` the CPU ms per env-step its processes spent in it."""

    def measured() -> float:
        before = _tree_cpu_s(pids)
        rate = run()
        sink.append(round((_tree_cpu_s(pids) - before) * 1000 / per_call, 3))
        return rate

    return measured


def _local_job(job: dict[str, Any]) -> contextlib.AbstractContextManager[Any]:
    """``job`` run by one pod on free ports (room for a LIBERO set's envs), until it is ready."""
    config = job_config(job, replicas=1, max_envs=256, heartbeat_ttl_s=5.0)
    return local_job(config, ready_timeout_s=READY_TIMEOUT_S)


def measure(
    name: str,
    tasks: list[str],
    per_task: int,
    camera: CameraConfig,
    steps: int,
    rounds: int,
    with_auto: bool,
    with_pool: bool = False,
) -> dict[str, Any]:
    """Build the contenders for one scene set, run the interleaved rounds; return the figures."""
    num_envs = len(tasks) * per_task
    makers = [
        (lambda task_id=task_id: make_env(task_id, camera, "lean", CAP)) for task_id in tasks for _ in range(per_task)
    ]
    log.info("%s: %d envs (%s x %d), camera %s", name, num_envs, tasks, per_task, camera.model_dump())
    with contextlib.ExitStack() as stack:
        running = stack.enter_context(_local_job(_job(name, tasks, per_task, camera, 1)))
        envs: dict[str, Any] = {"http": HTTPVectorEnv(controller_url=running.controller_url, token=running.token)}
        if with_auto:
            auto_job = _job(f"{name}-auto", tasks, per_task, camera, AUTO_ENVS_PER_WORKER)
            packed = stack.enter_context(_local_job(auto_job))
            envs["http_auto"] = HTTPVectorEnv(controller_url=packed.controller_url, token=packed.token)
        envs["inproc"] = AsyncVectorEnv(makers, context="forkserver", autoreset_mode=AutoresetMode.NEXT_STEP)
        if with_pool:
            envs["pool"] = _PoolVectorEnv(tasks, per_task, camera)
        for env in envs.values():
            stack.callback(env.close)
        trees = {"pod": [running.processes["sim-0"].pid], "inproc": _workers_and_forkserver(envs["inproc"])}
        if with_auto:
            trees["pod_auto"] = [packed.processes["sim-0"].pid]
        if with_pool:
            trees["pool"] = envs["pool"].env.worker_pids
        tree_of = {"http": "pod", "http_auto": "pod_auto", "inproc": "inproc", "pool": "pool"}
        cpu_ms: dict[str, list[float]] = {key: [] for key in envs}
        contenders = {
            key: _with_cpu(stepper(env, steps, seed=i), trees[tree_of[key]], steps * num_envs, cpu_ms[key])
            for i, (key, env) in enumerate(envs.items())
        }
        for run in contenders.values():
            run()  # warm-up
        for sink in cpu_ms.values():
            sink.clear()
        with contextlib.ExitStack() as sampling:
            memory = {key: sampling.enter_context(PeakRSS(pids)) for key, pids in trees.items()}
            figures = interleaved(contenders, rounds)
    ratio = paired_ratio(figures["http"], figures["inproc"])
    return {
        "tasks": tasks,
        "envs_per_task": per_task,
        "num_envs": num_envs,
        "camera": camera.model_dump(mode="json"),
        "steps_per_round": steps,
        "env_steps_per_s": {name: rate_spread(values) for name, values in figures.items()},
        "ratio_http_vs_inproc": ratio,
        **({"ratio_http_auto_vs_inproc": paired_ratio(figures["http_auto"], figures["inproc"])} if with_auto else {}),
        **(
            {
                "ratio_http_vs_pool": paired_ratio(figures["http"], figures["pool"]),
                "ratio_pool_vs_inproc": paired_ratio(figures["pool"], figures["inproc"]),
            }
            if with_pool
            else {}
        ),
        "cpu_ms_per_env_step": {key: rate_spread(values) for key, values in cpu_ms.items() if values},
        "target": TARGETS[name],
        "met": ratio["median"] >= TARGETS[name],
        "peak_rss_mib_per_env": {key: round(rss.peak_bytes / MIB / num_envs, 1) for key, rss in memory.items()},
        "peak_pss_mib_per_env": {key: round(rss.peak_pss_bytes / MIB / num_envs, 1) for key, rss in memory.items()},
        "processes": {key: rss.processes for key, rss in memory.items()},
        "per_round": figures,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="tiny sizes, for the smoke test")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument(
        "--libero-steps",
        type=int,
        default=40,
        help="steps of the LIBERO set per contender and round (a step is ~15-60 ms: rounds of 8, "
        "the old count, left the median to a handful of calls)",
    )
    parser.add_argument(
        "--no-pool",
        action="store_true",
        help="leave the pool contender out of the LIBERO set (its 4 workers building beside the pod's "
        "and the in-process run's ran a 24 GiB machine out of memory)",
    )
    parser.add_argument("--wait-quiet-s", type=float, default=0.0, help="wait up to this long for load < 1.5")
    parser.add_argument(
        "--sets", nargs="+", choices=("libero", "cheap"), default=["libero", "cheap"], help="the scene sets to measure"
    )
    args = parser.parse_args()
    setup_logging()
    load_before = wait_for_quiet(timeout_s=args.wait_quiet_s)
    results: dict[str, dict[str, Any]] = {}
    if args.quick:
        # The LIBERO set runs the same code with other envs; the smoke test keeps to cheap ones.
        results["cheap"] = measure("cheap", ["gym/HalfCheetah-v5"], 2, CameraConfig(names=()), 10, 2, with_auto=False)
    else:
        if "libero" in args.sets:
            camera = CameraConfig(names=("agentview", "robot0_eye_in_hand"), height=64, width=64)
            libero = ["libero_10/0", "libero_10/1"]
            results["libero"] = measure(
                "libero", libero, 2, camera, args.libero_steps, args.rounds, with_auto=False, with_pool=not args.no_pool
            )
        if "cheap" in args.sets:
            cheap = ["gym/HalfCheetah-v5"]
            results["cheap"] = measure("cheap", cheap, 32, CameraConfig(names=()), 100, args.rounds, True)
    headline = results.get("libero") or results["cheap"]
    cheap_set = results.get("cheap", {})
    summary = {
        "baseline": "gymnasium AsyncVectorEnv in process, same envs, one worker process per env",
        "ratio": headline["ratio_http_vs_inproc"]["median"],
        "ratio_cheap": cheap_set.get("ratio_http_vs_inproc", {}).get("median"),
        "ratio_cheap_auto": cheap_set.get("ratio_http_auto_vs_inproc", {}).get("median"),
        "target": f">= {TARGETS['libero']} (LIBERO, two cameras); >= {TARGETS['cheap']} (HalfCheetah x 32)",
        "met": all(result["met"] for result in results.values()),
        "quick": args.quick,
        "load_avg_before": round(load_before, 2),
        **{name: {k: v for k, v in result.items() if k != "per_round"} for name, result in results.items()},
    }
    write_result("bench_serving", summary, results)


if __name__ == "__main__":
    main()
