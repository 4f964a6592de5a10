"""Benchmark 5, scaling: env-steps/s against the number of pods, envs per pod fixed.

Pods are real ``vecsim pod`` processes, pod ``i`` pinned to core ``i`` (``taskset``, as a CPU
limit of one core would confine it in Kubernetes; its workers inherit the pin, and
``envs_per_worker: auto`` sizes them for that one core). One ``HTTPVectorEnv`` steps the first P
pods as one stage, all pods of a call concurrently, for P = 1, 2, 4, ... up to the cores (2 on
the development machine). All pods are built first; then the pod counts take turns, the order
rotating each round. Linear scaling is P times the one-pod figure of the same round.

Scene sets: ``robot`` (tiny/lift x 4 per pod, two 32x32 cameras: simulation-bound) and ``cheap``
(HalfCheetah-v5 x 16 per pod, no camera: the client's per-call cost shows). The trainer (this
process) is not pinned: on a machine with as many cores as pods it shares them with the pods.
``--quick`` (the smoke test) runs the cheap set only, 2 envs per pod.

    python bench/bench_scaling.py [--quick] [--rounds 5] [--max-pods <cores>]

Prints ``RESULT {json}`` and writes out/bench/bench_scaling.json and docs/img/bench_scaling.png.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
from typing import Any

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
from lib.records import img_dir, write_result

from vecsim.client import HTTPVectorEnv
from vecsim.config import AUTO_ENVS_PER_WORKER, Assignment, CameraConfig, TaskBlock

log = logging.getLogger("bench.scaling")

TARGET = 0.8  # of linear, while pods <= cores


def pod_counts(max_pods: int) -> list[int]:
    """1, 2, 4, ... up to ``max_pods``, and ``max_pods`` itself."""
    counts, n = [], 1
    while n < max_pods:
        counts.append(n)
        n *= 2
    return [*counts, max_pods]


def measure(
    task_id: str, per_pod: int, camera: CameraConfig, counts: list[int], steps: int, rounds: int
) -> dict[str, Any]:
    """Start max(counts) pinned pods; step the first P of them for each P, in interleaved rounds."""
    cores = sorted(os.sched_getaffinity(0))
    assignments = [
        Assignment(
            generation=0,
            job_id="bench-scaling",
            pod=f"sim-{i}",
            stage_id=0,
            tasks=(TaskBlock(task_id=task_id, env_start=0, num_envs=per_pod),),
            camera=camera,
            render="lean",
            envs_per_worker=AUTO_ENVS_PER_WORKER,
            max_episode_steps=1000,
        )
        for i in range(max(counts))
    ]
    pins = [str(cores[i % len(cores)]) for i in range(len(assignments))]
    log.info("%s x %d per pod, pods %s pinned to cores %s", task_id, per_pod, counts, pins)
    with contextlib.ExitStack() as stack:
        pods = stack.enter_context(standalone_pods(assignments, cores=pins, ready_timeout_s=READY_TIMEOUT_S))
        envs = {p: HTTPVectorEnv(pod_urls=[pod.url for pod in pods[:p]]) for p in counts}
        for env in envs.values():
            stack.callback(env.close)
        contenders = {str(p): stepper(env, steps, seed=p) for p, env in envs.items()}
        for run in contenders.values():
            run()  # warm-up
        figures = interleaved(contenders, rounds)
    one = figures["1"]
    efficiency = {
        p: paired_ratio(values, [p * x for x in one]) for p, values in ((int(k), v) for k, v in figures.items())
    }
    return {
        "task_id": task_id,
        "envs_per_pod": per_pod,
        "camera": camera.model_dump(mode="json"),
        "steps_per_round": steps,
        "pinned_cores": pins,
        "env_steps_per_s": {p: rate_spread(v) for p, v in figures.items()},
        "fraction_of_linear": efficiency,
        "per_round": figures,
    }


def plot(results: dict[str, dict[str, Any]], path: Any) -> None:
    """Env-steps/s against pods, with the linear ideal, one panel per scene set."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(results), figsize=(5 * len(results), 3.8), squeeze=False)
    for ax, (name, result) in zip(axes[0], results.items()):
        counts = sorted(int(p) for p in result["env_steps_per_s"])
        measured = [result["env_steps_per_s"][str(p)]["median"] for p in counts]
        low = [result["env_steps_per_s"][str(p)]["min"] for p in counts]
        high = [result["env_steps_per_s"][str(p)]["max"] for p in counts]
        ax.plot(counts, [measured[0] * p for p in counts], "--", color="grey", label="linear")
        ax.plot(counts, [TARGET * measured[0] * p for p in counts], ":", color="grey", label=f"{TARGET} x linear")
        ax.errorbar(
            counts,
            measured,
            yerr=[[m - lo for m, lo in zip(measured, low)], [hi - m for m, hi in zip(measured, high)]],
            marker="o",
            capsize=3,
            label="measured (median, min-max)",
        )
        ax.set_xticks(counts)
        ax.set_xlabel("pods (one core each)")
        ax.set_ylabel("env-steps/s")
        ax.set_title(f"{name}: {result['task_id']} x {result['envs_per_pod']} per pod")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="tiny sizes, for the smoke test")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--max-pods", type=int, default=len(os.sched_getaffinity(0)), help="default: the cores")
    parser.add_argument("--wait-quiet-s", type=float, default=0.0, help="wait up to this long for load < 1.5")
    args = parser.parse_args()
    setup_logging()
    load_before = wait_for_quiet(timeout_s=args.wait_quiet_s)
    counts = pod_counts(max(1, args.max_pods))
    results: dict[str, dict[str, Any]] = {}
    if args.quick:  # the robot set runs the same code; the smoke test keeps to cheap scenes
        results["cheap"] = measure("gym/HalfCheetah-v5", 2, CameraConfig(names=()), counts, steps=10, rounds=2)
    else:
        results["robot"] = measure("tiny/lift", 4, CameraConfig(height=32, width=32), counts, 24, args.rounds)
        results["cheap"] = measure("gym/HalfCheetah-v5", 16, CameraConfig(names=()), counts, 100, args.rounds)
    fractions = {name: result["fraction_of_linear"][max(counts)]["median"] for name, result in results.items()}
    path = img_dir() / "bench_scaling.png"
    summary = {
        "baseline": "one pod (linear: pods x one pod's figure in the same round)",
        "pods": max(counts),
        "ratio": fractions.get("robot", fractions["cheap"]),
        "ratio_cheap": fractions["cheap"],
        "target": f">= {TARGET} of linear while pods <= cores",
        "met": all(f >= TARGET for f in fractions.values()),
        "quick": args.quick,
        "load_avg_before": round(load_before, 2),
        "plot": None if args.quick else str(path.relative_to(img_dir().parent.parent)),
        **{name: {k: v for k, v in result.items() if k != "per_round"} for name, result in results.items()},
    }
    write_result("bench_scaling", summary, results)
    if not args.quick:  # after the record: a machine without matplotlib still keeps the figures
        plot(results, path)


if __name__ == "__main__":
    main()
