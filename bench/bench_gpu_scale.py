"""At scale on a GPU machine: LIBERO-10 at 256x256 x 2 cameras, pinned pods, bf16 vision policies.

Two measurements, one invocation each (``--only``), each starting its own local job
(``service.runner.LocalJob``: the controller and its pods, each pod and its env worker pinned
with ``pods.cpu_affinity``, rendering with ``MUJOCO_GL=egl``) and a trainer in this process,
pinned to the cores left over. Every pod serves the SAME task mix (``--tasks-per-pod`` tasks of
``--tasks``, ``--envs-per-task`` envs each; default: the ten LIBERO-10 tasks, one env each, and
for the pipeline's 2C pods the first five), all its envs in ONE worker process, so pods carry
equal load. The job has one stage per pod (so the
controller gives every pod the whole mix); the trainer groups pods into its own stages.

- ``--only scaling``: pods pinned one per core, physical cores first (hyperthread siblings
  last; the CPU topology is recorded). For P in ``--pod-counts``, over the first P pods, one
  stage: (a) the service alone: a StageClient stepping every env with scripted actions, no
  policy; (b) the pipelined EnvLoop with a ResNet-18 policy (bf16, one CUDA graph per batch
  size). Interleaved rounds; linear = P x the 1-pod figure of the same round. Per stage call
  the client's per-pod round trips are recorded: their mean and the slowest pod's, so the cost
  of waiting for the slowest pod is known; the pods' ``/metrics`` split a pod's time into
  physics, rendering and the rest.
- ``--only pipeline``: ``--pipeline-cores`` C cores, 2C pods, pod i and pod i+C on core i
  (``--pods-per-core 1``: C pods, a core each, to be split in ``slices``; give them twice the
  envs with ``--envs-per-task 2`` for the same job size).
  1 stage = all the pods' envs (both pods of a core simulate at once); 2 stages in each
  ``--stage-layout`` (the job setting's two values, side by side in interleaved rounds):
  ``pods``: pods 0..C-1 against C..2C-1 (one stage simulates while the other's observations are
  in the policy); ``slices``: every pod's envs alternate stage 0, stage 1, ... (a stage is a
  slice of every pod, as the ``slices`` job plan lays them out). Also 1 stage in lockstep
  (``stages=1/lockstep``: the loop waits for every pod of the stage before the policy runs, the
  rollout before issue 27), the second baseline of two stages. The policy is
  a ViT-B/16-style encoder per camera (bf16) whose depth is calibrated so that its forward pass
  on the 1-stage batch lasts as long as the 1-stage simulation call (the service alone), captured
  in a CUDA graph per batch size, so its launches cost the trainer's Python thread little (every
  multiple of a pod's envs is captured before the clock, and other sizes are padded to one).
  ``--chunk K``: the policy acts in chunks of K actions (its one action repeated K times), the
  service's calls step K actions too (K=8 is issue 27's case).

Commands::

    source .device/setup.sh && python bench/bench_gpu_scale.py --gpu --only scaling --copy-to "$OUT"
    source .device/setup.sh && python bench/bench_gpu_scale.py --gpu --only pipeline --copy-to "$OUT"
    python bench/bench_gpu_scale.py --gpu --only pipeline --dry   # probe: 1 core, tiny policy; fails fast
    # a machine of 2 GPUs: pods render on GPU 1, the policy runs on GPU 0
    python bench/bench_gpu_scale.py --gpu --only pipeline --render-gpu 1 --tag render-gpu1 --copy-to "$OUT"
    python bench/bench_gpu_scale.py --cpu-small --only scaling     # here: 2 pods, 2 LIBERO tasks, 64x64
    # issue 27's case: two stages against one at K=8, both layouts side by side
    source .device/setup.sh && python bench/bench_gpu_scale.py --gpu --only pipeline --chunk 8 --copy-to "$OUT"
    python bench/bench_gpu_scale.py --quick --chunk 8   # here, under ~2 min: a cheap gym scene, tiny ViT
    # the same, each layout also waiting 30 ms for more of a stage's pods before the policy runs,
    # and waiting for all of them (two stages, each in lockstep)
    python bench/bench_gpu_scale.py --gpu --only pipeline --chunk 8 --render-gpu 1 --compare-batch-wait-s 0.03,300

Each writes out/bench/bench_gpu_scale_<scaling|pipeline>[_cpu|_dry|_quick].json and its plots under
docs/img/, and prints one ``RESULT {json}`` line; ``--copy-to`` also copies them into a folder,
with a failed job's logs (``<job id>-logs.tar.gz``). Rounds stop being added at ``--deadline``
seconds after the start; the job's start-up is bounded by it too, and memory in use above
``--max-memory-gib`` while the pods build stops the run.

``--render-compare`` measures GPU against software rendering on the same pod setup instead: one
pinned pod of one scene (default LIBERO-10 task 0, 256x256, two cameras, 4 envs), first with the
machine's EGL (NVIDIA's vendor file when the machine has one), then with Mesa's software EGL
(llvmpipe): the bundle's private copy when ``mesa.sh`` exported ``VECSIM_MESA_*`` (see
``scripts/build_device_bundle.py --mesa``), else the machine's own Mesa vendor file. Each pod is
a new job with ``__EGL_VENDOR_LIBRARY_FILENAMES`` (and, for the carried Mesa, ``LD_LIBRARY_PATH``
and ``LIBGL_DRIVERS_PATH``) set for it alone; GL_VENDOR, GL_RENDERER and the EGL libraries a
child process with that environment maps are recorded. Both run the same open-loop actions from
the same init states, so physics is the same (the proprio of every step is compared) and the
images differ only by the renderer; the images are compared pixel by pixel. Writes
out/bench/bench_gpu_render_compare[_cpu].json and docs/img/gpu_render_compare[_cpu].png (bars)
and ..._frames.png (the two renderers' images and their difference):

    source .device-mesa/setup.sh && python bench/bench_gpu_scale.py --render-compare --copy-to "$OUT"
    source .device-mesa/mesa.sh && python bench/bench_gpu_scale.py --render-compare --size 64   # here
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
from typing import TYPE_CHECKING, Any

# Only what checking the options needs loads here: a refused option exits at once, not after
# seconds of torch, MuJoCo and the service's code, which the functions that run import.
from lib.jobs import STAGE_LAYOUTS, Plan, parse_stage_layouts

if TYPE_CHECKING:
    from lib.measure import Deadline, Measured

    from vecsim.config import RoutingTable

log = logging.getLogger("bench.gpu_scale")

# A batch wait that outlasts any stage call: EnvLoop then waits for every pod of the stage before
# the policy runs, the lockstep rollout from before issue 27 (the baseline that issue measured).
LOCKSTEP_WAIT_S = 300.0
QUICK_TASKS = ("gym/HalfCheetah-v5",)  # --quick: a cheap scene, so the run fits in about 2 min
QUICK_ENVS_PER_TASK = 4


# -- scaling -------------------------------------------------------------------------------------


def measure_scaling(plan: Plan, job: Any, table: RoutingTable, deadline: Deadline) -> dict[str, Any]:
    """For each pod count P, the first P pods in one stage: the service alone (scripted actions)
    and the EnvLoop with the graphed ResNet-18 policy; and the EnvLoop with a stage per pod (P
    stages of one pod: a slow pod holds up its own stage only). Interleaved rounds."""
    from lib.jobs import regroup, requests_for
    from lib.measure import TimedStageClient, interleave, loop_rollout, service_rollout
    from lib.pods import paired_ratio
    from lib.policies import GraphedPolicy, VisionPolicy, forward_ms, parameters_m
    from lib.stats import summarise

    names = [f"sim-{i}" for i in range(plan.pods)]
    clients: dict[int, TimedStageClient] = {}
    per_pod: dict[int, TimedStageClient] = {}
    try:
        for p in plan.pod_counts:
            clients[p] = TimedStageClient(
                regroup(table, names[:p], 1), token=job.token, timeout_s=300, ended_envs="step"
            )
            if p > 1:
                per_pod[p] = TimedStageClient(
                    regroup(table, names[:p], p), token=job.token, timeout_s=300, ended_envs="step"
                )
        full = clients[plan.pods]
        space, action = full.observation_space, full.action_space
        policy = VisionPolicy(space, action, device=plan.device, dtype=plan.torch_dtype)
        sizes = {p: len(requests_for(clients[p].routing)) for p in plan.pod_counts}
        graphed = GraphedPolicy(policy, space, plan.device, [*sizes.values(), plan.envs_per_pod])
        policy_info = {
            "name": "ResNet-18 per camera + proprio MLP + MLP head",
            "parameters_m": parameters_m(policy),
            "dtype": plan.dtype,
            "device": plan.device,
            "cuda_graphs": graphed.graphed,
            "forward_ms": {
                str(b): round(forward_ms(graphed, space, b, 5, plan.device), 2) for b in sorted(set(sizes.values()))
            },
        }
        log.info("policy: %s", policy_info)
        for p, client in clients.items():  # warm-up: connections open, caches filled, kernels picked
            service_rollout(client, min(plan.service_steps, 2), 300)
            loop_rollout(client, graphed, min(plan.horizon, 2), plan.device)
        for client in per_pod.values():
            loop_rollout(client, graphed, min(plan.horizon, 2), plan.device)
        log.info("warm-up done, %.0f s left", deadline.left())
        contenders: dict[str, Callable[[], Measured]] = {}
        for p, client in clients.items():
            contenders[f"service/pods={p}"] = lambda c=client: service_rollout(c, plan.service_steps, 300)
            contenders[f"loop/pods={p}"] = lambda c=client: loop_rollout(c, graphed, plan.horizon, plan.device)
            if p in per_pod:
                contenders[f"loop_per_pod/pods={p}"] = lambda c=per_pod[p]: loop_rollout(
                    c, graphed, plan.horizon, plan.device
                )
        runs = interleave(contenders, plan.rounds, deadline, reserve_s=20)
    finally:
        for client in [*clients.values(), *per_pod.values()]:
            client.close()
    if 1 in plan.pod_counts:  # with one pod, a stage per pod is the one stage
        runs["loop_per_pod/pods=1"] = runs["loop/pods=1"]
    result: dict[str, Any] = {"policy": policy_info}
    for kind in ("service", "loop", "loop_per_pod"):
        base = "loop" if kind == "loop_per_pod" else kind
        one = [m.env_steps_per_s for m in runs[f"{base}/pods=1"]] if 1 in plan.pod_counts else None
        section: dict[str, Any] = {}
        for p in plan.pod_counts:
            rounds = runs[f"{kind}/pods={p}"]
            section[f"pods={p}"] = summarise(rounds)
            if one is not None:
                section[f"pods={p}"]["fraction_of_linear"] = paired_ratio(
                    [m.env_steps_per_s for m in rounds], [p * x for x in one]
                )
        result[kind] = section
    result["per_round"] = {name: [round(m.env_steps_per_s, 2) for m in v] for name, v in runs.items()}
    return result


# -- pipelining ----------------------------------------------------------------------------------


WARMUP_HORIZON = 32  # pipeline: actions per trajectory in each contender's warm-up rollout


def measure_pipeline(plan: Plan, job: Any, table: RoutingTable, deadline: Deadline) -> dict[str, Any]:
    """P pods on C cores, pod i on core i % C (P = 2C: pods i and i+C share core i; P = C: a pod
    a core): the service alone in one stage (the target of the calibration) and its first half
    of the pods alone, then the EnvLoop with the calibrated graphed ViT in 1 stage (all pods)
    against 2 stages in each of ``plan.stage_layouts`` (``pods``: the first half of the pods
    against the second; ``slices``: every pod's envs alternating stages), interleaved rounds.
    Every call steps ``plan.chunk`` actions per env. For each of ``plan.compare_batch_wait_s``,
    each 2-stage layout also runs waiting that long for more of a stage's pods (:func:`waiting`).
    For each of ``plan.compare_stages``, ``slices`` also runs in that many stages, at
    ``plan.batch_wait_s`` and each compared wait: a third stage's slack against the slowest pod."""
    from lib.jobs import regroup, regroup_slices
    from lib.measure import Chunked, TimedStageClient, interleave, loop_rollout, service_rollout
    from lib.pods import paired_ratio
    from lib.policies import calibrate_vit, pod_multiples
    from lib.stats import breakdown, core_overlap, summarise, waiting

    names = [f"sim-{i}" for i in range(plan.pods)]
    half = plan.pods // 2
    core_of = {pod: i % plan.pipeline_cores for i, pod in enumerate(names)}
    two_stages = {"pods": regroup(table, names, 2), "slices": regroup_slices(table, names, 2)}
    more_stages = {n: regroup_slices(table, names, n) for n in plan.compare_stages}
    clients: dict[str, TimedStageClient] = {}

    def client_of(routing: RoutingTable) -> TimedStageClient:
        return TimedStageClient(routing, token=job.token, timeout_s=300, ended_envs="step")

    try:
        clients["stages=1"] = client_of(regroup(table, names, 1))
        for layout in plan.stage_layouts:
            clients[f"{layout}/stages=2"] = client_of(two_stages[layout])
        for n, routing in more_stages.items():
            clients[f"slices/stages={n}"] = client_of(routing)
        clients["half"] = client_of(regroup(table, names[:half], 1))
        one = clients["stages=1"]
        k = plan.chunk
        for client in (one, clients["half"]):  # warm-up
            service_rollout(client, min(plan.service_steps, 2), 300, k)
        service = interleave(
            {
                "service/stages=1": lambda: service_rollout(one, plan.service_steps, 300, k),
                "service/half": lambda: service_rollout(clients["half"], plan.service_steps, 300, k),
            },
            plan.rounds,
            deadline,
            reserve_s=0.6 * max(deadline.left(), 0),
        )
        target_ms = breakdown(service["service/stages=1"])["stage_call_ms"]
        batch = one.routing.num_envs
        stage_sizes = sorted(
            {stage.num_envs for layout in plan.stage_layouts for stage in two_stages[layout].stages}
            | {stage.num_envs for routing in more_stages.values() for stage in routing.stages}
        )
        space, action = one.observation_space, one.action_space
        # Without lockstep the loop's policy calls take batches of many sizes, mostly whole lanes'
        # answers (a lane: one stage's envs on one pod); a size met first inside a timed round would
        # be captured there (seconds for this ViT). So every multiple of a lane's envs is captured
        # up front and other sizes padded. More stages' lanes are not (a pod's envs split three
        # ways leave lanes of one env); their whole stages are, and part stages are padded.
        lane = math.gcd(
            *(p.num_envs for layout in plan.stage_layouts for stage in two_stages[layout].stages for p in stage.pods),
            plan.envs_per_pod,
        )
        graphed, policy_info = calibrate_vit(
            plan, space, action, batch, target_ms, [batch, *stage_sizes], pod_multiples(lane, batch)
        )
        policy = Chunked(graphed, k)
        # Each contender: (its client, its batch_wait_s); for each compare_batch_wait_s, each
        # 2-stage layout again, waiting that long for more of a stage's pods before the policy runs.
        contenders = {
            name: (name, plan.batch_wait_s)
            for name in ["stages=1", *(f"{layout}/stages=2" for layout in plan.stage_layouts)]
        }
        contenders.update(
            {
                waiting(layout, wait): (f"{layout}/stages=2", wait)
                for wait in plan.compare_batch_wait_s
                for layout in plan.stage_layouts
            }
        )
        for n in plan.compare_stages:
            contenders[f"slices/stages={n}"] = (f"slices/stages={n}", plan.batch_wait_s)
            contenders.update(
                {waiting("slices", wait, n): (f"slices/stages={n}", wait) for wait in plan.compare_batch_wait_s}
            )
        # Warm-up: a short rollout per contender (connections, the pods' first renders); the
        # policy's batch sizes are all captured already.
        for client_name, wait in contenders.values():
            loop_rollout(clients[client_name], policy, min(plan.horizon, WARMUP_HORIZON), plan.device, wait)
        log.info("warm-up done, %.0f s left", deadline.left())
        runs = {
            name: (lambda c=clients[client_name], w=wait: loop_rollout(c, policy, plan.horizon, plan.device, w))
            for name, (client_name, wait) in contenders.items()
        }
        # One stage in lockstep: the whole stage's answers before each policy call.
        runs["stages=1/lockstep"] = lambda: loop_rollout(one, policy, plan.horizon, plan.device, LOCKSTEP_WAIT_S)
        loops = interleave(runs, plan.rounds, deadline, reserve_s=20)
    finally:
        for client in clients.values():
            client.close()
    rates = {name: [m.env_steps_per_s for m in runs] for name, runs in loops.items()}
    compared = [
        {
            "batch_wait_s": wait,
            # Over the same layout at --batch-wait-s (default 0: no wait).
            "speedup_over_same_layout": {
                layout: paired_ratio(rates[waiting(layout, wait)], rates[f"{layout}/stages=2"])
                for layout in plan.stage_layouts
            },
            "speedup_2_vs_1_lockstep": {
                layout: paired_ratio(rates[waiting(layout, wait)], rates["stages=1/lockstep"])
                for layout in plan.stage_layouts
            },
        }
        for wait in plan.compare_batch_wait_s
    ]
    return {
        **({"batch_wait": compared} if compared else {}),
        "policy": {**policy_info, "chunk": plan.chunk, "graphs": graphed.describe()},
        "service": {name.split("/")[1]: summarise(runs) for name, runs in service.items()},
        # Pods i and i+C share core i: how often they simulate at once (0 with a pod a core).
        "loop": {
            name: {**summarise(runs), "core_overlap": core_overlap(runs, core_of)} for name, runs in loops.items()
        },
        "speedup_2_vs_1": {
            layout: paired_ratio(rates[f"{layout}/stages=2"], rates["stages=1"]) for layout in plan.stage_layouts
        },
        # Against one stage in lockstep (the rollout issue 27 measured): the no-lockstep loop's one
        # stage already overlaps its policy with the simulation of pods still in flight.
        "speedup_2_vs_1_lockstep": {
            layout: paired_ratio(rates[f"{layout}/stages=2"], rates["stages=1/lockstep"])
            for layout in plan.stage_layouts
        },
        # Every contender over 1 stage in lockstep, more stages' included.
        "speedup_over_lockstep": {
            name: paired_ratio(values, rates["stages=1/lockstep"])
            for name, values in rates.items()
            if name != "stages=1/lockstep"
        },
        "stage_envs": {
            **{
                layout: [[p.num_envs for p in stage.pods] for stage in two_stages[layout].stages]
                for layout in plan.stage_layouts
            },
            **{
                f"slices/stages={n}": [[p.num_envs for p in stage.pods] for stage in routing.stages]
                for n, routing in more_stages.items()
            },
        },
        "per_round": {name: [round(m.env_steps_per_s, 2) for m in runs] for name, runs in {**service, **loops}.items()},
    }


def make_plan(args: argparse.Namespace) -> Plan:
    """The run's sizes: ``--gpu``, ``--cpu-small`` or ``--quick`` defaults, ``--dry`` shrinks,
    then overrides. Every size is checked before torch loads (last, for the device); without
    ``--tasks``, LIBERO-10's task list loads MuJoCo and LIBERO first.

    Raises:
        SystemExit: sizes the run cannot lay out (the message names the option).
    """
    gpu, dry, quick = args.gpu, args.dry, args.quick
    if args.tasks:
        tasks = tuple(t for t in args.tasks.split(",") if t)
    elif quick:
        tasks = QUICK_TASKS
    else:
        from vecsim.engine.tasks import suite_tasks

        every = tuple(t.task_id for t in suite_tasks("libero_10"))
        tasks = every if gpu else every[:2]
    # 2C pods of ten LIBERO tasks each (~5 GiB a pod, estimated) would crowd 125 GiB: pipelining
    # serves five by default on the GPU machine.
    per_pod = args.tasks_per_pod or (min(5, len(tasks)) if gpu and args.only == "pipeline" else len(tasks))
    if not 1 <= per_pod <= len(tasks):
        raise SystemExit(f"--tasks-per-pod must be 1..{len(tasks)} (the tasks given), got {per_pod}")
    cores = 1 if dry else args.pipeline_cores or (8 if gpu else 1)
    if args.pods_per_core not in (1, 2):
        raise SystemExit(f"--pods-per-core must be 1 or 2, got {args.pods_per_core}")
    if args.only == "pipeline":
        pods = args.pods_per_core * cores
        if pods < 2:
            raise SystemExit(f"--pods-per-core 1 needs --pipeline-cores of at least 2 (two stages), got {cores}")
        counts = (pods,)
    else:
        pods = 1 if dry else args.pods or (12 if gpu else 2)
        try:
            given = (
                tuple(int(c) for c in args.pod_counts.split(","))
                if args.pod_counts
                else ((1, 2, 4, 8, 12) if gpu else (1, 2))
            )
        except ValueError:
            raise SystemExit(f"--pod-counts takes pod counts, comma-separated: got {args.pod_counts!r}") from None
        counts = tuple(sorted({c for c in given if 1 <= c <= pods} | {1, pods}))
    max_depth = args.vit_max_depth or (512 if gpu else 256)
    chunk = args.chunk
    if chunk < 1:
        raise SystemExit(f"--chunk must be at least 1, got {chunk}")
    layouts = parse_stage_layouts(args.stage_layout)
    # The horizon counts actions: by default as many calls at K as at K=1.
    horizon = 2 * chunk if dry else args.horizon or (30 if gpu else 6 if quick else 3) * chunk
    envs_per_task = args.envs_per_task or (QUICK_ENVS_PER_TASK if quick else 1)
    envs = pods * per_pod * envs_per_task
    for n in args.compare_stages:
        # The loop gives request i to stage i % n: the stages must be of one size.
        if envs % n:
            raise SystemExit(
                f"--compare-stages {n}: the job's {envs} envs do not split into {n} equal stages "
                "(change --tasks-per-pod, --envs-per-task or the pods)"
            )
    import torch  # after every check: seconds to load

    cuda = torch.cuda.is_available()
    return Plan(
        mode=args.only,
        tasks=tasks[:per_pod],
        size=args.size or (256 if gpu else 16 if quick else 64),
        envs_per_task=envs_per_task,
        pods=pods,
        pod_counts=counts,
        pipeline_cores=cores,
        horizon=horizon,
        service_steps=2 if dry else args.service_steps or (30 if gpu else 3),
        rounds=1 if dry else args.rounds or (3 if gpu else 2 if quick else 1),
        device="cuda" if cuda else "cpu",
        dtype="bfloat16" if cuda else "float32",
        vit_width=args.vit_width or (768 if gpu else 64 if quick else 192),
        vit_max_depth=min(max_depth, 4) if dry else min(max_depth, 32) if quick else max_depth,
        max_memory_gib=args.max_memory_gib,
        deadline_s=args.deadline,
        render_preset=args.render_preset,
        render_gpu=args.render_gpu,
        chunk=chunk,
        batch_wait_s=args.batch_wait_s,
        compare_batch_wait_s=args.compare_batch_wait_s,
        stage_layouts=layouts,
        pods_per_core=args.pods_per_core,
        compare_stages=args.compare_stages,
    )


def run_mode(args: argparse.Namespace, plan: Plan) -> int:
    """``--only scaling`` or ``--only pipeline`` (with ``--gpu``, ``--cpu-small``, ``--dry``)."""
    import psutil
    import torch
    from lib.jobs import camera, job_config, pod_processes, running_job, wait_for_job
    from lib.machine import (
        MemoryWatch,
        cores_first,
        cpu_topology,
        gl_probe,
        gpu_name,
        gpu_process_table,
        memory_gib,
        physical_core_of,
        split_cores,
    )
    from lib.measure import Deadline
    from lib.plots import plot_pipeline, plot_scaling
    from lib.records import img_dir, write_result
    from lib.stats import PIPELINE_TARGET, SCALING_TARGET

    deadline = Deadline(args.deadline)
    tag = ("_dry" if args.dry else "" if args.gpu else "_quick" if args.quick else "_cpu") + (
        f"_{args.tag}" if args.tag else ""
    )
    gl = gl_probe()
    gpu = gpu_name()
    log.info("GL: %s; GPU: %s; torch %s on %s", gl, gpu, torch.__version__, plan.device)
    if args.gpu and "NVIDIA" not in gl.get("renderer", "").upper():
        log.error("GL_RENDERER is %r, not NVIDIA's: not measuring", gl.get("renderer", gl))
        return 2
    if args.gpu and plan.device != "cuda":
        log.error("torch sees no CUDA device: not measuring")
        return 2

    topology = cpu_topology()
    pinned = plan.pods if plan.mode == "scaling" else plan.pipeline_cores
    pins, trainer = split_cores(cores_first(topology), pinned)
    pod_pins = [pins[i % len(pins)] for i in range(plan.pods)]
    # Pinned before the client's threads start, so they and torch inherit it; the controller too.
    os.sched_setaffinity(0, set(trainer))
    torch.set_num_threads(len(trainer))
    torch.backends.cudnn.benchmark = True
    log.info(
        "topology: %d CPUs, %d physical cores; pods pinned to %s; trainer on %s",
        topology["cpus"],
        topology["physical_cores"],
        pod_pins,
        trainer,
    )

    started = time.monotonic()
    config = job_config(plan, pins, f"gpu-{plan.mode}", plan.pods)
    with running_job(config, args.copy_to) as job, MemoryWatch(plan.max_memory_gib) as memory:
        table = wait_for_job(job, max(60.0, min(600.0, deadline.left())))
        build_s = time.monotonic() - started
        used = memory_gib()
        processes = pod_processes(job)
        gpu_processes = gpu_process_table()
        log.info(
            "%d pods ready in %.0f s; memory used %.1f GiB; per pod %s",
            plan.pods,
            build_s,
            used,
            next(iter(processes.values())),
        )
        if plan.mode == "scaling":
            measured = measure_scaling(plan, job, table, deadline)
        else:
            measured = measure_pipeline(plan, job, table, deadline)
        used_end = memory_gib()

    cores_of_pods = [physical_core_of(topology, cpu) for cpu in pod_pins]
    setup = {
        **dataclasses.asdict(plan),
        "suite": "libero_10" if plan.tasks[0].startswith("libero_10/") else plan.tasks[0].split("/")[0],
        "envs_per_pod": plan.envs_per_pod,
        "camera": camera(plan),
        "pods_pinned_to": pod_pins,
        "pods_physical_cores": cores_of_pods,
        "trainer_cores": trainer,
        "torch": torch.__version__,
        "job_build_s": round(build_s, 1),
        "memory_used_gib_at_ready": used,
        "memory_used_gib_at_end": used_end,
        "memory_used_gib_peak": memory.peak_gib,
        "memory_total_gib": round(psutil.virtual_memory().total / 2**30, 1),
        "pod_processes": processes,
        "gpu_processes_at_ready": gpu_processes,
        "pod_tasks": {p.pod: [f"{b.task_id} x{b.num_envs}" for b in p.tasks] for st in table.stages for p in st.pods},
    }
    setup["how"] = {
        "service": "service_rollout: reset every env, then service_steps calls stepping all of them with scripted "
        "actions, no policy; env-steps/s over the step calls only",
        "loop": "one EnvLoop.run: reset, then `horizon` steps of every trajectory; env-steps/s over the whole run",
        "slowest_pod": "per stage call, the client's round trip to each pod (HTTP + the pod's work + decoding): "
        "the mean over the call's pods and the slowest; medians over calls",
    }
    details = {"per_round": measured.pop("per_round")}
    summary: dict[str, Any] = {"quick": not args.gpu, "dry": args.dry}
    setup["chunk"] = plan.chunk
    if plan.mode == "scaling":
        physical = topology["physical_cores"]
        top = f"pods={plan.pods}"
        within = [p for p in plan.pod_counts if len(set(cores_of_pods[:p])) == p]
        service = measured["service"][top].get("fraction_of_linear", {}).get("median")
        loop = measured["loop"][top].get("fraction_of_linear", {}).get("median")
        loop_per_pod = measured["loop_per_pod"][top].get("fraction_of_linear", {}).get("median")
        at_cores = f"pods={max(within)}" if within else None
        summary.update(
            {
                "baseline": "1 pod of the same job (same task mix), same round; linear = pods x that",
                "ratio": service,
                "ratio_loop": loop,
                "ratio_loop_stage_per_pod": loop_per_pod,
                "ratio_at_physical_cores": measured["service"][at_cores].get("fraction_of_linear", {}).get("median")
                if at_cores
                else None,
                "largest_pod_count_on_distinct_physical_cores": max(within) if within else None,
                "pod_counts_beyond_physical_cores": [p for p in plan.pod_counts if p not in within],
                "target": f"scaling >= {SCALING_TARGET} of linear at {plan.pods} pods ({physical} physical cores)",
                "met": {
                    "scaling_service": service is not None and service >= SCALING_TARGET,
                    "scaling_loop": loop is not None and loop >= SCALING_TARGET,
                    "scaling_loop_stage_per_pod": loop_per_pod is not None and loop_per_pod >= SCALING_TARGET,
                },
            }
        )
    else:
        speedups = {layout: ratio["median"] for layout, ratio in measured["speedup_2_vs_1"].items()}
        setup["stage_envs"] = [plan.envs_per_pod * (plan.pods // 2)] * 2
        setup["stage_envs_by_layout"] = measured.pop("stage_envs")
        summary.update(
            {
                "baseline": "1 stage over the same pods (both pods of a core simulate at once), same policy; "
                "also 1 stage in lockstep (speedup_2_vs_1_lockstep)",
                # The headline: the first layout measured (--stage-layout's order; 'slices' by default).
                "ratio": speedups[plan.stage_layouts[0]],
                "ratio_by_layout": speedups,
                "ratio_over_lockstep_by_layout": {
                    layout: ratio["median"] for layout, ratio in measured["speedup_2_vs_1_lockstep"].items()
                },
                "target": f"2 stages >= {PIPELINE_TARGET}x 1 stage at K={plan.chunk}",
                "met": {f"pipelining_{layout}": speedup >= PIPELINE_TARGET for layout, speedup in speedups.items()},
            }
        )
    summary.update({"setup": setup, "topology": topology, "gpu": gpu, "gl": gl, **measured})
    if args.dry:
        plots: list[Path] = []
    elif plan.mode == "scaling":
        plots = plot_scaling(summary, tag)
    else:
        plots = plot_pipeline(summary, tag)
    summary["plots"] = [str(p.relative_to(img_dir().parent.parent)) for p in plots]
    path = write_result(f"bench_gpu_scale_{plan.mode}{tag}", summary, details)
    if args.copy_to:
        args.copy_to.mkdir(parents=True, exist_ok=True)
        for item in (path, *plots):
            shutil.copy(item, args.copy_to / item.name)
    return 0


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line, every option checked alone and against the others (``--only``, the
    waits, ``--compare-stages``); :func:`make_plan` checks the sizes they lay out.

    Raises:
        SystemExit: argparse's usage error (2), naming the option.
    """
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    mode = parser.add_mutually_exclusive_group(required=True)
    mode.add_argument("--gpu", action="store_true", help="LIBERO-10 at 256x256 with its defaults; GL must be NVIDIA's")
    mode.add_argument("--cpu-small", action="store_true", help="2 LIBERO-10 tasks per pod, 64x64, few pods (Mesa)")
    mode.add_argument(
        "--quick",
        action="store_true",
        help="--only pipeline on this machine in about 2 min: a cheap gym scene, 16x16, a tiny ViT",
    )
    mode.add_argument(
        "--render-compare",
        action="store_true",
        help="one pod of one scene (default libero_10/0, 256x256, 4 envs): default EGL, then Mesa's",
    )
    parser.add_argument(
        "--only",
        choices=("scaling", "pipeline"),
        help="which measurement (one job each; required with --gpu and --cpu-small)",
    )
    parser.add_argument(
        "--dry",
        action="store_true",
        help="the same code at the smallest size (1 pod / 1 core, 2 steps, a 4-block ViT): fails fast",
    )
    parser.add_argument("--tasks", help="comma-separated task ids (default: LIBERO-10; --cpu-small: its first 2)")
    parser.add_argument(
        "--tasks-per-pod",
        type=int,
        help="how many of --tasks every pod serves (default: all; --gpu --only pipeline: 5)",
    )
    parser.add_argument("--envs-per-task", type=int, help="envs per task per pod (default 1; --render-compare 4)")
    parser.add_argument("--pods", type=int, help="scaling: the most pods (default 12; --cpu-small 2)")
    parser.add_argument("--pod-counts", help="scaling: comma-separated pod counts (default 1,2,4,8,12)")
    parser.add_argument("--pipeline-cores", type=int, help="pipeline: C cores, 2C pods (default 8; --cpu-small 1)")
    parser.add_argument("--size", type=int, help="camera height and width")
    parser.add_argument("--horizon", type=int, help="steps per trajectory in each EnvLoop rollout")
    parser.add_argument("--service-steps", type=int, help="steps per service-alone rollout")
    parser.add_argument("--rounds", type=int)
    parser.add_argument(
        "--batch-wait-s",
        type=float,
        default=0.0,
        help="pipeline: EnvLoop's batch_wait_s, how long the loop waits for more of a stage's "
        "answers before the policy runs (default 0: at once)",
    )
    parser.add_argument(
        "--compare-batch-wait-s",
        default="",
        help="pipeline: also run each 2-stage layout with each of these batch_wait_s (seconds, "
        "comma-separated), side by side in the same rounds (contenders "
        "'<layout>/stages=2/batch_wait=<W>s'): fuller policy batches against the time the loop "
        "waits for them; a wait longer than a stage call is each stage in lockstep",
    )
    parser.add_argument(
        "--chunk",
        type=int,
        default=1,
        help="pipeline: actions per env per call, the policy's chunk K (default 1; issue 27: 8)",
    )
    parser.add_argument(
        "--stage-layout",
        default=",".join(STAGE_LAYOUTS),
        help="pipeline: the 2-stage layouts to measure against 1 stage, comma-separated "
        "(slices, pods; default both, side by side)",
    )
    parser.add_argument(
        "--compare-stages",
        default="",
        help="pipeline: also run 'slices' in each of these stage counts (3 or more, comma-separated), "
        "at --batch-wait-s and each --compare-batch-wait-s (contenders 'slices/stages=<N>[...]')",
    )
    parser.add_argument(
        "--pods-per-core",
        type=int,
        default=2,
        help="pipeline: pods pinned to each core (2: one of each 'pods' stage a core; 1: one pod a "
        "core, its envs split between the stages in 'slices')",
    )
    parser.add_argument("--vit-width", type=int, help="pipeline: the ViT's width (default 768; --cpu-small 192)")
    parser.add_argument(
        "--vit-max-depth", type=int, help="pipeline: the calibration's cap (default 512; --cpu-small 256)"
    )
    parser.add_argument(
        "--max-memory-gib", type=float, default=100.0, help="stop when memory in use passes this while the pods build"
    )
    parser.add_argument(
        "--render-preset",
        default="lean",
        choices=("full", "fast", "lean", "lowpoly"),
        help="the pods' render preset (default lean)",
    )
    parser.add_argument(
        "--render-gpu",
        type=int,
        help="the EGL device (GPU index) pods render on (pods.render_gpus); the policy stays on cuda:0",
    )
    parser.add_argument("--tag", help="suffix of the output files' names (e.g. lowpoly)")
    parser.add_argument("--deadline", type=float, default=480.0, help="seconds: stop adding rounds after this")
    parser.add_argument("--soft-rounds", type=int, default=1, help="--render-compare: rollouts with Mesa")
    parser.add_argument("--copy-to", type=Path, help="also copy the JSON and plots (and a failed job's logs) here")
    args = parser.parse_args(argv)
    if args.render_compare:
        return args
    if args.quick:
        if args.only not in (None, "pipeline"):
            parser.error("--quick measures the pipeline only: leave --only out or say --only pipeline")
        args.only = "pipeline"
    if args.only is None:
        parser.error("--only scaling or --only pipeline: each measurement is its own run")
    try:
        args.compare_batch_wait_s = tuple(float(w) for w in args.compare_batch_wait_s.split(",") if w.strip())
    except ValueError:
        parser.error(f"--compare-batch-wait-s takes seconds, comma-separated: got {args.compare_batch_wait_s!r}")
    for flag, wait in (
        ("--batch-wait-s", args.batch_wait_s),
        *(("--compare-batch-wait-s", w) for w in args.compare_batch_wait_s),
    ):
        if not (math.isfinite(wait) and wait >= 0):
            parser.error(f"{flag} must be a finite number of seconds >= 0, got {wait}")
    if len(set(args.compare_batch_wait_s)) < len(args.compare_batch_wait_s):
        parser.error(f"--compare-batch-wait-s names a wait twice: {args.compare_batch_wait_s}")
    if args.compare_batch_wait_s and args.only != "pipeline":
        parser.error("--compare-batch-wait-s is a pipeline contender: say --only pipeline")
    try:
        args.compare_stages = tuple(dict.fromkeys(int(n) for n in args.compare_stages.split(",") if n.strip()))
    except ValueError:
        parser.error(f"--compare-stages takes stage counts, comma-separated: got {args.compare_stages!r}")
    if any(n < 3 for n in args.compare_stages):
        parser.error(
            f"--compare-stages: stage counts of 3 or more (1 and 2 are always measured), got {args.compare_stages}"
        )
    if args.compare_stages and (args.only != "pipeline" or "slices" not in args.stage_layout.split(",")):
        parser.error(
            "--compare-stages runs the 'slices' layout in more stages: "
            "say --only pipeline with slices in --stage-layout"
        )
    return args


def main() -> int:
    args = parse_args()
    os.environ.setdefault("MUJOCO_GL", "egl")  # before MuJoCo loads (LIBERO-10's task list)
    plan = None if args.render_compare else make_plan(args)
    # Every option is checked: what runs from here loads torch, MuJoCo and the service's code.
    from lib.pods import setup_logging

    setup_logging()
    if plan is None:
        from lib.render_compare import render_compare

        return render_compare(args)
    if args.gpu and plan.device != "cuda":
        import torch

        # Before anything starts (GL probe, pods): a machine without a GPU fails at once.
        log.error(
            "--gpu: torch sees no CUDA device on this machine (torch %s); run --quick or --cpu-small here",
            torch.__version__,
        )
        return 2
    return run_mode(args, plan)


if __name__ == "__main__":
    sys.exit(main())
