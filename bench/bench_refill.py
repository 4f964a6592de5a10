"""Refill against batch-at-once: EnvLoop env-steps/s over episodes of mixed length.

The same N trajectories (N = ``--waves`` x the job's envs), each capped at its own horizon,
spread evenly between 20% and 100% of ``--horizon`` (a seeded shuffle), as a scripted policy's
episodes that succeed or fail at different points would end. Two contenders, in interleaved
rounds, on the same pods:

- ``refill``: one ``EnvLoop.run`` of all N requests; an env whose trajectory ended starts the next
  waiting request at once.
- ``batch``: ``--waves`` runs of one env's worth of requests each, in request order: each run
  ends when its longest trajectory ends, its other envs idle meanwhile (the rollout before refill).

Both apply exactly the same actions (the sum of the horizons); env-steps/s = that sum / wall time.
The policy is scripted: zeros, each call taking ``--policy-ms`` (a sleep, as a GPU forward pass
takes about the same time for any batch). Ideal ratio: (longest / mean horizon) of a wave, ~1.67
for 20-100%, less the drain of the refill run's tail, where the envs' idle time costs: cores of
their own, or a per-call cost (policy, HTTP). Where the pods' cores are shared by all their envs
and the policy is free (a loaded small box), a call of fewer live envs is just faster and refill
gains little; nor where the trainer is the bound (``trainer_cpu_per_wall_s`` near 1: one
process handling every pod's answer), which ``--chunk K`` (K actions per env and policy call)
relieves K-fold for the same actions. Target (issue 27): refill >= 1.3x batch-at-once.

Where a pod's call goes (``call_split_ms``, per contender, medians over rounds): ``in_flight``, a
call's time from the client's send to its answer (median over calls); ``turnaround``, from one
answer of a pod to its next call (the pod idle while the trainer decodes, runs the policy and
encodes); and the pods' own means per call from their ``/metrics``: ``pod_step`` (the route's
simulate wall time), ``physics`` and ``render`` (worker seconds, summed over the pod's workers:
with one env a pod, within ``pod_step``). ``in_flight`` less ``pod_step``
is HTTP and serving.

    python bench/bench_refill.py --quick     # smoke: a gym scene at 8x8, 2 pods of 2 envs
    python bench/bench_refill.py             # dev box: tiny/lift 32x32, 2 pods of 4 envs
    python bench/bench_refill.py --gpu       # GPU node: libero_10/0 128x128, 12 pods of 1 env pinned one per core
    python bench/bench_refill.py --gpu --chunk 8   # the same, 8 actions per env and call

Prints ``RESULT {json}`` and writes out/bench/bench_refill.json.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import statistics
import time
from typing import Any

import numpy as np
import torch
from lib.measure import counted
from lib.pods import (
    READY_TIMEOUT_S,
    interleaved,
    paired_ratio,
    rate_spread,
    setup_logging,
    standalone_pods,
    wait_for_quiet,
)
from lib.records import with_flags, write_result

from vecsim.client import StageClient
from vecsim.config import Assignment, CameraConfig, TaskBlock
from vecsim.rollout import EnvLoop, RolloutStats

log = logging.getLogger("bench.refill")

TARGET = 1.3  # refill over batch-at-once
SHORTEST = 0.2  # the shortest episode, as a fraction of the horizon


class ScriptedPolicy:
    """Zero actions of the job's action shape, ``chunk`` of them per env and call (one: ``[n, A]``;
    more: ``[n, K, A]``), each call taking ``call_s`` (a sleep: a GPU forward pass, whose time
    hardly depends on the batch, without taking the pods' cores)."""

    def __init__(self, action_dim: int, call_s: float, chunk: int = 1) -> None:
        self.action_dim = action_dim
        self.call_s = call_s
        self.chunk = chunk

    def __call__(self, obs: dict[str, Any], instructions: list[str], task_ids: list[str]) -> torch.Tensor:
        if self.call_s > 0:
            time.sleep(self.call_s)
        if self.chunk == 1:
            return torch.zeros((len(task_ids), self.action_dim))
        return torch.zeros((len(task_ids), self.chunk, self.action_dim))


def mixed_horizons(n: int, horizon: int, seed: int) -> list[int]:
    """``n`` horizons spread evenly over [SHORTEST, 1] x ``horizon``, in a seeded random order."""
    fractions = np.linspace(SHORTEST, 1.0, n)
    np.random.default_rng(seed).shuffle(fractions)
    return [max(1, round(horizon * f)) for f in fractions]


def call_split(stats: list[RolloutStats], pods: dict[str, float]) -> dict[str, float]:
    """Where one contender's pod calls went, in ms (see the module's doc): the client's view from
    ``stats`` (the runs of one measurement) and the pods' counters ``pods`` over the same runs."""
    in_flight, turnaround = [], []
    for run in stats:
        last_end: dict[str, float] = {}
        for _stage, pod, begin, end, _resets, _steps in sorted(run.pod_calls, key=lambda call: call[2]):
            in_flight.append(end - begin)
            if pod in last_end:
                turnaround.append(begin - last_end[pod])
            last_end[pod] = end
    calls = max(pods["vecsim_pod_step_seconds_count"], 1.0)
    return {
        "in_flight": round(1000 * statistics.median(in_flight), 2) if in_flight else 0.0,
        "turnaround": round(1000 * statistics.median(turnaround), 2) if turnaround else 0.0,
        "pod_step": round(1000 * pods["vecsim_pod_step_seconds_sum"] / calls, 2),
        "physics": round(1000 * pods["vecsim_pod_physics_seconds_total"] / calls, 2),
        "render": round(1000 * pods["vecsim_pod_render_seconds_total"] / calls, 2),
    }


def settings(args: argparse.Namespace) -> dict[str, Any]:
    """The mode's sizes, with the flags given on the command line taking precedence."""
    if args.quick:
        mode = {
            "task": "gym/HalfCheetah-v5",
            "pods": 2,
            "envs_per_pod": 2,
            "size": 8,
            "horizon": 12,
            "waves": 3,
            "rounds": 2,
        }
    elif args.gpu:
        mode = {
            "task": "libero_10/0",
            "pods": 12,
            "envs_per_pod": 1,
            "size": 128,
            "horizon": 100,
            "waves": 6,
            "rounds": 2,
        }
    else:
        mode = {"task": "tiny/lift", "pods": 2, "envs_per_pod": 4, "size": 32, "horizon": 40, "waves": 4, "rounds": 3}
    return with_flags({**mode, "chunk": 1}, args)  # one action a call in every mode unless --chunk says


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--quick", action="store_true", help="tiny sizes, for the smoke test")
    group.add_argument("--gpu", action="store_true", help="the GPU node: LIBERO, pods pinned one per core (NVIDIA GL)")
    parser.add_argument("--task", help="the task every pod serves")
    parser.add_argument("--pods", type=int, help="standalone pods, all in one stage")
    parser.add_argument("--envs-per-pod", type=int)
    parser.add_argument("--size", type=int, help="camera height and width")
    parser.add_argument("--horizon", type=int, help="the longest episode, in actions")
    parser.add_argument("--waves", type=int, help="trajectories per env: N = waves x envs")
    parser.add_argument("--rounds", type=int, help="interleaved rounds")
    parser.add_argument(
        "--chunk",
        type=int,
        help="actions per env and policy call (K; default 1): fewer calls, "
        "so less of the trainer's per-call work, for the same actions",
    )
    parser.add_argument("--policy-ms", type=float, default=0.0, help="how long each policy call takes (a sleep)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--wait-quiet-s", type=float, default=0.0, help="wait up to this long for load < 1.5")
    args = parser.parse_args()
    setup_logging()
    os.environ.setdefault("MUJOCO_GL", "egl")
    mode = settings(args)
    if mode["chunk"] < 1:
        parser.error(f"--chunk must be at least 1, got {mode['chunk']}")
    load_before = wait_for_quiet(timeout_s=args.wait_quiet_s)
    task, pods, per_pod = mode["task"], mode["pods"], mode["envs_per_pod"]
    camera = CameraConfig(height=mode["size"], width=mode["size"])
    assignments = [
        Assignment(
            generation=0,
            job_id="bench-refill",
            pod=f"sim-{i}",
            stage_id=0,
            tasks=(TaskBlock(task_id=task, env_start=0, num_envs=per_pod),),
            camera=camera,
            render="lean",
            envs_per_worker=1,
            max_episode_steps=10 * mode["horizon"],
        )
        for i in range(pods)
    ]
    cores = sorted(os.sched_getaffinity(0))
    # On the GPU node each pod owns a core, the trainer the ones left; on a small box none is pinned.
    pins = [str(c) for c in cores[-pods:]] if args.gpu and len(cores) > pods else None
    envs = pods * per_pod
    n = mode["waves"] * envs
    requests = [(task, i % 50) for i in range(n)]
    horizons = mixed_horizons(n, mode["horizon"], args.seed)
    runs: dict[str, list[RolloutStats]] = {"refill": [], "batch": []}
    with contextlib.ExitStack() as stack:
        running = stack.enter_context(standalone_pods(assignments, cores=pins, ready_timeout_s=READY_TIMEOUT_S))
        client = stack.enter_context(StageClient.from_pods([pod.url for pod in running], timeout_s=120))
        policy = ScriptedPolicy(int(np.prod(client.action_space.shape)), args.policy_ms / 1000, mode["chunk"])
        loop = EnvLoop(client, policy, horizon=mode["horizon"], keep_obs=())

        # The trainer's CPU seconds per wall second, all its threads: near 1 (or above), the
        # trainer and not the pods bounds the rollout, and refill can gain little.
        busy: dict[str, list[float]] = {"refill": [], "batch": []}
        splits: dict[str, list[dict[str, float]]] = {"refill": [], "batch": []}

        # The pods' counters are read around each contender, outside its clocks.
        def refill() -> float:
            with counted(client) as counters:
                cpu = time.process_time()
                stats = loop.run(requests, horizons=horizons).stats
                cpu = time.process_time() - cpu
            busy["refill"].append(cpu / stats.wall_s)
            splits["refill"].append(call_split([stats], counters["pods"]))
            runs["refill"].append(stats)
            return stats.env_steps / stats.wall_s

        def batch() -> float:
            waves = []
            with counted(client) as counters:
                started, cpu, steps = time.perf_counter(), time.process_time(), 0
                for begin in range(0, n, envs):
                    stats = loop.run(requests[begin : begin + envs], horizons=horizons[begin : begin + envs]).stats
                    waves.append(stats)
                    steps += stats.env_steps
                wall, cpu = time.perf_counter() - started, time.process_time() - cpu
            busy["batch"].append(cpu / wall)
            splits["batch"].append(call_split(waves, counters["pods"]))
            runs["batch"].extend(waves)
            return steps / wall

        refill(), batch()  # warm-up: connections, first renders
        for stats in runs.values():
            stats.clear()
        for seconds in (*busy.values(), *splits.values()):
            seconds.clear()
        figures = interleaved({"refill": refill, "batch": batch}, mode["rounds"])
    ratio = paired_ratio(figures["refill"], figures["batch"])
    expected_steps = sum(horizons)
    steps = {
        "refill": statistics.median(s.env_steps for s in runs["refill"]),
        "batch": statistics.median(
            sum(s.env_steps for s in runs["batch"][r * mode["waves"] : (r + 1) * mode["waves"]])
            for r in range(mode["rounds"])
        ),
    }
    waves = [horizons[b : b + envs] for b in range(0, n, envs)]
    summary = {
        "baseline": "batch-at-once: the same trajectories in waves of one per env",
        "ratio": ratio["median"],
        "target": f"refill >= {TARGET}x batch-at-once",
        "met": ratio["median"] >= TARGET,
        "quick": args.quick,
        "load_avg_before": round(load_before, 2),
        "setup": {
            **mode,
            "envs": envs,
            "trajectories": n,
            "policy": f"scripted zeros, {mode['chunk']} action(s) per env, {args.policy_ms:g} ms a call",
            "pinned": pins is not None,
            "horizons_min_mean_max": [min(horizons), round(statistics.mean(horizons), 1), max(horizons)],
            "ideal_ratio": round(sum(max(w) for w in waves) * envs / expected_steps, 3),
            "env_steps_per_run": expected_steps,
        },
        "env_steps_per_s": {name: rate_spread(values) for name, values in figures.items()},
        "ratio_refill_vs_batch": ratio,
        "env_steps_median": steps,
        "trainer_cpu_per_wall_s": {name: rate_spread(values) for name, values in busy.items()},
        "call_split_ms": {
            name: {key: round(statistics.median(split[key] for split in rounds), 2) for key in rounds[0]}
            for name, rounds in splits.items()
        },
    }
    details = {
        "per_round": figures,
        "horizons": horizons,
        "call_split_ms_by_round": splits,
        "stats": {
            name: [{k: v for k, v in s.__dict__.items() if k not in ("timeline", "pod_calls")} for s in stats]
            for name, stats in runs.items()
        },
    }
    write_result("bench_refill", summary, details)


if __name__ == "__main__":
    main()
