"""Benchmark 4, pipelining: EnvLoop env-steps/s with 1, 2 and 4 stages.

What it measures, and how it keeps that honest on a small CPU machine: pipelining overlaps the
policy's forward pass on one stage with the simulation of the others, which pays only when the
two do not fight for the same processor. On a training machine the policy runs on a GPU and the
sims on CPU cores; here the trainer (this process: EnvLoop, the policy with torch on one thread,
the client's event loop) is pinned to core 0 and every pod, workers included, to core 1
(``taskset``), so policy and simulation each own a core, as they would own a GPU and a CPU.

The same envs serve all three: four standalone pods of ``--envs-per-pod`` tiny/lift envs each
(two 32x32 cameras, lean preset: rendering dominates a step). A "stage" is a group of pods the
client steps together; the client's routing table groups the four pods into 1, 2 or 4 stages
(pods never look at their stage, only the client does). The policy is a real torch CNN over
both cameras whose depth is calibrated at start-up so that its forward pass on one stage of the
2-stage split takes about as long as that stage's simulation; the same model serves 1 and 4
stages. Ideal: 2 stages = 2x of 1 stage (policy and simulation fully overlapped); 4 stages
cannot beat that and pay more per-call overhead.

Each round runs one rollout (``EnvLoop.run``: reset, then ``--horizon`` steps of every
trajectory) per stage count, the order rotating each round. The reset and the pipeline's fill
and drain are part of every rollout: with a horizon of 48 the ideal 2-stage speed-up is ~1.92x
(1.85x at 24), not 2x.

    python bench/bench_pipeline.py [--quick] [--rounds 3] [--horizon 48]

Prints ``RESULT {json}`` and writes out/bench/bench_pipeline.json and docs/img/bench_pipeline.png.
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
from lib.pods import (
    READY_TIMEOUT_S,
    interleaved,
    paired_ratio,
    rate_spread,
    setup_logging,
    standalone_pods,
    wait_for_quiet,
)
from lib.records import img_dir, write_result
from gymnasium import spaces
from torch import nn

from vecsim.client import StageClient
from vecsim.config import Assignment, CameraConfig, RoutedPod, RoutedStage, RoutingTable, TaskBlock
from vecsim.rollout import EnvLoop

log = logging.getLogger("bench.pipeline")

TARGET = 1.8  # 2 stages over 1 stage
PODS = 4


class CalibratedCNN(nn.Module):
    """A CNN policy over every camera and proprio whose cost grows with ``depth`` (3x3 convs)."""

    def __init__(self, observation_space: spaces.Dict, action_space: spaces.Box, depth: int, width: int = 32) -> None:
        super().__init__()
        self.cameras = list(observation_space["images"].spaces)
        layers: list[nn.Module] = [nn.Conv2d(3, width, 3, padding=1), nn.ReLU()]
        for _ in range(depth):
            layers += [nn.Conv2d(width, width, 3, padding=1), nn.ReLU()]
        self.encoder = nn.Sequential(*layers, nn.AdaptiveAvgPool2d(1), nn.Flatten())
        proprio = int(np.prod(observation_space["proprio"].shape))
        actions = int(np.prod(action_space.shape))
        self.head = nn.Sequential(nn.Linear(width * len(self.cameras) + proprio, 64), nn.ReLU(), nn.Linear(64, actions))

    def forward(self, obs: dict[str, Any], instructions: list[str], task_ids: list[str]) -> torch.Tensor:
        """Return actions in [-1, 1], ``[n, action_dim]``."""
        features = [self.encoder(obs["images"][c].float().permute(0, 3, 1, 2) / 255.0) for c in self.cameras]
        features.append(obs["proprio"].float())
        return torch.tanh(self.head(torch.cat(features, dim=1)))


def routing(pods: list[Any], task: str, stages: int, per_pod: int) -> RoutingTable:
    """The client's view: the pods grouped, in order, into ``stages`` stages."""
    per_stage = len(pods) // stages
    grouped = []
    for s in range(stages):
        routed = [
            RoutedPod(
                pod=f"sim-{i}",
                url=pods[i].url,
                num_envs=per_pod,
                tasks=(TaskBlock(task_id=task, env_start=0, num_envs=per_pod),),
            )
            for i in range(s * per_stage, (s + 1) * per_stage)
        ]
        grouped.append(RoutedStage(stage_id=s, pods=tuple(routed)))
    return RoutingTable(generation=0, job_id="bench-pipeline", ready=True, stages=tuple(grouped))


def stage_sim_s(client: StageClient, task: str, envs: int, calls: int) -> float:
    """Median time of one step call of stage 0 (of a 2-stage client), zero actions."""
    client.reset_trajectories([(task, i) for i in range(envs)])
    client.reset_stage(0).result()
    client.reset_stage(1).result()
    keys = client.stage_traj_keys(0)
    zeros = np.zeros(client.action_space.shape, np.float32)
    times = []
    for _ in range(calls):
        batch = client.step_stage(0, {key: zeros for key in keys}).result()
        times.append(batch.finished_at - batch.submitted_at)
    return statistics.median(times)


def forward_s(policy: nn.Module, client: StageClient, batch: int, calls: int) -> float:
    """Median time of one forward pass on ``batch`` observations (the client's spaces)."""
    space = client.observation_space
    obs = {
        "images": {c: torch.zeros((batch, *s.shape), dtype=torch.uint8) for c, s in space["images"].spaces.items()},
        "proprio": torch.zeros((batch, *space["proprio"].shape)),
    }
    times = []
    with torch.no_grad():
        for _ in range(calls):
            started = time.perf_counter()
            policy(obs, [""] * batch, [""] * batch)
            times.append(time.perf_counter() - started)
    return statistics.median(times)


def calibrate(client: StageClient, task: str, envs: int, calls: int) -> tuple[nn.Module, dict[str, float]]:
    """A CalibratedCNN whose forward on one stage of the 2-stage split ~ that stage's simulation.

    A first depth comes from the cost of 0 and 4 layers; then the depth is scaled by target /
    achieved until within 10% (at most 4 tries), since one noisy timing can be far off.
    """
    target = stage_sim_s(client, task, envs, calls)
    space, action = client.observation_space, client.action_space
    batch = envs // 2
    base = forward_s(CalibratedCNN(space, action, depth=0), client, batch, calls)
    per_layer = max((forward_s(CalibratedCNN(space, action, depth=4), client, batch, calls) - base) / 4, 1e-4)
    depth = max(0, round((target - base) / per_layer))
    for attempt in range(4):
        policy = CalibratedCNN(space, action, depth=depth)
        achieved = forward_s(policy, client, batch, calls)
        if abs(achieved - target) <= 0.1 * target or attempt == 3:
            break
        depth = max(1, round(depth * target / achieved))
    log.info("stage simulation %.1f ms; policy depth %d forwards in %.1f ms", 1000 * target, depth, 1000 * achieved)
    return policy, {"stage_sim_ms": round(1000 * target, 1), "depth": depth, "forward_ms": round(1000 * achieved, 1)}


def _per_call_ms(stats: list[Any]) -> dict[str, float]:
    """Median milliseconds of one policy call and of one stage's simulation call, over rollouts."""
    calls: dict[str, list[float]] = {"policy": [], "sim": []}
    for rollout in stats:
        for kind, _stage, begin, end in rollout.timeline:
            calls[kind].append(end - begin)
    return {kind: round(1000 * statistics.median(times), 1) for kind, times in calls.items() if times}


def plot(figures: dict[str, list[float]], bound: float, path: Any) -> None:
    """Env-steps/s per stage count (median and min-max of the rounds), against 1.8x and 2x one
    stage and against ``bound``: the rate at which the simulation core is never idle."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    stages = sorted(int(s) for s in figures)
    medians = [statistics.median(figures[str(s)]) for s in stages]
    low = [m - min(figures[str(s)]) for s, m in zip(stages, medians)]
    high = [max(figures[str(s)]) - m for s, m in zip(stages, medians)]
    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    ax.bar(range(len(stages)), medians, yerr=[low, high], capsize=4, color="#4c72b0", label="measured")
    ax.set_xticks(range(len(stages)), [str(s) for s in stages])
    ax.axhline(bound, ls="-.", color="black", label="bound: simulation core always busy")
    ax.axhline(2 * medians[0], ls="--", color="grey", label="2x one stage")
    ax.axhline(TARGET * medians[0], ls=":", color="grey", label=f"target: {TARGET}x one stage")
    ax.set_ylim(0, 1.15 * max(bound, *medians))
    ax.set_xlabel("pipeline stages")
    ax.set_ylabel("env-steps/s")
    ax.set_title("EnvLoop: policy on core 0, pods on core 1")
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="tiny sizes, for the smoke test")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--horizon", type=int, default=48)
    parser.add_argument("--envs-per-pod", type=int, default=2)
    parser.add_argument("--wait-quiet-s", type=float, default=0.0, help="wait up to this long for load < 1.5")
    args = parser.parse_args()
    setup_logging()
    load_before = wait_for_quiet(timeout_s=args.wait_quiet_s)
    cores = sorted(os.sched_getaffinity(0))
    trainer_core, sim_core = cores[0], cores[-1]
    # Pinned before any thread starts, so the client's loop thread and torch inherit it.
    os.sched_setaffinity(0, {trainer_core})
    torch.set_num_threads(1)
    if args.quick:  # a gym scene with its render camera: the same code, no robosuite to load
        task, per_pod, camera, horizon, rounds, calls = (
            "gym/HalfCheetah-v5",
            1,
            CameraConfig(height=8, width=8),
            3,
            2,
            2,
        )
    else:
        task, per_pod, camera = "tiny/lift", args.envs_per_pod, CameraConfig(height=32, width=32)
        horizon, rounds, calls = args.horizon, args.rounds, 5
    envs = PODS * per_pod
    assignments = [
        Assignment(
            generation=0,
            job_id="bench-pipeline",
            pod=f"sim-{i}",
            stage_id=0,
            tasks=(TaskBlock(task_id=task, env_start=0, num_envs=per_pod),),
            camera=camera,
            render="lean",
            envs_per_worker=1,
            max_episode_steps=1000,
        )
        for i in range(PODS)
    ]
    requests = [(task, i % 50) for i in range(envs)]
    with contextlib.ExitStack() as stack:
        pods = stack.enter_context(
            standalone_pods(assignments, cores=[str(sim_core)] * PODS, ready_timeout_s=READY_TIMEOUT_S)
        )
        # Steps go on past episode ends: the calls are timed, not the episodes.
        clients = {s: StageClient(routing(pods, task, s, per_pod), ended_envs="step") for s in (1, 2, 4)}
        for client in clients.values():
            stack.callback(client.close)
        policy, calibration = calibrate(clients[2], task, envs, calls)
        results: dict[str, list[Any]] = {str(s): [] for s in clients}

        def rollout(stages: int) -> float:
            loop = EnvLoop(clients[stages], policy, horizon=horizon, keep_obs=())
            result = loop.run(requests)
            results[str(stages)].append(result.stats)
            return result.stats.env_steps_per_s

        for s in clients:
            rollout(s)  # warm-up
        for stats in results.values():
            stats.clear()
        figures = interleaved({str(s): (lambda s=s: rollout(s)) for s in clients}, rounds)
    speedup = {s: paired_ratio(figures[s], figures["1"]) for s in figures}
    # What no number of stages can beat: every env-step simulated with the simulation core never idle.
    bound = statistics.median(x.env_steps / x.simulation_s for stats in results.values() for x in stats)
    path = img_dir() / "bench_pipeline.png"
    if not args.quick:
        plot(figures, bound, path)
    overlap = {s: round(statistics.median(x.overlap_fraction for x in stats), 3) for s, stats in results.items()}
    per_call_ms = {s: _per_call_ms(stats) for s, stats in results.items()}
    summary = {
        "baseline": "the same EnvLoop, policy and pods as 1 stage",
        "ratio": speedup["2"]["median"],
        "ratio_4_stages": speedup["4"]["median"],
        "target": f"2 stages >= {TARGET}x of 1 stage",
        "met": speedup["2"]["median"] >= TARGET,
        "quick": args.quick,
        "load_avg_before": round(load_before, 2),
        "setup": {
            "task": task,
            "pods": PODS,
            "envs": envs,
            "camera": camera.model_dump(mode="json"),
            "horizon": horizon,
            "trainer_core": trainer_core,
            "sim_core": sim_core,
            "torch_threads": torch.get_num_threads(),
            **calibration,
        },
        "env_steps_per_s": {s: rate_spread(v) for s, v in figures.items()},
        "speedup_vs_1_stage": speedup,
        "overlap_fraction": overlap,
        "per_call_ms": per_call_ms,
        "simulation_bound_env_steps_per_s": round(bound, 2),
        "plot": None if args.quick else "docs/img/bench_pipeline.png",
    }
    # Every call's interval is in the rollouts' timelines; the record keeps their medians above.
    details = {
        "per_round": figures,
        "stats": {
            s: [{k: v for k, v in x.__dict__.items() if k != "timeline"} for x in stats] for s, stats in results.items()
        },
    }
    write_result("bench_pipeline", summary, details)


if __name__ == "__main__":
    main()
