"""At scale on a GPU machine: LIBERO-10 at 256x256 x 2 cameras, pinned pods, a bf16 vision policy.

One command starts a local job (``service.runner.LocalJob``: the controller and ``--pods`` pods,
each pod and its env workers pinned to one core with ``pods.cpu_affinity``, rendering with
``MUJOCO_GL=egl``) and a trainer in this process, pinned to the cores left over, that runs a
ResNet-18-style vision policy (one encoder per camera, proprio MLP, MLP head; bf16 on the GPU)
through the pipelined ``EnvLoop``. Each pod serves one task of the suite, ``--envs-per-task``
envs of it in one worker process; pods beyond the suite's task count (12 pods, 10 LIBERO-10
tasks) are standalone pods serving its tasks again, joined to the job's routing table at its
generation. The trainer groups pods into stages itself, so one build serves every measurement:

- scaling: env-steps/s of a 1-stage rollout over the first P pods, P in ``--pod-counts``
  (interleaved rounds; linear = P x the 1-pod figure of the same round);
- pipelining: 1 against 2 stages over all pods, with the ResNet-18 policy, and with a
  ViT-B/16-style policy whose depth is calibrated so that its forward pass on one stage takes
  as long as that stage's simulation (a stand-in for a VLA-sized policy: where pipelining pays);
- time per step, split: policy (the rollout's stats), and from the pods' ``/metrics``: physics
  and rendering (worker seconds), the pod's step wall time, and serving (the client's call
  time beyond the pod's: HTTP, codec, waiting for the slowest pod);
- rendering: the GL renderer of the pods' EGL (must be NVIDIA's with ``--gpu``), and, when
  Mesa's libEGL is on the machine, one pod of the same assignment rendering through Mesa
  (software) against the GPU pod.

    source .device/setup.sh && python bench/bench_gpu_scale.py --gpu --copy-to "$OUT"
    python bench/bench_gpu_scale.py --gpu --dry        # probe the machine only: fails fast
    python bench/bench_gpu_scale.py --cpu-small        # here: 2 pods, 2 LIBERO tasks, 64x64

Writes out/bench/bench_gpu_scale[_cpu|_dry].json and docs/img/gpu_scale*.png, prints
``RESULT {json}``; ``--copy-to`` also copies them into a folder.

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
import contextlib
import ctypes.util
import dataclasses
import glob
import json
import logging
import math
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import torch
import torch.nn.functional as F
import psutil
from _perf_common import (
    free_port,
    free_port_block,
    paired_ratio,
    rate_spread,
    setup_logging,
    standalone_pods,
    wait_until_ready,
)
from common import img_dir, write_result
from gymnasium import spaces
from torch import nn

from vecsim.client import StageClient, fetch_routing
from vecsim.config import Assignment, RoutedPod, RoutedStage, RoutingTable, RunnerConfig, TaskBlock
from vecsim.rollout import EnvLoop, RolloutStats

log = logging.getLogger("bench.gpu_scale")

PIPELINE_TARGET = 1.8  # 2 stages over 1 stage (the performance issue's target)
SCALING_TARGET = 0.8  # of linear
ROBOT_CAMERAS = ("agentview", "robot0_eye_in_hand")
MESA_VENDOR_GLOBS = ("/usr/share/glvnd/egl_vendor.d/*mesa*.json", "/etc/glvnd/egl_vendor.d/*mesa*.json")
NVIDIA_VENDOR_FILES = ("/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json",
                       "/usr/share/glvnd/egl_vendor.d/10_nvidia.json")  # fmt: skip
GL_LIBRARY = re.compile(r"EGL|GLX|GLdispatch|nvidia|mesa|LLVM|_dri\.so|gallium|gbm|glapi")


@dataclasses.dataclass(frozen=True)
class Plan:
    """What one run builds and measures."""

    tasks: tuple[str, ...]
    size: int
    pods: int
    pod_counts: tuple[int, ...]
    envs_per_task: int
    horizon: int
    rounds: int
    device: str
    dtype: str
    heavy: bool
    soft_horizon: int
    deadline_s: float


# -- the policy ----------------------------------------------------------------------------------


class BasicBlock(nn.Module):
    """ResNet's basic block: two 3x3 convs with batch norm, and a (projected) shortcut."""

    def __init__(self, inputs: int, outputs: int, stride: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(inputs, outputs, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(outputs)
        self.conv2 = nn.Conv2d(outputs, outputs, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(outputs)
        self.shortcut: nn.Module = nn.Identity()
        if stride != 1 or inputs != outputs:
            self.shortcut = nn.Sequential(nn.Conv2d(inputs, outputs, 1, stride, bias=False), nn.BatchNorm2d(outputs))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Return the block's output (spatial size divided by the stride)."""
        out = F.relu(self.bn1(self.conv1(x)))
        return F.relu(self.bn2(self.conv2(out)) + self.shortcut(x))


class ResNet18Encoder(nn.Module):
    """ResNet-18 (stem, 4 stages of 2 basic blocks, 64-512 channels) to a 512-d feature."""

    out_dim = 512

    def __init__(self) -> None:
        super().__init__()
        layers: list[nn.Module] = [
            nn.Conv2d(3, 64, 7, 2, 3, bias=False), nn.BatchNorm2d(64), nn.ReLU(), nn.MaxPool2d(3, 2, 1),
        ]  # fmt: skip
        inputs = 64
        for outputs, stride in ((64, 1), (128, 2), (256, 2), (512, 2)):
            layers += [BasicBlock(inputs, outputs, stride), BasicBlock(outputs, outputs, 1)]
            inputs = outputs
        self.body = nn.Sequential(*layers, nn.AdaptiveAvgPool2d(1), nn.Flatten())

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """Return ``[n, 512]`` features of ``[n, 3, H, W]`` normalised images."""
        return self.body(images)


class ViTEncoder(nn.Module):
    """A ViT over 16x16 patches (pre-norm blocks, ``width`` wide, ``depth`` deep) to its CLS token."""

    def __init__(self, size: int, width: int = 768, depth: int = 12, heads: int = 12) -> None:
        super().__init__()
        self.out_dim = width
        self.heads = heads
        self.patch = nn.Conv2d(3, width, 16, 16)
        tokens = (size // 16) ** 2 + 1
        self.cls = nn.Parameter(torch.zeros(1, 1, width))
        self.position = nn.Parameter(torch.randn(1, tokens, width) * 0.02)
        self.blocks = nn.ModuleList(
            nn.ModuleDict(
                {
                    "norm1": nn.LayerNorm(width),
                    "qkv": nn.Linear(width, 3 * width),
                    "proj": nn.Linear(width, width),
                    "norm2": nn.LayerNorm(width),
                    "mlp": nn.Sequential(nn.Linear(width, 4 * width), nn.GELU(), nn.Linear(4 * width, width)),
                }
            )
            for _ in range(depth)
        )
        self.norm = nn.LayerNorm(width)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """Return ``[n, width]`` CLS features of ``[n, 3, H, W]`` normalised images."""
        x = self.patch(images).flatten(2).transpose(1, 2)
        x = torch.cat([self.cls.expand(x.shape[0], -1, -1), x], dim=1) + self.position
        n, t, d = x.shape
        for block in self.blocks:
            q, k, v = block["qkv"](block["norm1"](x)).view(n, t, 3, self.heads, d // self.heads).unbind(2)
            attended = F.scaled_dot_product_attention(q.transpose(1, 2), k.transpose(1, 2), v.transpose(1, 2))
            x = x + block["proj"](attended.transpose(1, 2).reshape(n, t, d))
            x = x + block["mlp"](block["norm2"](x))
        return self.norm(x[:, 0])


class VisionPolicy(nn.Module):
    """One image encoder per camera, a proprio MLP and an MLP head to actions in the action bounds.

    ``encoder`` is ``"resnet18"`` or ``"vit"`` (ViT-B/16-style, ``vit_depth`` blocks). Runs in
    eval mode (batch norm uses its running statistics) in ``dtype`` on ``device``.
    """

    def __init__(
        self,
        observation_space: spaces.Dict,
        action_space: spaces.Box,
        *,
        encoder: str = "resnet18",
        vit_depth: int = 12,
        device: str = "cpu",
        dtype: torch.dtype = torch.float32,
    ) -> None:
        super().__init__()
        images = observation_space.spaces.get("images")
        self.cameras = list(images.spaces) if images is not None else []
        size = images[self.cameras[0]].shape[0] if self.cameras else 16

        def make() -> nn.Module:
            return ResNet18Encoder() if encoder == "resnet18" else ViTEncoder(size, depth=vit_depth)

        self.encoders = nn.ModuleDict({camera: make() for camera in self.cameras})
        feature = sum(e.out_dim for e in self.encoders.values())
        proprio = int(np.prod(observation_space["proprio"].shape))
        self.proprio = nn.Sequential(nn.Linear(proprio, 128), nn.GELU())
        actions = int(np.prod(action_space.shape))
        self.head = nn.Sequential(nn.Linear(feature + 128, 512), nn.GELU(), nn.Linear(512, 256), nn.GELU(),
                                  nn.Linear(256, actions))  # fmt: skip
        low, high = np.asarray(action_space.low, np.float32), np.asarray(action_space.high, np.float32)
        bounded = np.isfinite(low) & np.isfinite(high)
        self.register_buffer("center", torch.from_numpy(np.where(bounded, (low + high) / 2, 0.0).astype(np.float32)))
        self.register_buffer("scale", torch.from_numpy(np.where(bounded, (high - low) / 2, 1.0).astype(np.float32)))
        self.register_buffer("mean", torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1) * 255)
        self.register_buffer("std", torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1) * 255)
        self.dtype = dtype
        self.to(device=device, dtype=dtype, memory_format=torch.channels_last)
        self.eval()

    def forward(self, obs: dict[str, Any], instructions: list[str], task_ids: list[str]) -> torch.Tensor:
        """Return float32 actions ``[n, action_dim]`` for a batch of observations (uint8 images)."""
        features = []
        for camera in self.cameras:
            image = obs["images"][camera].to(self.center.device).permute(0, 3, 1, 2).to(self.dtype)
            image = ((image - self.mean) / self.std).contiguous(memory_format=torch.channels_last)
            features.append(self.encoders[camera](image))
        features.append(self.proprio(obs["proprio"].to(self.center.device, self.dtype)))
        raw = self.head(torch.cat(features, dim=1)).float()
        return self.center + self.scale * torch.tanh(raw)


def dummy_obs(space: spaces.Dict, batch: int, device: str) -> dict[str, Any]:
    """Return a batch of ``batch`` random observations of ``space``, as tensors on ``device``."""
    generator = torch.Generator().manual_seed(0)
    images = {
        camera: torch.randint(0, 256, (batch, *box.shape), generator=generator, dtype=torch.uint8).to(device)
        for camera, box in space["images"].spaces.items()
    }
    return {"images": images, "proprio": torch.randn((batch, *space["proprio"].shape), generator=generator).to(device)}


def forward_ms(policy: nn.Module, space: spaces.Dict, batch: int, calls: int, device: str) -> float:
    """Median milliseconds of one forward pass on ``batch`` observations, synchronised."""
    obs = dummy_obs(space, batch, device)
    times = []
    with torch.no_grad():
        for _ in range(calls + 2):  # the first calls pick kernels
            started = time.perf_counter()
            policy(obs, [""] * batch, [""] * batch).cpu()
            times.append(time.perf_counter() - started)
    return 1000 * statistics.median(times[2:])


# -- the machine ---------------------------------------------------------------------------------


def gl_probe(extra_env: dict[str, str] | None = None, timeout_s: float = 120.0) -> dict[str, Any]:
    """Return the GL backend/vendor/renderer/version a pod process would render with (made in a
    child process with this environment plus ``extra_env``), or ``{"error": ...}``."""
    code = "import json; from vecsim.batch_render import gl_info; print(json.dumps(gl_info()))"
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"), **(extra_env or {})}
    try:
        done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return {"error": f"no GL context within {timeout_s:.0f} s"}
    if done.returncode != 0:
        return {"error": done.stderr.strip().splitlines()[-1] if done.stderr.strip() else f"exit {done.returncode}"}
    return json.loads(done.stdout.strip().splitlines()[-1])


def mesa_egl() -> dict[str, Any]:
    """Return whether Mesa's libEGL is on this machine: its glvnd vendor file and library."""
    vendors = sorted({path for pattern in MESA_VENDOR_GLOBS for path in glob.glob(pattern)})
    return {"vendor_files": vendors, "library": ctypes.util.find_library("EGL_mesa"), "present": bool(vendors)}


def gpu_name() -> str | None:
    """Return nvidia-smi's name and driver of the GPU, or None without one."""
    try:
        done = subprocess.run(["nvidia-smi", "--query-gpu=name,driver_version", "--format=csv,noheader"],
                              capture_output=True, text=True, timeout=20)  # fmt: skip
    except (OSError, subprocess.TimeoutExpired):
        return None
    return done.stdout.strip() or None


def split_cores(pods: int) -> tuple[list[str], list[int]]:
    """Return each pod's CPU list and the trainer's cores: one core per pod while cores last,
    the rest to the trainer; with too few cores the trainer keeps the first and pods share the
    others."""
    cores = sorted(os.sched_getaffinity(0))
    if len(cores) > pods:
        return [str(c) for c in cores[:pods]], cores[pods:]
    rest = cores[1:] or cores
    return [str(rest[i % len(rest)]) for i in range(pods)], cores[:1]


# -- the job -------------------------------------------------------------------------------------


def camera(plan: Plan) -> dict[str, Any]:
    """The job's cameras: LIBERO's two (gym tasks: their one render camera), ``size`` square."""
    names = ("render",) if plan.tasks[0].startswith("gym/") else ROBOT_CAMERAS
    return {"names": list(names), "height": plan.size, "width": plan.size}


def runner_config(plan: Plan, pins: Sequence[str], job_id: str, tasks: Sequence[str]) -> RunnerConfig:
    """One stage of one pod per task, ``envs_per_task`` envs of it in one worker process: a
    worker hosts envs of one task, so this is the fewest processes (a pod serving all ten tasks
    needs ten workers, and 12 such pods did not build within 9 minutes on the GPU machine)."""
    return RunnerConfig.model_validate(
        {
            "job": {
                "job_id": job_id,
                "tasks": list(tasks),
                "group_size": plan.envs_per_task,
                "num_stages": 1,
                "pods_per_stage": len(tasks),
                "camera": camera(plan),
                "render": "lean",
                "envs_per_worker": plan.envs_per_task,
                "max_episode_steps": 520,
            },
            "pods": {
                "replicas": len(tasks),
                "base_port": free_port_block(len(tasks)),
                "max_envs": max(64, plan.envs_per_task),
                "cpu_affinity": list(pins[: len(tasks)]),
            },
            "controller": {
                "port": free_port(),
                "heartbeat_interval_s": 2.0,
                "heartbeat_ttl_s": 60.0,
                "reconcile_interval_s": 0.5,
            },
        }
    )


def extra_assignments(plan: Plan, job_id: str) -> list[Assignment]:
    """Pods beyond one per task (LIBERO-10 has 10 tasks; 12 pods are measured): standalone pods
    serving the suite's tasks again from its start, joined to the job's routing table."""
    first = min(plan.pods, len(plan.tasks))
    return [
        Assignment(
            generation=0, job_id=job_id, pod=f"sim-{i}", stage_id=0,
            tasks=(TaskBlock(task_id=plan.tasks[i % len(plan.tasks)], env_start=0, num_envs=plan.envs_per_task),),
            camera=camera(plan), render="lean", envs_per_worker=plan.envs_per_task, max_episode_steps=520,
        )  # fmt: skip
        for i in range(first, plan.pods)
    ]


def join_extra(table: RoutingTable, assignments: Sequence[Assignment], pods: Sequence[Any]) -> RoutingTable:
    """Move the standalone pods to the job's generation (same envs: no rebuild) and return the
    job's routing table with them added to its one stage."""
    routed = []
    for assignment, pod in zip(assignments, pods):
        moved = assignment.model_copy(update={"generation": table.generation})
        response = httpx.put(f"{pod.url}/v1/assignment", json=moved.model_dump(mode="json"), timeout=30)
        if response.status_code != 200 or response.json().get("rebuilt"):
            raise RuntimeError(f"{assignment.pod}: moving to generation {table.generation}: {response.text}")
        routed.append(RoutedPod(pod=assignment.pod, url=pod.url, num_envs=assignment.num_envs, tasks=assignment.tasks))
    for pod in pods:
        wait_until_ready(pod.url, pod, pod.log_path, 60)
    stage = table.stages[0]
    return table.model_copy(update={"stages": (stage.model_copy(update={"pods": (*stage.pods, *routed)}),)})


@contextlib.contextmanager
def running_job(
    config: RunnerConfig, keep_logs: Path | None = None, env: dict[str, str] | None = None
) -> Iterator[Any]:
    """Start a LocalJob (not waiting for it); yield it; stop every process it started on exit.
    When the body fails, the job's logs go to ``keep_logs/<job id>-logs.tar.gz``."""
    from service.runner.job import LocalJob

    job = LocalJob(config, log_dir=tempfile.mkdtemp(prefix="vecsim-gpu-scale-"), env=env, grace_s=10)
    try:
        job.start()
        yield job
    except BaseException:
        if keep_logs is not None:
            keep_logs.mkdir(parents=True, exist_ok=True)
            shutil.make_archive(str(keep_logs / f"{config.job.job_id}-logs"), "gztar", job.log_dir)
        raise
    finally:
        job.stop()


def regroup(table: RoutingTable, pods: Sequence[str], stages: int) -> RoutingTable:
    """The trainer's view: the named pods of the job's table, in order, in ``stages`` stages."""
    by_name = {p.pod: p for stage in table.stages for p in stage.pods}
    per_stage = math.ceil(len(pods) / stages)
    grouped = [
        RoutedStage(stage_id=s, pods=tuple(by_name[name] for name in pods[s * per_stage : (s + 1) * per_stage]))
        for s in range(stages)
    ]
    return table.model_copy(update={"stages": tuple(grouped)})


def requests_for(table: RoutingTable) -> list[tuple[str, int]]:
    """One request per env of the table, interleaved so that request ``i`` is on stage ``i % S``."""
    per_stage = [
        [(block.task_id, (pod_index * 7 + k) % 50) for pod_index, pod in enumerate(stage.pods)
         for block in pod.tasks for k in range(block.num_envs)]  # fmt: skip
        for stage in table.stages
    ]
    return [per_stage[i % len(per_stage)][i // len(per_stage)] for i in range(sum(map(len, per_stage)))]


_METRIC = re.compile(r"^(vecsim_pod_[a-z_]+?)(?:\{[^}]*\})? (\S+)$", re.M)
POD_COUNTERS = (
    "vecsim_pod_env_steps_total",
    "vecsim_pod_step_seconds_sum",
    "vecsim_pod_step_seconds_count",
    "vecsim_pod_physics_seconds_total",
    "vecsim_pod_render_seconds_total",
)


def scrape(urls: Sequence[str]) -> dict[str, float]:
    """Return the pods' step counters (``POD_COUNTERS``), summed over ``urls``."""
    totals = dict.fromkeys(POD_COUNTERS, 0.0)
    for url in urls:
        text = httpx.get(f"{url}/metrics", timeout=10).text
        for name, value in _METRIC.findall(text):
            if name in totals:
                totals[name] += float(value)
    return totals


@dataclasses.dataclass
class Measured:
    """One rollout: its stats and the pods' counters over it."""

    stats: RolloutStats
    pods: dict[str, float]

    @property
    def env_steps_per_s(self) -> float:
        return self.stats.env_steps_per_s


def rollout(client: StageClient, policy: nn.Module, requests: list[tuple[str, int]], horizon: int,
            device: str) -> Measured:  # fmt: skip
    """Run one EnvLoop rollout; return its stats with the pods' counters over it."""
    urls = [p.url for stage in client.routing.stages for p in stage.pods]
    before = scrape(urls)
    result = EnvLoop(client, policy, horizon=horizon, device=device, keep_obs=(), log_every_s=60).run(requests)
    after = scrape(urls)
    if result.lost:
        raise RuntimeError(f"{len(result.lost)} trajectories lost: {next(iter(result.lost.values())).reason}")
    return Measured(result.stats, {name: after[name] - before[name] for name in POD_COUNTERS})


def breakdown(measured: Sequence[Measured]) -> dict[str, float]:
    """Milliseconds per loop step (one policy call + one stage call), median over rollouts:
    policy, the client's stage call, the pods' step wall time, physics and render worker
    seconds per pod, and serving = the call beyond the pod's wall time."""
    rows = []
    for m in measured:
        stats, pods = m.stats, m.pods
        calls = pods["vecsim_pod_step_seconds_count"]
        # The first interval of each stage is its reset; the pods count steps only.
        seen: set[int] = set()
        sim_calls = []
        for what, stage, begin, end in stats.timeline:
            if what == "sim":
                if stage in seen:
                    sim_calls.append(end - begin)
                seen.add(stage)
        policy_calls = [end - begin for what, _, begin, end in stats.timeline if what == "policy"]
        pods_per_call = max(calls / max(len(sim_calls), 1), 1.0)
        pod_ms = 1000 * pods["vecsim_pod_step_seconds_sum"] / max(calls, 1)
        call_ms = 1000 * statistics.mean(sim_calls) if sim_calls else 0.0
        env_steps = max(pods["vecsim_pod_env_steps_total"], 1)
        rows.append({
            "policy_ms": 1000 * statistics.mean(policy_calls) if policy_calls else 0.0,
            "stage_call_ms": call_ms,
            "pod_step_ms": pod_ms,
            "physics_ms_per_pod": 1000 * pods["vecsim_pod_physics_seconds_total"] / max(calls, 1),
            "render_ms_per_pod": 1000 * pods["vecsim_pod_render_seconds_total"] / max(calls, 1),
            "serving_ms": max(call_ms - pod_ms, 0.0),
            "physics_ms_per_env_step": 1000 * pods["vecsim_pod_physics_seconds_total"] / env_steps,
            "render_ms_per_env_step": 1000 * pods["vecsim_pod_render_seconds_total"] / env_steps,
            "envs_per_pod_call": pods["vecsim_pod_env_steps_total"] / max(calls, 1),
            "pods_per_call": pods_per_call,
        })  # fmt: skip
    return {key: round(statistics.median(r[key] for r in rows), 2) for key in rows[0]}


class Deadline:
    """Seconds left of the run's budget; measurements stop adding rounds once it is spent."""

    def __init__(self, seconds: float) -> None:
        self.end = time.monotonic() + seconds

    def left(self) -> float:
        return self.end - time.monotonic()


def interleave(
    contenders: dict[str, Any], rounds: int, deadline: Deadline, reserve_s: float
) -> dict[str, list[Measured]]:
    """Run each contender once per round, the order rotating; stop after a round once less than
    ``reserve_s`` is left (at least one round always runs)."""
    names = list(contenders)
    out: dict[str, list[Measured]] = {name: [] for name in names}
    for r in range(rounds):
        if r and deadline.left() < reserve_s:
            log.warning("deadline near: %d of %d rounds run", r, rounds)
            break
        for name in names[r % len(names):] + names[: r % len(names)]:
            out[name].append(contenders[name]())
        log.info("round %d: %s", r + 1, {n: round(v[-1].env_steps_per_s, 1) for n, v in out.items()})
    return out


# -- the measurements ----------------------------------------------------------------------------


def measure_job(plan: Plan, job: Any, table: RoutingTable, deadline: Deadline) -> dict[str, Any]:
    """Scaling, pipelining and the time split on one running job (``table``: its routing)."""
    names = [f"sim-{i}" for i in range(plan.pods)]
    clients: dict[str, StageClient] = {}
    try:
        for p in plan.pod_counts:
            clients[f"pods={p}"] = StageClient(regroup(table, names[:p], 1), token=job.token, timeout_s=300)
        clients["stages=2"] = StageClient(regroup(table, names, 2), token=job.token, timeout_s=300)
        full = clients[f"pods={plan.pods}"]
        space, action = full.observation_space, full.action_space
        dtype = torch.bfloat16 if plan.dtype == "bfloat16" else torch.float32
        policy = VisionPolicy(space, action, device=plan.device, dtype=dtype)
        envs_all = len(requests_for(regroup(table, names, 1)))
        policy_info = {
            "name": "ResNet-18 per camera + proprio MLP + MLP head",
            "parameters_m": round(sum(p.numel() for p in policy.parameters()) / 1e6, 2),
            "dtype": plan.dtype,
            "device": plan.device,
            "forward_ms": {b: round(forward_ms(policy, space, b, 5, plan.device), 2)
                           for b in sorted({1, max(envs_all // 2, 1), envs_all})},  # fmt: skip
        }
        log.info("policy: %s", policy_info)

        def run(name: str, with_policy: nn.Module, horizon: int = plan.horizon) -> Measured:
            client = clients[name] if name != "stages=1" else full
            return rollout(client, with_policy, requests_for(client.routing), horizon, plan.device)

        for name in clients:  # warm-up: kernels picked, connections open, caches filled
            run(name, policy, horizon=min(plan.horizon, 3))
        scaling = interleave({f"pods={p}": (lambda p=p: run(f"pods={p}", policy)) for p in plan.pod_counts},
                             plan.rounds, deadline, reserve_s=0.45 * max(deadline.left(), 0))  # fmt: skip
        stages = interleave({"stages=1": lambda: run("stages=1", policy), "stages=2": lambda: run("stages=2", policy)},
                            plan.rounds, deadline, reserve_s=0.3 * max(deadline.left(), 0))  # fmt: skip
        heavy: dict[str, Any] = {}
        if plan.heavy and deadline.left() > 60:
            target_ms = breakdown(stages["stages=2"])["stage_call_ms"]
            heavy = measure_heavy(plan, len(clients["stages=2"].stage_traj_keys(0)), target_ms, space, action, dtype,
                                  run, deadline)  # fmt: skip
    finally:
        for client in clients.values():
            client.close()
    one = [m.env_steps_per_s for m in scaling["pods=1"]]
    return {
        "policy": policy_info,
        "envs_per_pod": plan.envs_per_task,
        "scaling": {
            "env_steps_per_s": {k: rate_spread([m.env_steps_per_s for m in v]) for k, v in scaling.items()},
            "fraction_of_linear": {
                k: paired_ratio([m.env_steps_per_s for m in v], [int(k.split("=")[1]) * x for x in one])
                for k, v in scaling.items()
            },
            "time_split_ms": {k: breakdown(v) for k, v in scaling.items()},
        },
        "stages": summarise_stages(stages),
        "heavy_policy": heavy,
        "per_round": {
            "scaling": {k: [m.env_steps_per_s for m in v] for k, v in scaling.items()},
            "stages": {k: [m.env_steps_per_s for m in v] for k, v in stages.items()},
        },
    }


def summarise_stages(stages: dict[str, list[Measured]]) -> dict[str, Any]:
    """Env-steps/s of 1 and 2 stages, the paired speed-up, overlap and time split."""
    return {
        "env_steps_per_s": {k: rate_spread([m.env_steps_per_s for m in v]) for k, v in stages.items()},
        "speedup_2_vs_1": paired_ratio([m.env_steps_per_s for m in stages["stages=2"]],
                                       [m.env_steps_per_s for m in stages["stages=1"]]),  # fmt: skip
        "overlap_fraction": {
            k: round(statistics.median(m.stats.overlap_fraction for m in v), 3) for k, v in stages.items()
        },
        "time_split_ms": {k: breakdown(v) for k, v in stages.items()},
    }


def measure_heavy(plan: Plan, batch: int, target_ms: float, space: spaces.Dict, action: spaces.Box,
                  dtype: torch.dtype, run: Any, deadline: Deadline) -> dict[str, Any]:  # fmt: skip
    """1 vs 2 stages with a ViT-B/16-style policy whose forward on one stage (``batch``
    observations) of the 2-stage split lasts ``target_ms``, that stage's simulation call."""
    shallow = forward_ms(VisionPolicy(space, action, encoder="vit", vit_depth=1, device=plan.device, dtype=dtype),
                         space, batch, 3, plan.device)  # fmt: skip
    deeper = forward_ms(VisionPolicy(space, action, encoder="vit", vit_depth=5, device=plan.device, dtype=dtype),
                        space, batch, 3, plan.device)  # fmt: skip
    per_block = max((deeper - shallow) / 4, 0.05)
    depth = int(min(max(round(1 + (target_ms - shallow) / per_block), 1), 96))
    policy = VisionPolicy(space, action, encoder="vit", vit_depth=depth, device=plan.device, dtype=dtype)
    achieved = forward_ms(policy, space, batch, 3, plan.device)
    log.info("heavy policy: stage call %.1f ms; ViT depth %d forwards in %.1f ms", target_ms, depth, achieved)
    stages = interleave({"stages=1": lambda: run("stages=1", policy), "stages=2": lambda: run("stages=2", policy)},
                        plan.rounds, deadline, reserve_s=60)  # fmt: skip
    return {
        "name": f"ViT-B/16-style per camera (width 768, {depth} blocks) + MLP head",
        "parameters_m": round(sum(p.numel() for p in policy.parameters()) / 1e6, 1),
        "stage_call_ms_target": target_ms,
        "depth": depth,
        "forward_ms_one_stage": round(achieved, 2),
        **summarise_stages(stages),
    }


def measure_software(plan: Plan, pins: Sequence[str], mesa: dict[str, Any], gpu_pod: dict[str, Any]) -> dict[str, Any]:
    """One pod of the same assignment as sim-0, on sim-0's core, rendering through Mesa's EGL."""
    env = {"__EGL_VENDOR_LIBRARY_FILENAMES": mesa["vendor_files"][0]}
    gl = gl_probe(env)
    if "error" in gl:
        return {"skipped": f"Mesa's EGL made no context: {gl['error']}", "gl": gl}
    config = runner_config(plan, pins, "gpu-scale-mesa", plan.tasks[:1])
    with running_job(config, env=env) as job:
        job.wait_ready(timeout=600)
        table = fetch_routing(job.controller_url, wait_ready_s=30)
        with StageClient(table, token=job.token, timeout_s=600) as client:
            policy = VisionPolicy(client.observation_space, client.action_space, device=plan.device,
                                  dtype=torch.bfloat16 if plan.dtype == "bfloat16" else torch.float32)  # fmt: skip
            measured = rollout(client, policy, requests_for(table), plan.soft_horizon, plan.device)
    split = breakdown([measured])
    return {
        "gl": gl,
        "horizon": plan.soft_horizon,
        "env_steps_per_s": round(measured.env_steps_per_s, 2),
        "time_split_ms": split,
        "gpu_pod_env_steps_per_s": gpu_pod["env_steps_per_s"],
        "gpu_pod_render_ms_per_env_step": gpu_pod["render_ms_per_env_step"],
        "render_speedup_gpu_vs_software": round(
            split["render_ms_per_env_step"] / max(gpu_pod["render_ms_per_env_step"], 1e-6), 1
        ),
    }


# -- GPU against software rendering ----------------------------------------------------------------


RENDER_PROBE_CODE = (
    "import json; from vecsim.batch_render import gl_info; info = gl_info(); "
    "info['libraries'] = sorted({l.split()[-1] for l in open('/proc/self/maps') if '.so' in l.split()[-1]}); "
    "print(json.dumps(info))"
)


def render_probe(env: dict[str, str], timeout_s: float = 120.0) -> dict[str, Any]:
    """Return GL backend/vendor/renderer/version and the GL libraries (EGL, drivers) that a child
    process with this environment plus ``env`` maps once it has a context, or ``{"error": ...}``."""
    full = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"), **env}
    try:
        done = subprocess.run([sys.executable, "-c", RENDER_PROBE_CODE], env=full, capture_output=True, text=True,
                              timeout=timeout_s)  # fmt: skip
    except subprocess.TimeoutExpired:
        return {"error": f"no GL context within {timeout_s:.0f} s"}
    if done.returncode != 0:
        return {"error": done.stderr.strip().splitlines()[-1] if done.stderr.strip() else f"exit {done.returncode}"}
    info = json.loads(done.stdout.strip().splitlines()[-1])
    info["libraries"] = [path for path in info["libraries"] if GL_LIBRARY.search(Path(path).name)]
    return info


def gpu_egl_env() -> dict[str, str]:
    """The environment of the machine's own EGL: NVIDIA's vendor file alone where there is one."""
    for path in NVIDIA_VENDOR_FILES:
        if Path(path).is_file():
            return {"__EGL_VENDOR_LIBRARY_FILENAMES": path}
    return {}


def software_egl_env() -> tuple[dict[str, str] | None, str]:
    """The environment that makes a process render through Mesa's EGL, and where that Mesa is:
    the device bundle's private copy (``VECSIM_MESA_*`` from ``mesa.sh``), else the machine's.
    None when neither is there."""
    vendor = os.environ.get("VECSIM_MESA_EGL_VENDOR")
    if vendor:
        paths = [os.environ["VECSIM_MESA_LIBRARY_PATH"], os.environ.get("LD_LIBRARY_PATH", "")]
        return {
            "__EGL_VENDOR_LIBRARY_FILENAMES": vendor,
            "LD_LIBRARY_PATH": ":".join(path for path in paths if path),
            "LIBGL_DRIVERS_PATH": os.environ["VECSIM_MESA_DRIVERS"],
        }, "the device bundle's Mesa (private prefix)"
    mesa = mesa_egl()
    if mesa["present"]:
        return {"__EGL_VENDOR_LIBRARY_FILENAMES": mesa["vendor_files"][0]}, "the machine's Mesa"
    return None, "no Mesa EGL: neither the bundle's (source mesa.sh) nor the machine's"


class ScriptedPolicy(nn.Module):
    """Open-loop actions: a slow sine per action dimension, the same for every env at a step, so
    that two rollouts from the same init states pass through the same states whatever they see."""

    def __init__(self, action_space: spaces.Box) -> None:
        super().__init__()
        low, high = np.asarray(action_space.low, np.float32), np.asarray(action_space.high, np.float32)
        bounded = np.isfinite(low) & np.isfinite(high)
        self.center = torch.from_numpy(np.where(bounded, (low + high) / 2, 0.0).astype(np.float32))
        self.scale = torch.from_numpy(np.where(bounded, (high - low) / 2, 1.0).astype(np.float32))
        self.phase = torch.arange(len(low), dtype=torch.float32) * 0.9
        self.calls = 0

    def forward(self, obs: dict[str, Any], instructions: list[str], task_ids: list[str]) -> torch.Tensor:
        """Return ``[n, action_dim]`` actions of this call's step (one call per step: one stage)."""
        action = self.center + 0.5 * self.scale * torch.sin(0.35 * self.calls + self.phase)
        self.calls += 1
        return action.expand(len(task_ids), -1).clone()


def render_rollouts(plan: Plan, pins: Sequence[str], name: str, env: dict[str, str], rounds: int,
                    deadline: Deadline) -> tuple[list[Measured], dict[str, Any]]:  # fmt: skip
    """Start a one-pod job of ``plan.tasks[0]`` with ``env`` on core ``pins[0]``; run a warm-up
    and then ``rounds`` rollouts of ``plan.horizon`` steps (fewer once the deadline nears; at
    least one); return them and the first one's observations, ``{traj_key: observations}``."""
    config = runner_config(plan, pins, f"render-{name}", plan.tasks[:1])
    with running_job(config, env=env) as job:
        job.wait_ready(timeout=max(60.0, min(600.0, deadline.left())))
        table = fetch_routing(job.controller_url, wait_ready_s=30)
        requests = requests_for(table)
        with StageClient(table, token=job.token, timeout_s=600) as client:
            space = client.action_space

            def one(horizon: int, keep: tuple[str, ...]) -> tuple[Measured, Any]:
                urls = [p.url for stage in table.stages for p in stage.pods]
                before = scrape(urls)
                loop = EnvLoop(client, ScriptedPolicy(space), horizon=horizon, keep_obs=keep, log_every_s=60)
                result = loop.run(requests, [f"env-{i}" for i in range(len(requests))])
                after = scrape(urls)
                if result.lost:
                    raise RuntimeError(f"{name}: {len(result.lost)} trajectories lost")
                return Measured(result.stats, {k: after[k] - before[k] for k in POD_COUNTERS}), result.trajectories

            one(min(2, plan.horizon), ())  # warm-up: shaders compiled, caches filled
            started = time.monotonic()
            first, trajectories = one(plan.horizon, ("images", "proprio"))
            measured = [first]
            for _ in range(rounds - 1):
                if deadline.left() < 2 * (time.monotonic() - started) + 60:
                    log.warning("%s: deadline near, %d of %d rounds run", name, len(measured), rounds)
                    break
                measured.append(one(plan.horizon, ())[0])
            log.info("%s: %s env-steps/s", name, [round(m.env_steps_per_s, 1) for m in measured])
    return measured, {key: t.observations for key, t in trajectories.items()}


def compare_images(first: dict[str, Any], second: dict[str, Any]) -> dict[str, Any]:
    """Pixel differences between two rollouts' images of the same states (every trajectory and
    step both have), per camera: mean and max absolute difference (0-255), PSNR, the share of
    pixels off by more than 8 and 32 levels in some channel; and the largest proprio difference
    (0 when both ran through the same physics states)."""
    keys = sorted(set(first) & set(second))
    steps = min(min(len(first[k]["proprio"]), len(second[k]["proprio"])) for k in keys)
    proprio = max(float((first[k]["proprio"][:steps].double() - second[k]["proprio"][:steps].double()).abs().max())
                  for k in keys)  # fmt: skip
    cameras = {}
    for camera in first[keys[0]]["images"]:
        a = np.stack([first[k]["images"][camera][:steps].numpy() for k in keys]).astype(np.int16)
        b = np.stack([second[k]["images"][camera][:steps].numpy() for k in keys]).astype(np.int16)
        diff = np.abs(a - b)
        mse = float(np.mean(diff.astype(np.float64) ** 2))
        per_frame = np.mean(diff.reshape(-1, *diff.shape[2:]).astype(np.float64) ** 2, axis=(1, 2, 3))
        worst = float(per_frame.max())
        cameras[camera] = {
            "frames": int(per_frame.size),
            "mean_abs_diff": round(float(diff.mean()), 3),
            "max_abs_diff": int(diff.max()),
            "psnr_db": round(10 * math.log10(255**2 / mse), 2) if mse > 0 else None,
            "worst_frame_psnr_db": round(10 * math.log10(255**2 / worst), 2) if worst > 0 else None,
            "pixels_off_by_more_than_8": round(float((diff.max(axis=-1) > 8).mean()), 4),
            "pixels_off_by_more_than_32": round(float((diff.max(axis=-1) > 32).mean()), 4),
            "identical": bool(diff.max() == 0),
        }
    return {"trajectories": len(keys), "steps_compared": steps, "proprio_max_abs_diff": proprio,
            "same_states": proprio == 0.0, "cameras": cameras}  # fmt: skip


def render_figures(summary: dict[str, Any], observations: dict[str, dict[str, Any]], tag: str) -> list[Path]:
    """Draw the bar chart (env-steps/s; ms per env-step split) and the frames figure (the last
    compared step of the first env, each camera: GPU, software, difference x4); return the PNGs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = {name: run for name, run in summary["renderers"].items() if "env_steps_per_s" in run}
    labels = [f"{name} EGL\n{run['gl']['renderer'].split('/')[0].split(' (')[0]}" for name, run in runs.items()]
    fig, (left, right) = plt.subplots(1, 2, figsize=(9.5, 4.0))
    rates = [run["env_steps_per_s"]["median"] for run in runs.values()]
    bars = left.bar(labels, rates, color=["tab:green", "tab:orange"][: len(rates)])
    left.bar_label(bars, fmt="%.1f", fontsize=8)
    left.set_ylabel("env-steps/s")
    left.set_title("one pod, one core", fontsize=9)
    bottom = np.zeros(len(runs))
    parts = (("physics", "physics_ms_per_env_step"), ("render", "render_ms_per_env_step"))
    for label, key in parts:
        values = np.array([run["time_split_ms"][key] for run in runs.values()])
        right.bar(labels, values, bottom=bottom, label=label)
        bottom += values
    rest = np.array([max(run["wall_ms_per_env_step"] - run["time_split_ms"]["physics_ms_per_env_step"]
                         - run["time_split_ms"]["render_ms_per_env_step"], 0) for run in runs.values()])  # fmt: skip
    bars = right.bar(labels, rest, bottom=bottom, label="rest (resets, IPC, serving)")
    right.bar_label(bars, labels=[f"{v:.1f} ms" for v in bottom + rest], fontsize=8)
    right.set_ylabel("ms per env-step")
    right.set_title("where an env-step's time goes", fontsize=9)
    right.legend(fontsize=7)
    setup = summary["setup"]
    fig.suptitle(f"{setup['task']}, {setup['size']}x{setup['size']} x {len(setup['cameras'])} cameras, "
                 f"{setup['envs']} envs: GPU against software EGL", fontsize=10)  # fmt: skip
    fig.tight_layout()
    paths = [img_dir() / f"gpu_render_compare{tag}.png"]
    fig.savefig(paths[0], dpi=110)
    plt.close(fig)

    if len(observations) == 2:
        gpu, software = observations.values()
        key = sorted(set(gpu) & set(software))[0]
        step = summary["images"]["steps_compared"] - 1
        cameras = list(gpu[key]["images"])
        fig, axes = plt.subplots(len(cameras), 3, figsize=(9, 3.1 * len(cameras)), squeeze=False)
        for row, camera in enumerate(cameras):
            a = gpu[key]["images"][camera][step].numpy()
            b = software[key]["images"][camera][step].numpy()
            diff = np.clip(np.abs(a.astype(np.int16) - b.astype(np.int16)) * 4, 0, 255).astype(np.uint8)
            for col, (image, title) in enumerate(((a, f"GPU: {camera}"), (b, f"software: {camera}"),
                                                  (diff, "|difference| x 4"))):  # fmt: skip
                axes[row][col].imshow(image)
                axes[row][col].set_title(title, fontsize=8)
                axes[row][col].axis("off")
        fig.suptitle(f"{key}, step {step}", fontsize=9)
        fig.tight_layout()
        paths.append(img_dir() / f"gpu_render_compare{tag}_frames.png")
        fig.savefig(paths[-1], dpi=100)
        plt.close(fig)
    return paths


def render_compare(args: argparse.Namespace) -> int:
    """``--render-compare``: one pinned pod of one scene, the machine's EGL then Mesa's."""
    deadline = Deadline(args.deadline)
    task = args.tasks.split(",")[0] if args.tasks else "libero_10/0"
    plan = Plan(
        tasks=(task,), size=args.size or 256, pods=1, pod_counts=(1,), envs_per_task=args.envs_per_task or 4,
        horizon=args.horizon or 10, rounds=args.rounds or 3, device="cpu", dtype="float32", heavy=False,
        soft_horizon=args.horizon or 10, deadline_s=args.deadline,
    )  # fmt: skip
    pins, trainer = split_cores(1)
    os.sched_setaffinity(0, set(trainer))
    soft_env, soft_source = software_egl_env()
    contenders: dict[str, tuple[dict[str, str] | None, str, int]] = {
        "gpu": (gpu_egl_env(), "the machine's default EGL (NVIDIA's vendor file where there is one)", plan.rounds),
        "software": (soft_env, soft_source, args.soft_rounds),
    }
    renderers: dict[str, Any] = {}
    observations: dict[str, dict[str, Any]] = {}
    for name, (env, source, rounds) in contenders.items():
        if env is None:
            renderers[name] = {"skipped": source}
            continue
        gl = render_probe(env)
        log.info("%s EGL (%s): %s", name, source, gl)
        shown = {k: v for k, v in env.items() if k != "LD_LIBRARY_PATH"}
        if "error" in gl:
            renderers[name] = {"skipped": f"no GL context: {gl['error']}", "source": source, "env": shown, "gl": gl}
            continue
        measured, observations[name] = render_rollouts(plan, pins, name, env, rounds, deadline)
        rates = [m.env_steps_per_s for m in measured]
        renderers[name] = {
            "source": source,
            "env": shown,
            "gl": gl,
            "env_steps_per_s": rate_spread(rates),
            "wall_ms_per_env_step": round(1000 / statistics.median(rates), 2),
            "time_split_ms": breakdown(measured),
            "per_round": [round(rate, 2) for rate in rates],
        }
    gpu_renderer = renderers["gpu"].get("gl", {}).get("renderer", "")
    nvidia = "NVIDIA" in gpu_renderer.upper()
    if not nvidia:
        log.warning("the default EGL renders with %r, not NVIDIA's: recording under the _cpu name", gpu_renderer)
    both = all("env_steps_per_s" in run for run in renderers.values())
    summary: dict[str, Any] = {
        "baseline": "the same pod with the machine's default EGL (the GPU's)",
        "ratio": None,
        "setup": {
            "task": task, "size": plan.size, "cameras": camera(plan)["names"], "envs": plan.envs_per_task,
            "horizon": plan.horizon, "preset": "lean", "pod_pinned_to": pins[0], "trainer_cores": trainer,
            "policy": "open-loop sine actions (the same each run, so the states are the same)",
            "rollout": "one EnvLoop.run: reset, then `horizon` steps of every env; a warm-up first",
        },  # fmt: skip
        "gpu_is_nvidia": nvidia,
        "gpu": gpu_name(),
        "renderers": renderers,
    }
    if both:
        gpu_run, soft_run = renderers["gpu"], renderers["software"]
        summary["ratio"] = round(gpu_run["env_steps_per_s"]["median"] / soft_run["env_steps_per_s"]["median"], 2)
        summary["render_ms_per_env_step_software_over_gpu"] = round(
            soft_run["time_split_ms"]["render_ms_per_env_step"]
            / max(gpu_run["time_split_ms"]["render_ms_per_env_step"], 1e-6), 1)  # fmt: skip
        summary["images"] = compare_images(observations["gpu"], observations["software"])
    tag = "" if nvidia else "_cpu"
    plots = render_figures(summary, observations, tag) if both else []
    summary["plots"] = [str(p.relative_to(img_dir().parent.parent)) for p in plots]
    path = write_result(f"bench_gpu_render_compare{tag}", summary)
    if args.copy_to:
        args.copy_to.mkdir(parents=True, exist_ok=True)
        for item in (path, *plots):
            shutil.copy(item, args.copy_to / item.name)
    return 0 if both else 2


# -- plots ---------------------------------------------------------------------------------------


def plot(result: dict[str, Any], tag: str) -> list[Path]:
    """Draw scaling, stages and the time split; return the PNG paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    scaling = result["scaling"]
    counts = sorted(int(k.split("=")[1]) for k in scaling["env_steps_per_s"])
    med = [scaling["env_steps_per_s"][f"pods={p}"]["median"] for p in counts]
    low = [m - scaling["env_steps_per_s"][f"pods={p}"]["min"] for p, m in zip(counts, med)]
    high = [scaling["env_steps_per_s"][f"pods={p}"]["max"] - m for p, m in zip(counts, med)]
    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    ax.plot(counts, [med[0] * p for p in counts], "--", color="grey", label="linear")
    target = [SCALING_TARGET * med[0] * p for p in counts]
    ax.plot(counts, target, ":", color="grey", label=f"{SCALING_TARGET} x linear")
    ax.errorbar(counts, med, yerr=[low, high], marker="o", capsize=3, label="measured (median, min-max)")
    ax.set_xticks(counts)
    ax.set_xlabel("pods (one core each)")
    ax.set_ylabel("env-steps/s")
    ax.set_title(f"{result['setup']['suite']}, {result['setup']['size']}px x 2 cameras, 1 stage")
    ax.legend(fontsize=8)
    fig.tight_layout()
    paths.append(img_dir() / f"gpu_scale{tag}_pods.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    groups = {"ResNet-18": result["stages"]}
    if result.get("heavy_policy"):
        groups[f"ViT x{result['heavy_policy']['depth']} (calibrated)"] = result["heavy_policy"]
    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    for offset, (label, data) in enumerate(groups.items()):
        values = [data["env_steps_per_s"][f"stages={s}"]["median"] for s in (1, 2)]
        bars = ax.bar(np.arange(2) + 0.4 * offset, values, 0.4, label=label)
        ax.bar_label(bars, fmt="%.0f", fontsize=7)
    ax.set_xticks(np.arange(2) + 0.2 * (len(groups) - 1), ["1 stage", "2 stages"])
    ax.set_ylabel("env-steps/s")
    ax.set_title("pipelining: all pods, the policy on the GPU")
    ax.legend(fontsize=8)
    fig.tight_layout()
    paths.append(img_dir() / f"gpu_scale{tag}_stages.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    split = scaling["time_split_ms"]
    parts = [("policy", "policy_ms"), ("physics", "physics_ms_per_pod"), ("render", "render_ms_per_pod")]
    fig, ax = plt.subplots(figsize=(6.5, 3.8))
    bottom = np.zeros(len(counts))
    for label, key in parts:
        values = np.array([split[f"pods={p}"][key] for p in counts])
        ax.bar(range(len(counts)), values, bottom=bottom, label=label)
        bottom += values
    other = np.array([max(split[f"pods={p}"]["pod_step_ms"] - split[f"pods={p}"]["physics_ms_per_pod"]
                          - split[f"pods={p}"]["render_ms_per_pod"], 0) for p in counts])  # fmt: skip
    ax.bar(range(len(counts)), other, bottom=bottom, label="pod: rest (IPC, waiting)")
    bottom += other
    serving = np.array([split[f"pods={p}"]["serving_ms"] for p in counts])
    ax.bar(range(len(counts)), serving, bottom=bottom, label="serving (HTTP, codec, slowest pod)")
    ax.set_xticks(range(len(counts)), [str(p) for p in counts])
    ax.set_xlabel("pods")
    ax.set_ylabel("ms per loop step")
    ax.set_title("where a step's time goes (physics/render: worker s per pod)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    paths.append(img_dir() / f"gpu_scale{tag}_split.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)
    return paths


# -- main ----------------------------------------------------------------------------------------


def make_plan(args: argparse.Namespace) -> Plan:
    """The run's sizes: ``--gpu`` (12 pods, LIBERO-10, 256x256) or ``--cpu-small``, then overrides."""
    from vecsim.tasks import suite_tasks

    gpu = args.gpu
    if args.tasks:
        tasks = tuple(t for t in args.tasks.split(",") if t)
    else:
        every = tuple(t.task_id for t in suite_tasks("libero_10"))
        tasks = every if gpu else every[:2]
    pods = args.pods or (12 if gpu else 2)
    counts = tuple(int(c) for c in args.pod_counts.split(",")) if args.pod_counts else (
        (1, 2, 4, 8, 12) if gpu else (1, 2))  # fmt: skip
    counts = tuple(sorted({c for c in counts if 1 <= c <= pods} | {pods}))
    cuda = torch.cuda.is_available()
    if args.dry:
        tasks, pods, counts = tasks[:1], 1, (1,)
    return Plan(
        tasks=tasks,
        size=args.size or (256 if gpu else 64),
        pods=pods,
        pod_counts=counts,
        envs_per_task=args.envs_per_task or (4 if gpu else 2),
        horizon=args.horizon or (2 if args.dry else 30 if gpu else 4),
        rounds=args.rounds or (2 if gpu else 1),
        device="cuda" if cuda else "cpu",
        dtype="bfloat16" if cuda else "float32",
        heavy=(gpu if args.heavy is None else args.heavy) and not args.dry,
        soft_horizon=args.soft_horizon,
        deadline_s=args.deadline,
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    mode = parser.add_mutually_exclusive_group(required=True)
    mode.add_argument("--gpu", action="store_true", help="12 pods, LIBERO-10, 256x256; GL must be NVIDIA's")
    mode.add_argument("--cpu-small", action="store_true", help="2 pods, 2 LIBERO-10 tasks, 64x64 (Mesa)")
    mode.add_argument("--render-compare", action="store_true",
                      help="one pod of one scene (default libero_10/0, 256x256, 4 envs): default EGL, then Mesa's")
    parser.add_argument("--dry", action="store_true", help="probe GL, Mesa, torch and a 1-pod job; fails fast")
    parser.add_argument("--tasks", help="comma-separated task ids (default: LIBERO-10; --cpu-small: its first 2)")
    parser.add_argument("--pods", type=int)
    parser.add_argument("--pod-counts", help="comma-separated pod counts to measure (default 1,2,4,8,12)")
    parser.add_argument("--envs-per-task", type=int, help="envs per pod, of its one task (default 4; --cpu-small 2)")
    parser.add_argument("--size", type=int, help="camera height and width")
    parser.add_argument("--horizon", type=int, help="steps per trajectory in each rollout")
    parser.add_argument("--rounds", type=int)
    parser.add_argument("--heavy", action=argparse.BooleanOptionalAction, default=None,
                        help="also 1 vs 2 stages with a calibrated ViT policy (default: with --gpu)")
    parser.add_argument("--soft-horizon", type=int, default=2, help="steps of the Mesa (software) pod's rollout")
    parser.add_argument("--deadline", type=float, default=480.0, help="seconds: stop adding rounds after this")
    parser.add_argument("--soft-rounds", type=int, default=1, help="--render-compare: rollouts with Mesa")
    parser.add_argument("--copy-to", type=Path, help="also copy the JSON and plots into this folder")
    args = parser.parse_args()
    setup_logging()
    os.environ.setdefault("MUJOCO_GL", "egl")
    if args.render_compare:
        return render_compare(args)
    deadline = Deadline(args.deadline)
    plan = make_plan(args)
    tag = "_dry" if args.dry else "" if args.gpu else "_cpu"

    gl = gl_probe()
    mesa = mesa_egl()
    gpu = gpu_name()
    log.info("GL: %s; Mesa EGL: %s; GPU: %s; torch %s on %s", gl, mesa, gpu, torch.__version__, plan.device)
    if args.gpu and "NVIDIA" not in gl.get("renderer", "").upper():
        log.error("GL_RENDERER is %r, not NVIDIA's: not measuring", gl.get("renderer", gl))
        return 2
    if args.gpu and plan.device != "cuda":
        log.error("torch sees no CUDA device: not measuring")
        return 2

    pins, trainer = split_cores(plan.pods)
    # Pinned before the client's threads start, so they and torch inherit it; the controller too.
    os.sched_setaffinity(0, set(trainer))
    torch.set_num_threads(len(trainer))
    torch.backends.cudnn.benchmark = True
    log.info("pods pinned to %s; trainer on cores %s", pins, trainer)

    started = time.monotonic()
    job_tasks = plan.tasks[: min(plan.pods, len(plan.tasks))]
    extra = extra_assignments(plan, "gpu-scale")
    with contextlib.ExitStack() as stack:
        job = stack.enter_context(running_job(runner_config(plan, pins, "gpu-scale", job_tasks), args.copy_to))
        extra_pods = stack.enter_context(standalone_pods(extra, cores=pins[len(job_tasks):])) if extra else []
        job.wait_ready(timeout=max(60.0, min(600.0, deadline.left())))
        table = join_extra(fetch_routing(job.controller_url, wait_ready_s=30), extra, extra_pods)
        build_s = time.monotonic() - started
        memory = psutil.virtual_memory()
        log.info("%d pods ready in %.0f s; memory used %.1f GiB", plan.pods, build_s, memory.used / 2**30)
        measured = measure_job(plan, job, table, deadline)
    one_pod = measured["scaling"]["time_split_ms"]["pods=1"]
    gpu_pod = {"env_steps_per_s": measured["scaling"]["env_steps_per_s"]["pods=1"]["median"], **one_pod}
    if not mesa["present"]:
        software: dict[str, Any] = {"skipped": "Mesa's libEGL is not on this machine (no glvnd vendor file for it)"}
    elif args.dry or deadline.left() < 60:
        software = {"skipped": "dry run" if args.dry else "no time left"}
    else:
        software = measure_software(plan, pins, mesa, gpu_pod)

    scaling = measured["scaling"]["fraction_of_linear"][f"pods={plan.pods}"]["median"]
    pipelining = measured["stages"]["speedup_2_vs_1"]["median"]
    heavy = measured["heavy_policy"].get("speedup_2_vs_1", {}).get("median") if measured["heavy_policy"] else None
    summary = {
        "baseline": "1 pod (scaling) and 1 stage (pipelining), same job, same policy",
        "ratio": scaling,
        "ratio_pipelining": pipelining,
        "ratio_pipelining_heavy_policy": heavy,
        "target": f"scaling >= {SCALING_TARGET} of linear at {plan.pods} pods; 2 stages >= {PIPELINE_TARGET}x 1 stage",
        "met": {"scaling": scaling >= SCALING_TARGET, "pipelining": pipelining >= PIPELINE_TARGET,
                "pipelining_heavy_policy": None if heavy is None else heavy >= PIPELINE_TARGET},  # fmt: skip
        "quick": not args.gpu,
        "dry": args.dry,
        "setup": {
            **dataclasses.asdict(plan),
            "suite": "libero_10" if plan.tasks[0].startswith("libero_10/") else plan.tasks[0].split("/")[0],
            "pods_pinned_to": pins,
            "trainer_cores": trainer,
            "torch": torch.__version__,
            "job_build_s": round(build_s, 1),
            "memory_used_gib_at_ready": round(memory.used / 2**30, 1),
            "extra_standalone_pods": [a.pod for a in extra],
        },
        "gpu": gpu,
        "gl": gl,
        "mesa_egl": mesa,
        "software_rendering": software,
        **{k: v for k, v in measured.items() if k != "per_round"},
    }
    plots = [] if args.dry else plot(summary, tag)
    summary["plots"] = [str(p.relative_to(img_dir().parent.parent)) for p in plots]
    path = write_result(f"bench_gpu_scale{tag}", summary, {"per_round": measured["per_round"]})
    if args.copy_to:
        args.copy_to.mkdir(parents=True, exist_ok=True)
        for item in (path, *plots):
            shutil.copy(item, args.copy_to / item.name)
    return 0


if __name__ == "__main__":
    sys.exit(main())
