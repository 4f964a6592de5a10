"""Action chunks at scale: env-steps/s of a node at K = 1, 4, 8, 16 actions per call, pipelining
at K = 8, and the physics-only rate of the same cores.

One job as ``bench_gpu_scale.py --only scaling`` builds it (its ``job_config``): ``--pods``
pods pinned one per core (physical cores first), every pod serving the same task mix in one
worker (default LIBERO-10's ten tasks, one env each, two cameras at ``--size``, ``lean``), the
trainer in this process on the cores left over. Contenders, in interleaved rounds, every one
applying ``--actions`` actions per env (so every K does the same physics):

- ``service/K=k``: the service alone, all pods in one stage: reset every env, then calls sending
  a chunk of k scripted actions per env until each env applied ``--actions`` (or ended);
  env-steps/s = actions applied / the step calls' time.
- ``loop/K=k``: the pipelined EnvLoop, one stage, with bench_gpu_scale's graphed ResNet-18 policy
  acting in chunks (one forward pass per chunk: its action, then k-1 more along a small sine
  around it, as a chunk head would), horizon ``--actions``; env-steps/s over the whole run. With
  ``--waves W``, W trajectories per env: an env whose trajectory ends takes the next request of
  its task (refill), so a pod on a faster core serves more of them.
- ``loop_stages=2/K=8``: the same loop at K = 8 with the pods in two stages (halves), against
  ``loop/K=8`` (one stage): what pipelining adds with chunks.
- ``loop_slices=2/K=8``: the same with two stages in the ``slices`` layout (every pod holds half
  its envs on each stage): a pod has one stage's call queued while the policy works on the other's.

Before the job starts, ``--pods`` processes pinned to the pods' cores step the same task mix
without cameras, HTTP or pods (``lib.ceiling.physics_only``) for ``--physics-seconds``: the
physics-only rate of the node. Then as many processes on the same cores build the mix with the
pods' cameras and render preset and stay up beside the job (``lib.ceiling.CeilingProcesses``): in
every round, while the pods idle, they apply K actions per env and render every camera once, in
one batch of the same renderer as a pod's worker (EGL on the GPU node), for ``--physics-seconds``
per K: the ceiling, the node's simulation alone (issue 27); and again with every env reset after
``--actions`` actions, as a rollout of that horizon must (``K=k/reset_every_H``). Every contender
is reported as a fraction of both ceilings, paired by round (on a shared machine the bare
processes' own rate drifts by up to 30% in minutes), and of physics-only; ``per_env_step_ms`` puts
the pods' own physics and render time per env-step (their ``/metrics``) next to the bare
processes'. The ceiling's processes hold about as much memory as the pods' workers (LIBERO-10 on
12 cores: ~40 GiB each), which ``--max-memory-gib`` counts.

Targets: ``loop/K=8`` >= 1.5x ``loop/K=1`` (paired by round), the node at K = 8 >= 0.8 of the
physics-only rate (the chunks issue), and ``loop/K=8`` >= 0.9 of the ceiling at K = 8 (issue 27).

Commands::

    source .device/setup.sh && python bench/bench_chunks.py --gpu --copy-to "$OUT"   # the GPU machine
    python bench/bench_chunks.py --gpu --dry       # probe: 1 pod, K = 1 and 4, 4 actions; fails fast
    python bench/bench_chunks.py --cpu-small       # here: 2 pods of 2 tiny tasks, 32x32, K = 1 and 4
    python bench/bench_chunks.py --gpu --chunks 8 --actions 64 --waves 10 --physics-seconds 5   # issue 27's 0.9
    python bench/bench_chunks.py --quick           # smoke: 2 pods of a gym scene, 16x16, K = 1 and 8

Writes out/bench/bench_chunks[_cpu|_dry].json and prints one ``RESULT {json}`` line; ``--copy-to``
also copies it into a folder, with a failed job's logs. Rounds stop being added at ``--deadline``
seconds after the start, and the job's start-up and the physics-only run are bounded by it too.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import math
import os
import shutil
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from lib.jobs import (
    Plan,
    STAGE_LAYOUTS,
    camera,
    job_config,
    parse_stage_layouts,
    regroup,
    regroup_slices,
    requests_for,
    running_job,
    wait_for_job,
)
from lib.machine import MemoryWatch, cores_first, cpu_topology, gl_probe, gpu_name, split_cores
from lib.measure import Deadline, Measured, TimedStageClient, counted, interleave, loop_rollout, scripted_actions
from lib.policies import PIPELINE_K, ChunkedPolicy, GraphedPolicy, VisionPolicy, forward_ms, parameters_m, pod_multiples
from lib.stats import summarise
from lib.pods import paired_ratio, setup_logging
from lib.ceiling import CeilingProcesses, CeilingRound, ceiling_key, ceiling_over_rounds, physics_only
from lib.records import write_result
from gymnasium import spaces

from vecsim.client import StageClient
from vecsim.rollout import RolloutStats

log = logging.getLogger("bench.chunks")

CHUNK_TARGET = 1.5  # loop at K = 8 over K = 1
PHYSICS_TARGET = 0.8  # the node at K = 8 over the physics-only rate of the same cores
CEILING_TARGET = 0.9  # EnvLoop at K = 8 over the ceiling: the same cores with cameras once per K (issue 27)
# --quick: the sizes of --cpu-small's smoke run (flags given on the command line win).
QUICK = {
    "tasks": "gym/HalfCheetah-v5",
    "envs_per_task": 2,
    "size": 16,
    "actions": 8,
    "chunks": "1,8",
    "physics_seconds": 0.5,
}


@dataclasses.dataclass(frozen=True)
class Settings:
    """What the run measures beyond the job itself (``Plan``)."""

    chunks: tuple[int, ...]
    actions: int
    physics_seconds: float
    waves: int = 1  # trajectories per env in every EnvLoop rollout (refill)

    @property
    def headline_k(self) -> int:
        """The K of the targets' figures: ``PIPELINE_K`` where it is measured, else the largest."""
        return PIPELINE_K if PIPELINE_K in self.chunks else self.chunks[-1]


def scripted_chunk(space: spaces.Box, first: int, k: int, n: int) -> np.ndarray:
    """``[n, k, action_dim]``: bench_gpu_scale's open-loop actions of steps ``first .. first+k-1``."""
    return np.stack([scripted_actions(space, first + j, n) for j in range(k)], axis=1)


def service_chunks(client: StageClient, actions: int, k: int, timeout_s: float) -> Measured:
    """The service alone at chunks of ``k``: reset every env, then calls of a chunk per env
    (every stage's call sent at once, then all awaited) until each env applied ``actions``
    actions or ended. Env-steps/s = actions applied over the step calls' time.

    Raises:
        TimeoutError: a call took longer than ``timeout_s``.
    """
    routes = client.reset_trajectories(requests_for(client.routing))
    stages = [s for s in range(client.num_stages) if client.stage_traj_keys(s)]
    space = client.action_space
    timeline: list[tuple[str, int, float, float]] = []
    applied = 0
    with counted(client) as seen:
        started = time.perf_counter()
        for stage, batch in zip(stages, [c.result(timeout_s) for c in [client.reset_stage(s) for s in stages]]):
            timeline.append(("sim", stage, batch.submitted_at - started, batch.finished_at - started))
        stepping = time.perf_counter()
        live = {s: client.stage_traj_keys(s) for s in stages}
        for first in range(0, actions, k):
            size = min(k, actions - first)
            calls = {
                s: client.step_stage(s, dict(zip(keys, scripted_chunk(space, first, size, len(keys)))))
                for s, keys in live.items()
                if keys
            }
            for stage, call in calls.items():
                batch = call.result(timeout_s)
                timeline.append(("sim", stage, batch.submitted_at - started, batch.finished_at - started))
                applied += int(batch.num_steps.sum())
                ended = (batch.terminated | batch.truncated).any(axis=1)
                live[stage] = [key for key, end in zip(batch.traj_keys, ended) if not end]
        finished = time.perf_counter()
    stats = RolloutStats(
        num_trajectories=len(routes),
        env_steps=applied,
        wall_s=finished - started,
        env_steps_per_s=applied / max(finished - stepping, 1e-9),
        simulation_s=finished - started,
        timeline=sorted(timeline, key=lambda item: item[2]),
    )
    return Measured(stats, **seen)


def measure(
    plan: Plan, settings: Settings, job: Any, table: Any, deadline: Deadline, bare: CeilingProcesses
) -> dict[str, Any]:
    """Every contender (module docstring) and the ceiling (``bare``'s processes, run while the pods
    idle) in interleaved rounds."""
    names = [f"sim-{i}" for i in range(plan.pods)]
    one = TimedStageClient(regroup(table, names, 1), token=job.token, timeout_s=300)
    two = (
        TimedStageClient(regroup(table, names, 2), token=job.token, timeout_s=300)
        if plan.pods > 1 and "pods" in plan.stage_layouts
        else None
    )
    # Two stages as slices of every pod: each pod has the other stage's call queued while the
    # policy works on one, so it does not idle between its calls.
    sliced = (
        TimedStageClient(regroup_slices(table, names, 2), token=job.token, timeout_s=300)
        if "slices" in plan.stage_layouts
        else None
    )
    try:
        space, action = one.observation_space, one.action_space
        policy = VisionPolicy(space, action, device=plan.device, dtype=plan.torch_dtype)
        sizes = [one.routing.num_envs, *([s.num_envs for s in two.routing.stages] if two else [])]
        # Every multiple of a pod's envs, other batch sizes padded: none is captured in a round.
        graphed = GraphedPolicy(
            policy, space, plan.device, pod_multiples(plan.envs_per_pod, max(sizes), sizes), pad=True
        )
        chunked = {k: ChunkedPolicy(graphed, action, k) for k in settings.chunks}
        policy_info = {
            "name": "ResNet-18 per camera + proprio MLP + MLP head, one forward pass per chunk",
            "parameters_m": parameters_m(policy),
            "dtype": plan.dtype,
            "device": plan.device,
            "cuda_graphs": graphed.graphed,
            "forward_ms": {str(b): round(forward_ms(graphed, space, b, 5, plan.device), 2) for b in sorted(set(sizes))},
        }
        log.info("policy: %s", policy_info)
        warm = min(settings.chunks[-1], settings.actions)
        service_chunks(one, warm, settings.chunks[-1], 300)  # warm-up: connections, caches, kernels
        loop_rollout(one, chunked[settings.chunks[-1]], warm, plan.device)
        if two is not None and PIPELINE_K in chunked:
            loop_rollout(two, chunked[PIPELINE_K], warm, plan.device)
        if sliced is not None and PIPELINE_K in chunked:
            loop_rollout(sliced, chunked[PIPELINE_K], warm, plan.device)
        log.info("warm-up done, %.0f s left", deadline.left())
        contenders: dict[str, Callable[[], Any]] = {}  # each round's Measured; the ceiling's CeilingRound
        for k in settings.chunks:
            contenders[f"service/K={k}"] = lambda k=k: service_chunks(one, settings.actions, k, 300)
            contenders[f"loop/K={k}"] = lambda k=k: loop_rollout(
                one, chunked[k], settings.actions, plan.device, waves=settings.waves
            )
        if two is not None and PIPELINE_K in chunked:
            contenders[f"loop_stages=2/K={PIPELINE_K}"] = lambda: loop_rollout(
                two, chunked[PIPELINE_K], settings.actions, plan.device, waves=settings.waves
            )
        if sliced is not None and PIPELINE_K in chunked:
            contenders[f"loop_slices=2/K={PIPELINE_K}"] = lambda: loop_rollout(
                sliced, chunked[PIPELINE_K], settings.actions, plan.device, waves=settings.waves
            )
        contenders["ceiling"] = lambda: CeilingRound(bare.measure(), ceiling_key(settings.headline_k, 0))
        runs = interleave(contenders, plan.rounds, deadline, reserve_s=10)
    finally:
        for client in (one, two, sliced):
            if client is not None:
                client.close()
    ceilings: list[CeilingRound] = runs.pop("ceiling")
    rates = {name: [m.env_steps_per_s for m in measured] for name, measured in runs.items()}
    for key in ceilings[0].figures:
        rates[f"ceiling/{key}"] = [c.figures[key]["env_steps_per_s"] for c in ceilings]
    result: dict[str, Any] = {
        "policy": {**policy_info, "graphs": graphed.describe()},
        "ceiling": ceiling_over_rounds(ceilings, bare.describe()),
    }
    for kind in ("service", "loop"):
        section = {}
        for k in settings.chunks:
            name = f"{kind}/K={k}"
            section[f"K={k}"] = {
                **summarise(runs[name]),
                "over_K=1": paired_ratio(rates[name], rates[f"{kind}/K=1"]) if 1 in settings.chunks else None,
            }
        result[kind] = section
    pipelined = f"loop_stages=2/K={PIPELINE_K}"
    if pipelined in runs:
        result["pipeline"] = {
            "stages=2": summarise(runs[pipelined]),
            "speedup_2_vs_1": paired_ratio(rates[pipelined], rates[f"loop/K={PIPELINE_K}"]),
        }
    sliced_name = f"loop_slices=2/K={PIPELINE_K}"
    if sliced_name in runs:
        result["slices"] = {
            "stages=2": summarise(runs[sliced_name]),
            "speedup_2_vs_1": paired_ratio(rates[sliced_name], rates[f"loop/K={PIPELINE_K}"]),
        }
    result["per_round"] = {name: [round(x, 2) for x in values] for name, values in rates.items()}
    return result


def make_plan(args: argparse.Namespace) -> tuple[Plan, Settings]:
    """``--gpu`` (LIBERO-10, 256x256, 12 pods) or ``--cpu-small`` defaults; ``--dry`` shrinks."""
    from vecsim.engine.tasks import suite_tasks

    gpu, dry = args.gpu, args.dry
    if args.tasks:
        tasks = tuple(t for t in args.tasks.split(",") if t)
    elif gpu:
        tasks = tuple(t.task_id for t in suite_tasks("libero_10"))
    else:
        tasks = ("tiny/lift", "tiny/door")  # robot scenes with both cameras that build in seconds on a CPU
    chunks = (1, 4) if dry or not gpu else (1, 4, 8, 16)
    if args.chunks:
        chunks = tuple(sorted({int(k) for k in args.chunks.split(",")}))
    actions = args.actions or (4 if dry else 32 if gpu else 8)
    cuda = torch.cuda.is_available()
    pods = 1 if dry else args.pods or (12 if gpu else 2)
    plan = Plan(
        mode="scaling",
        tasks=tasks,
        size=args.size or (256 if gpu else 32),
        envs_per_task=args.envs_per_task or 1,
        pods=pods,
        pod_counts=(pods,),
        pipeline_cores=1,
        horizon=actions,
        service_steps=actions,
        rounds=1 if dry else args.rounds or (2 if gpu else 1),
        device="cuda" if cuda else "cpu",
        dtype="bfloat16" if cuda else "float32",
        vit_width=0,
        vit_max_depth=0,
        max_memory_gib=args.max_memory_gib,
        deadline_s=args.deadline,
        render_preset=args.render_preset,
        stage_layouts=parse_stage_layouts(args.stage_layout),
    )
    physics_seconds = args.physics_seconds or (1.0 if dry else 10.0 if gpu else 2.0)
    return plan, Settings(chunks=chunks, actions=actions, physics_seconds=physics_seconds, waves=args.waves)


def run(args: argparse.Namespace) -> int:
    deadline = Deadline(args.deadline)
    plan, settings = make_plan(args)
    tag = "_dry" if args.dry else "" if args.gpu else "_cpu"
    gl = gl_probe()
    log.info("GL: %s; GPU: %s; torch %s on %s", gl, gpu_name(), torch.__version__, plan.device)
    if args.gpu and "NVIDIA" not in gl.get("renderer", "").upper():
        log.error("GL_RENDERER is %r, not NVIDIA's: not measuring", gl.get("renderer", gl))
        return 2
    if args.gpu and plan.device != "cuda":
        log.error("torch sees no CUDA device: not measuring")
        return 2
    topology = cpu_topology()
    pins, trainer = split_cores(cores_first(topology), plan.pods)
    pod_pins = [pins[i % len(pins)] for i in range(plan.pods)]

    log.info("physics only: %d processes on %s, %.0f s", plan.pods, pod_pins, settings.physics_seconds)
    physics = physics_only(pod_pins, plan.tasks, settings.physics_seconds, min(deadline.left(), 300.0))
    log.info("physics only: %.1f env-steps/s", physics["env_steps_per_s"])
    log.info(
        "ceiling: %d processes, cameras %s once per K, %g s per K, in every round",
        plan.pods,
        camera(plan),
        settings.physics_seconds,
    )

    os.sched_setaffinity(0, set(trainer))
    torch.set_num_threads(len(trainer))
    torch.backends.cudnn.benchmark = True
    config = job_config(plan, pins, "chunks", plan.pods)
    started = time.monotonic()
    with (
        MemoryWatch(plan.max_memory_gib) as memory,
        CeilingProcesses(
            pod_pins, plan, settings.chunks, settings.physics_seconds, settings.actions, min(deadline.left(), 300.0)
        ) as bare,
        running_job(config, args.copy_to) as job,
    ):
        table = wait_for_job(job, max(60.0, min(600.0, deadline.left())))
        build_s = time.monotonic() - started
        log.info(
            "%d pods and the ceiling's processes ready in %.0f s, %.0f s left", plan.pods, build_s, deadline.left()
        )
        measured = measure(plan, settings, job, table, deadline, bare)

    node = physics["env_steps_per_s"]
    top = measured.pop("ceiling")
    per_round = measured["per_round"]
    rows = [(f"{kind}/K={k}", k, measured[kind][f"K={k}"]) for kind in ("service", "loop") for k in settings.chunks]
    rows += [
        (name, PIPELINE_K, measured[kind]["stages=2"])
        for kind, name in (("pipeline", f"loop_stages=2/K={PIPELINE_K}"), ("slices", f"loop_slices=2/K={PIPELINE_K}"))
        if kind in measured
    ]
    for name, k, row in rows:
        row["fraction_of_physics_only"] = round(row["env_steps_per_s"]["median"] / node, 3) if node else None
        # Paired by round: each round's rate over the ceiling of the same round; the second, the
        # ceiling with a reset every --actions actions, as a rollout of that horizon has.
        for field, key in (
            ("fraction_of_ceiling", ceiling_key(k, 0)),
            ("fraction_of_ceiling_with_resets", ceiling_key(k, settings.actions)),
        ):
            paired = paired_ratio(per_round[name], per_round[f"ceiling/{key}"])
            row[field] = paired["median"]
            row[f"{field}_by_round"] = paired
    at = f"K={settings.headline_k}"
    # The best EnvLoop at K=8, whichever stage layout it used: the user picks the layout.
    loops = {
        "loop/1 stage": measured["loop"].get(at, {}),
        "loop/2 stages (pods)": measured.get("pipeline", {}).get("stages=2", {}),
        "loop/2 stages (slices)": measured.get("slices", {}).get("stages=2", {}),
    }
    best = max(
        (name for name in loops if loops[name].get("fraction_of_ceiling")),
        key=lambda name: loops[name]["fraction_of_ceiling"],
        default=None,
    )
    chunk_gain = measured["loop"].get(at, {}).get("over_K=1") or {}
    node_fraction = measured["loop"].get(at, {}).get("fraction_of_physics_only")
    # Where a pod's step time goes beyond the bare processes' (same cores, same task mix).
    per_env_step_ms = {
        "bare_physics_only": physics["ms_per_env_step"],
        **{
            f"bare_ceiling/{k}": {key: top[k][key] for key in ("physics_ms_per_env_step", "render_ms_per_env_step")}
            for k in top
            if k.startswith("K=")
        },
        **{
            f"pod/{kind}/{k}": {
                key: row["time_split_ms"][key] for key in ("physics_ms_per_env_step", "render_ms_per_env_step")
            }
            for kind in ("service", "loop")
            for k, row in measured[kind].items()
        },
    }
    print_table(measured, physics, top)
    summary: dict[str, Any] = {
        "quick": not args.gpu,
        "dry": args.dry,
        "baseline": "K = 1 of the same job, same round (paired); and the physics-only rate of the pods' cores",
        "ratio": chunk_gain.get("median"),
        "ratio_of_physics_only": node_fraction,
        "ratio_of_ceiling": measured["loop"].get(at, {}).get("fraction_of_ceiling"),
        "best_loop_of_ceiling": {
            "contender": best,
            "of_ceiling": loops[best]["fraction_of_ceiling"],
            "of_ceiling_with_resets": loops[best]["fraction_of_ceiling_with_resets"],
        }
        if best
        else None,
        "target": f"loop K={PIPELINE_K} >= {CHUNK_TARGET}x K=1, >= {PHYSICS_TARGET} of physics-only and "
        f">= {CEILING_TARGET} of the ceiling",
        "met": {
            "chunks": None if chunk_gain.get("median") is None else chunk_gain["median"] >= CHUNK_TARGET,
            "physics_only": node_fraction is not None and node_fraction >= PHYSICS_TARGET,
            "ceiling": bool(best) and loops[best]["fraction_of_ceiling"] >= CEILING_TARGET,
        },
        "setup": {
            **dataclasses.asdict(plan),
            **dataclasses.asdict(settings),
            "camera": camera(plan),
            "envs_per_pod": plan.envs_per_pod,
            "pods_pinned_to": pod_pins,
            "trainer_cores": trainer,
            "job_build_s": round(build_s, 1),
            "memory_used_gib_peak": memory.peak_gib,
        },
        "physics_only": physics,
        "ceiling": top,
        "per_env_step_ms": per_env_step_ms,
        "topology": topology,
        "gl": gl,
        **measured,
    }
    details = {"per_round": summary.pop("per_round")}
    path = write_result(f"bench_chunks{tag}", summary, details)
    if args.copy_to:
        args.copy_to.mkdir(parents=True, exist_ok=True)
        shutil.copy(path, args.copy_to / path.name)
    return 0


def print_table(measured: dict[str, Any], physics: dict[str, Any], top: dict[str, Any]) -> None:
    """The figures as a table on stdout: each contender's env-steps/s, of physics-only and of the
    ceiling (cameras once per K) at its K."""
    rows = [("physics only", "", physics["env_steps_per_s"], "1.0", "", "")]
    for k in (k for k in top if k.startswith("K=")):
        at, _, resets = k.partition("/")
        name = f"ceiling, {resets.replace('_', ' ')}" if resets else "ceiling (cameras once per K)"
        rows.append((name, at, top[k]["env_steps_per_s"], "", "" if resets else "1.0", "1.0" if resets else ""))
    for kind, name in (
        ("service", "service alone"),
        ("loop", "EnvLoop"),
        ("pipeline", "EnvLoop, 2 stages (pods)"),
        ("slices", "EnvLoop, 2 stages (slices)"),
    ):
        if kind not in measured:
            continue
        section = {f"K={PIPELINE_K}": measured[kind]["stages=2"]} if kind in ("pipeline", "slices") else measured[kind]
        for k, row in section.items():
            rows.append(
                (
                    name,
                    k,
                    row["env_steps_per_s"]["median"],
                    f"{row['fraction_of_physics_only']}",
                    f"{row['fraction_of_ceiling']}",
                    f"{row['fraction_of_ceiling_with_resets']}",
                )
            )
    print(
        f"{'contender':<30} {'K':>6} {'env-steps/s':>12} {'of physics-only':>16} {'of ceiling':>11} {'with resets':>12}"
    )
    for name, k, rate, of_physics, of_top, of_resets in rows:
        print(f"{name:<30} {k:>6} {rate:>12.1f} {of_physics:>16} {of_top:>11} {of_resets:>12}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    mode = parser.add_mutually_exclusive_group(required=True)
    mode.add_argument("--gpu", action="store_true", help="LIBERO-10, 256x256 x 2 cameras, 12 pods; GL must be NVIDIA's")
    mode.add_argument("--cpu-small", action="store_true", help="2 pods of tiny/lift + tiny/door, 32x32 (Mesa)")
    mode.add_argument(
        "--quick",
        action="store_true",
        help="--cpu-small on HalfCheetah (2 envs a pod), 16x16, 8 actions, K = 1 and 8: a smoke run",
    )
    parser.add_argument("--dry", action="store_true", help="1 pod, K = 1 and 4, 4 actions, 1 round: fails fast")
    parser.add_argument("--tasks", help="comma-separated task ids every pod serves")
    parser.add_argument("--envs-per-task", type=int, help="envs per task per pod (default 1)")
    parser.add_argument("--pods", type=int, help="pods, one per core (default 12; --cpu-small 2)")
    parser.add_argument(
        "--chunks",
        help="comma-separated chunk lengths K (default 1,4,8,16; without 1, the "
        "chunks target (K=8 over K=1) is not measured)",
    )
    parser.add_argument(
        "--waves",
        type=int,
        default=1,
        help="trajectories per env in each EnvLoop rollout: the envs refill as trajectories end, "
        "so a faster pod takes more of them (default 1: one per env)",
    )
    parser.add_argument("--actions", type=int, help="actions per env in every rollout (default 32; --cpu-small 8)")
    parser.add_argument("--size", type=int, help="camera height and width (default 256; --cpu-small 32)")
    parser.add_argument("--rounds", type=int, help="interleaved rounds (default 2; --cpu-small 1)")
    parser.add_argument("--physics-seconds", type=float, help="length of the physics-only run (default 10)")
    parser.add_argument(
        "--stage-layout",
        default=",".join(STAGE_LAYOUTS),
        help="the 2-stage layouts measured at K = 8 beside 1 stage, comma-separated (slices, pods; default both)",
    )
    parser.add_argument("--render-preset", default="lean", choices=("full", "fast", "lean", "lowpoly"))
    parser.add_argument(
        "--max-memory-gib", type=float, default=100.0, help="stop when memory in use passes this while the pods build"
    )
    parser.add_argument("--deadline", type=float, default=540.0, help="seconds: stop adding rounds after this")
    parser.add_argument("--copy-to", type=Path, help="also copy the JSON (and a failed job's logs) here")
    args = parser.parse_args()
    if args.quick:
        args.cpu_small = True
        for name, value in QUICK.items():
            if getattr(args, name) is None:
                setattr(args, name, value)
    setup_logging()
    os.environ.setdefault("MUJOCO_GL", "egl")
    if math.isnan(args.deadline) or args.deadline <= 0:
        parser.error("--deadline must be a positive number of seconds")
    if args.waves < 1:
        parser.error(f"--waves must be >= 1, got {args.waves}")
    return run(args)


if __name__ == "__main__":
    sys.exit(main())
