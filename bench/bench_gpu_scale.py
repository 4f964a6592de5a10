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

import _thread
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
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import psutil
import torch
import torch.nn.functional as F
from _perf_common import free_port, free_port_block, paired_ratio, rate_spread, setup_logging
from common import img_dir, write_result
from gymnasium import spaces
from torch import nn

from vecsim.client import StageClient, fetch_routing
from vecsim.config import JobConfig, RoutedPod, RoutedStage, RoutingTable, TaskBlock
from vecsim.rollout import EnvLoop, RolloutStats
from vecsim.rollout.intervals import covered, intersection, merge

log = logging.getLogger("bench.gpu_scale")

PIPELINE_TARGET = 1.8  # 2 stages over 1 stage (the performance issue's target)
SCALING_TARGET = 0.8  # of linear
# How close the calibrated policy's forward pass must come to its target before the picking stops
# (within 3 picks). At 10% the picks ran 3-8% over the simulation call they stood for.
CALIBRATION_TOLERANCE = 0.04
ROBOT_CAMERAS = ("agentview", "robot0_eye_in_hand")
MESA_VENDOR_GLOBS = ("/usr/share/glvnd/egl_vendor.d/*mesa*.json", "/etc/glvnd/egl_vendor.d/*mesa*.json")
NVIDIA_VENDOR_FILES = ("/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json",
                       "/usr/share/glvnd/egl_vendor.d/10_nvidia.json")  # fmt: skip
GL_LIBRARY = re.compile(r"EGL|GLX|GLdispatch|nvidia|mesa|LLVM|_dri\.so|gallium|gbm|glapi")
MAX_EPISODE_STEPS = 520
# A batch wait that outlasts any stage call: EnvLoop then waits for every pod of the stage before
# the policy runs, the lockstep rollout from before issue 27 (the baseline that issue measured).
LOCKSTEP_WAIT_S = 300.0
STAGE_LAYOUTS = ("slices", "pods")  # vecsim.config.StageLayout's values, in --stage-layout's default order
QUICK_TASKS = ("gym/HalfCheetah-v5",)  # --quick: a cheap scene, so the run fits in about 2 min
QUICK_ENVS_PER_TASK = 4


@dataclasses.dataclass(frozen=True)
class Plan:
    """What one run builds and measures. ``tasks`` is every pod's task mix (one block per task,
    ``envs_per_task`` envs each, all in one worker process)."""

    mode: str  # "scaling", "pipeline" or "render"
    tasks: tuple[str, ...]
    size: int
    envs_per_task: int
    pods: int
    pod_counts: tuple[int, ...]
    pipeline_cores: int
    horizon: int
    service_steps: int
    rounds: int
    device: str
    dtype: str
    vit_width: int
    vit_max_depth: int
    max_memory_gib: float
    deadline_s: float
    render_preset: str = "lean"
    render_gpu: int | None = None  # the EGL device pods render on (None: the default one)
    chunk: int = 1  # actions per env per call (the policy's chunk K)
    batch_wait_s: float = 0.0  # pipeline: EnvLoop's batch_wait_s (how long it gathers a stage's answers)
    # pipeline: also each 2-stage layout with each of these batch_wait_s, side by side
    compare_batch_wait_s: tuple[float, ...] = ()
    stage_layouts: tuple[str, ...] = ("slices", "pods")  # the 2-stage layouts measured
    pods_per_core: int = 2  # pipeline: pods pinned to each of the pipeline_cores cores
    compare_stages: tuple[int, ...] = ()  # pipeline: also 'slices' in each of these stage counts (>= 3)

    @property
    def envs_per_pod(self) -> int:
        return len(self.tasks) * self.envs_per_task

    @property
    def torch_dtype(self) -> torch.dtype:
        return torch.bfloat16 if self.dtype == "bfloat16" else torch.float32


# -- the policies --------------------------------------------------------------------------------


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

    ``encoder`` is ``"resnet18"`` or ``"vit"`` (ViT-B/16-style, ``vit_depth`` blocks ``vit_width``
    wide). Runs in eval mode (batch norm uses its running statistics) in ``dtype`` on ``device``;
    the weights are made on ``device`` (a deep ViT's initialisation on the CPU would take minutes).
    """

    def __init__(
        self,
        observation_space: spaces.Dict,
        action_space: spaces.Box,
        *,
        encoder: str = "resnet18",
        vit_depth: int = 12,
        vit_width: int = 768,
        device: str = "cpu",
        dtype: torch.dtype = torch.float32,
    ) -> None:
        super().__init__()
        images = observation_space.spaces.get("images")
        self.cameras = list(images.spaces) if images is not None else []
        size = images[self.cameras[0]].shape[0] if self.cameras else 16

        def make() -> nn.Module:
            if encoder == "resnet18":
                return ResNet18Encoder()
            return ViTEncoder(size, width=vit_width, depth=vit_depth, heads=max(vit_width // 64, 1))

        with torch.device(device):
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


class GraphedPolicy:
    """A policy replayed from one CUDA graph per batch size (static input buffers), so a forward
    pass costs the calling Python thread a few copies and one replay instead of every kernel
    launch; eager where there is no CUDA. Call it as the policy: ``(obs, instructions, task_ids)``.

    With ``pad``, a batch of a size not captured runs in the graph of the smallest captured size
    above it, its rows first (the rest of the static input is left as it was; each row's output
    depends on that row alone, the policy being in eval mode), and ``padded_calls`` and
    ``padded_rows`` count what that cost. Otherwise, or above the largest captured size, a new
    size is captured when first seen (logged): seconds for a deep ViT, which without lockstep,
    where the loop's batches take many sizes, would fall inside the timed rounds."""

    def __init__(self, policy: nn.Module, space: spaces.Dict, device: str, batch_sizes: Sequence[int],
                 pad: bool = False) -> None:  # fmt: skip
        self.policy = policy
        self.space = space
        self.device = device
        self.pad = pad
        self.graphed = device.startswith("cuda")
        self.graphs: dict[int, tuple[torch.cuda.CUDAGraph, dict[str, Any], torch.Tensor]] = {}
        self.padded_calls = 0
        self.padded_rows = 0
        for batch in sorted(set(batch_sizes)):
            self.capture(batch)

    def graph_size(self, batch: int) -> int:
        """The captured size a batch of ``batch`` runs in: itself, or with ``pad`` the smallest
        captured size above it; ``batch`` itself (to be captured) where there is none."""
        if batch in self.graphs or not self.pad:
            return batch
        return min((size for size in self.graphs if size > batch), default=batch)

    def capture(self, batch: int) -> None:
        """Capture the forward pass on ``batch`` observations (a no-op without CUDA)."""
        if not self.graphed or batch in self.graphs or batch < 1:
            return
        static = dummy_obs(self.space, batch, self.device)
        blanks = [""] * batch
        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.no_grad(), torch.cuda.stream(side):
            for _ in range(3):  # warm-up off the capture: cuDNN/cuBLAS pick their kernels
                self.policy(static, blanks, blanks)
        torch.cuda.current_stream().wait_stream(side)
        graph = torch.cuda.CUDAGraph()
        with torch.no_grad(), torch.cuda.graph(graph):  # a private memory pool per graph
            out = self.policy(static, blanks, blanks)
        torch.cuda.synchronize()
        self.graphs[batch] = (graph, static, out)

    def __call__(self, obs: dict[str, Any], instructions: list[str], task_ids: list[str]) -> torch.Tensor:
        """Return ``[n, action_dim]`` float32 actions for ``n = len(task_ids)`` observations."""
        if not self.graphed:
            return self.policy(obs, instructions, task_ids)
        batch = len(task_ids)
        size = self.graph_size(batch)
        if size not in self.graphs:
            log.info("capturing the policy's CUDA graph for a batch of %d (not captured up front)", size)
            self.capture(size)
        if size != batch:
            self.padded_calls += 1
            self.padded_rows += size - batch
        graph, static, out = self.graphs[size]
        for camera, image in obs["images"].items():
            static["images"][camera][:batch].copy_(image, non_blocking=True)
        static["proprio"][:batch].copy_(obs["proprio"], non_blocking=True)
        graph.replay()
        return out[:batch].clone()

    def describe(self) -> dict[str, Any]:
        """The captured sizes and, with ``pad``, what padding cost."""
        return {"graph_sizes": sorted(self.graphs), "pad": self.pad, "padded_calls": self.padded_calls,
                "padded_rows": self.padded_rows}  # fmt: skip


def pod_multiples(per_pod: int, largest: int, extra: Sequence[int] = ()) -> list[int]:
    """Batch sizes to capture for a loop that hands the policy whole pods' answers: every multiple
    of ``per_pod`` up to ``largest``, ``largest`` itself and ``extra``."""
    step = max(per_pod, 1)
    return sorted({*range(step, largest + 1, step), largest, *extra})


def parameters_m(policy: nn.Module) -> float:
    """Return the policy's parameter count in millions."""
    return round(sum(p.numel() for p in policy.parameters()) / 1e6, 2)



# -- the machine ---------------------------------------------------------------------------------


def gl_probe(extra_env: dict[str, str] | None = None, timeout_s: float = 120.0) -> dict[str, Any]:
    """Return the GL backend/vendor/renderer/version a pod process would render with (made in a
    child process with this environment plus ``extra_env``), or ``{"error": ...}``."""
    code = "import json; from vecsim.engine.batch_render import gl_info; print(json.dumps(gl_info()))"
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


def gpu_process_table() -> list[str] | None:
    """Return nvidia-smi's table of the processes on each GPU (type G: a GL context, C: CUDA),
    which shows the GPU the pods render on; None without nvidia-smi."""
    try:
        done = subprocess.run(["nvidia-smi"], capture_output=True, text=True, timeout=20)
    except (OSError, subprocess.TimeoutExpired):
        return None
    lines = done.stdout.splitlines()
    start = next((i for i, line in enumerate(lines) if "Processes:" in line), None)
    return lines[start:] if start is not None else lines[-40:]


def _read(path: str) -> str | None:
    try:
        return Path(path).read_text().strip()
    except OSError:
        return None


def cpu_topology() -> dict[str, Any]:
    """Return the CPUs this process may use and how they sit on physical cores: per CPU its
    package, core and hyperthread siblings (``/sys/devices/system/cpu``), the number of physical
    cores, threads per core, and lscpu's model name and counts."""
    allowed = sorted(os.sched_getaffinity(0))
    cpus: dict[int, dict[str, Any]] = {}
    for cpu in allowed:
        base = f"/sys/devices/system/cpu/cpu{cpu}/topology"
        cpus[cpu] = {
            "package": _read(f"{base}/physical_package_id"),
            "core": _read(f"{base}/core_id"),
            "siblings": _read(f"{base}/thread_siblings_list"),
        }
    cores = {(c["package"], c["core"]) if c["core"] is not None else ("cpu", n) for n, c in cpus.items()}
    lscpu: dict[str, str] = {}
    with contextlib.suppress(OSError, subprocess.SubprocessError):
        out = subprocess.run(["lscpu"], capture_output=True, text=True, timeout=20).stdout
        for line in out.splitlines():
            key, _, value = line.partition(":")
            if key.strip() in ("Model name", "CPU(s)", "Thread(s) per core", "Core(s) per socket", "Socket(s)",
                               "NUMA node(s)", "Hypervisor vendor"):  # fmt: skip
                lscpu[key.strip()] = value.strip()
    return {
        "cpus": len(allowed),
        "physical_cores": len(cores),
        "threads_per_core": round(len(allowed) / max(len(cores), 1), 2),
        "per_cpu": {str(n): c for n, c in cpus.items()},
        "lscpu": lscpu,
    }


def cores_first(topology: dict[str, Any]) -> list[int]:
    """The usable CPUs ordered so that one thread of every physical core comes before any second
    thread of a core (hyperthread siblings last), each group in CPU order."""
    seen: dict[tuple[Any, Any], int] = {}
    rounds: list[tuple[int, int]] = []
    for name, cpu in sorted(topology["per_cpu"].items(), key=lambda item: int(item[0])):
        key = (cpu["package"], cpu["core"]) if cpu["core"] is not None else ("cpu", name)
        rounds.append((seen.get(key, 0), int(name)))
        seen[key] = seen.get(key, 0) + 1
    return [cpu for _, cpu in sorted(rounds)]


def split_cores(order: Sequence[int], pinned: int) -> tuple[list[str], list[int]]:
    """Return the CPU lists of ``pinned`` pod cores and the trainer's cores: the first ``pinned``
    of ``order`` and the rest; with too few CPUs the trainer keeps the first and the pods share
    the others (as on a 2-core development machine)."""
    if len(order) > pinned:
        return [str(c) for c in order[:pinned]], sorted(order[pinned:])
    rest = list(order[1:]) or list(order)
    return [str(rest[i % len(rest)]) for i in range(pinned)], [order[0]]


def memory_gib() -> float:
    """Return the machine's memory in use, GiB."""
    return round(psutil.virtual_memory().used / 2**30, 1)


# -- the job -------------------------------------------------------------------------------------


def camera(plan: Plan) -> dict[str, Any]:
    """The job's cameras: LIBERO's two (gym tasks: their one render camera), ``size`` square."""
    names = ("render",) if plan.tasks[0].startswith("gym/") else ROBOT_CAMERAS
    return {"names": list(names), "height": plan.size, "width": plan.size}


def job_config(plan: Plan, pins: Sequence[str], job_id: str, replicas: int) -> JobConfig:
    """``replicas`` pods, each serving the plan's whole task mix (``envs_per_task`` envs of each
    task) in one worker process: one job stage per pod, since the controller gives every stage
    every task. Pod ``i`` is pinned to ``pins[i % len(pins)]``."""
    return JobConfig.model_validate(
        {
            "job": {
                "job_id": job_id,
                "tasks": list(plan.tasks),
                "group_size": plan.envs_per_task,
                "num_stages": replicas,
                "pods_per_stage": 1,
                "camera": camera(plan),
                "render": plan.render_preset,
                "envs_per_worker": plan.envs_per_pod,
                "max_episode_steps": MAX_EPISODE_STEPS,
            },
            "pods": {
                "replicas": replicas,
                "base_port": free_port_block(replicas),
                "max_envs": max(64, plan.envs_per_pod),
                "cpu_affinity": list(pins),
                "render_gpus": [] if plan.render_gpu is None else [plan.render_gpu],
            },
            "controller": {
                "port": free_port(),
                "heartbeat_interval_s": 2.0,
                "heartbeat_ttl_s": 60.0,
                "reconcile_interval_s": 0.5,
            },
        }
    )


@contextlib.contextmanager
def running_job(
    config: JobConfig, keep_logs: Path | None = None, env: dict[str, str] | None = None
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


class MemoryWatch:
    """Samples the machine's memory in use every ``every_s`` in a thread while the body runs;
    once it passes ``limit_gib`` it interrupts the main thread, which the body's exit turns into
    :class:`MemoryError` (so the job is torn down before the machine runs out). Keeps the peak."""

    def __init__(self, limit_gib: float, every_s: float = 2.0) -> None:
        self.limit_gib = limit_gib
        self.every_s = every_s
        self.peak_gib = memory_gib()
        self.tripped: float | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, name="memory-watch", daemon=True)

    def _watch(self) -> None:
        while not self._stop.wait(self.every_s):
            used = memory_gib()
            self.peak_gib = max(self.peak_gib, used)
            if used > self.limit_gib:
                self.tripped = used
                _thread.interrupt_main()
                return

    def __enter__(self) -> MemoryWatch:
        self._thread.start()
        return self

    def __exit__(self, kind: type[BaseException] | None, *rest: object) -> None:
        self._stop.set()
        self._thread.join()
        if self.tripped is not None and (kind is None or issubclass(kind, KeyboardInterrupt)):
            raise MemoryError(f"{self.tripped} GiB of memory in use, above --max-memory-gib {self.limit_gib}: "
                              "run fewer pods, tasks per pod or envs")  # fmt: skip


def wait_for_job(job: Any, timeout_s: float) -> RoutingTable:
    """Wait for the job to be ready, at most ``timeout_s``, failing as soon as a pod says its
    envs failed to build (its ``/readyz`` detail) rather than at the timeout.

    Raises:
        RuntimeError: a pod's build failed (names the pod and its error).
        TimeoutError, CrashLoopError, JobRejectedError: as ``LocalJob.wait_ready``.
    """
    end = time.monotonic() + timeout_s
    while True:
        left = end - time.monotonic()
        try:
            return job.wait_ready(timeout=max(min(5.0, left), 0.5))
        except TimeoutError:
            if left <= 5.0:
                raise
        for name in job.pod_names:
            with contextlib.suppress(httpx.HTTPError, ValueError):
                answer = httpx.get(f"{job.pod_url(name)}/readyz", timeout=5)
                detail = str(answer.json().get("detail", "")) if answer.status_code == 503 else ""
                if "failed" in detail:
                    raise RuntimeError(f"{name}: {detail}")


def pod_processes(job: Any) -> dict[str, dict[str, Any]]:
    """Per pod: its processes (the server and its env workers, the forkserver included) and
    their summed resident memory, GiB."""
    out = {}
    for name in job.pod_names:
        pid = job.processes[name].pid
        tree: list[psutil.Process] = []
        with contextlib.suppress(psutil.Error, TypeError):
            root = psutil.Process(pid)
            tree = [root, *root.children(recursive=True)]
        rss = 0
        for process in tree:
            with contextlib.suppress(psutil.Error):
                rss += process.memory_info().rss
        out[name] = {"processes": len(tree), "rss_gib": round(rss / 2**30, 2)}
    return out


def regroup(table: RoutingTable, pods: Sequence[str], stages: int) -> RoutingTable:
    """The trainer's view: the named pods of the job's table, in order, in ``stages`` stages."""
    by_name = {p.pod: p for stage in table.stages for p in stage.pods}
    per_stage = math.ceil(len(pods) / stages)
    grouped = [
        RoutedStage(stage_id=s, pods=tuple(by_name[name] for name in pods[s * per_stage : (s + 1) * per_stage]))
        for s in range(stages)
    ]
    return table.model_copy(update={"stages": tuple(grouped)})


def regroup_slices(table: RoutingTable, pods: Sequence[str], stages: int) -> RoutingTable:
    """The trainer's view in the ``slices`` layout: every named pod in every stage, its envs
    alternating stage by stage in env order, as ``vecsim.plan.slice_blocks`` lays out a
    ``slices`` job's pods. The alternation runs on from one pod to the next (the k-th env of
    all the pods' envs is on stage ``k % stages``), so that stages stay equal in size when a pod
    has an odd number of envs and the pods an even one."""
    by_name = {p.pod: p for stage in table.stages for p in stage.pods}
    grouped: list[list[RoutedPod]] = [[] for _ in range(stages)]
    first = 0  # the stage of the next pod's first env
    for name in pods:
        routed = by_name[name]
        envs = [(b.task_id, e) for b in routed.tasks for e in range(b.env_start, b.env_start + b.num_envs)]
        for s in range(stages):
            mine = envs[(s - first) % stages :: stages]
            blocks = tuple(TaskBlock(task_id=task, env_start=env, num_envs=1, stage_id=s) for task, env in mine)
            grouped[s].append(routed.model_copy(update={"tasks": blocks, "num_envs": len(blocks)}))
        first = (first + len(envs)) % stages
    stage_list = tuple(RoutedStage(stage_id=s, pods=tuple(grouped[s])) for s in range(stages))
    return table.model_copy(update={"stages": stage_list})


def requests_for(table: RoutingTable, waves: int = 1) -> list[tuple[str, int]]:
    """One request per env of the table, interleaved so that request ``i`` is on stage ``i % S``;
    with ``waves`` > 1, that many such lists one after another (each wave's state ids moved on by
    7), for EnvLoop's refill: an env whose trajectory ends takes the next request of its task.

    Raises:
        ValueError: the stages differ in size (request i's stage is i % S: they must not).
    """
    sizes = [stage.num_envs for stage in table.stages]
    if len(set(sizes)) > 1:
        raise ValueError(f"stages of {sizes} envs: every stage needs as many envs (change the pods or envs per task)")
    per_stage = [
        [(block.task_id, (pod_index * 7 + k) % 50) for pod_index, pod in enumerate(stage.pods)
         for block in pod.tasks for k in range(block.num_envs)]  # fmt: skip
        for stage in table.stages
    ]
    one = [per_stage[i % len(per_stage)][i // len(per_stage)] for i in range(sum(map(len, per_stage)))]
    return [(task_id, (state_id + 7 * wave) % 50) for wave in range(waves) for task_id, state_id in one]


class TimedStageClient(StageClient):
    """A StageClient that records every request to a pod: ``(pod, op, begin, end)``
    (``time.perf_counter()``), the round trip as the client sees it (HTTP, the pod's work,
    decoding), so a stage call's per-pod times and its slowest pod are known. This bench's
    clients step ended envs on (``ended_envs="step"``): its service runs take a fixed number of
    one-action steps, the pods' work whether or not an episode ended."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        if not callable(getattr(StageClient, "_post", None)):  # the hook below would never run
            raise TypeError("StageClient has no _post(pod, op, body, keys) to time per pod any more")
        super().__init__(*args, **kwargs)
        self.pod_calls: list[tuple[str, str, float, float]] = []

    async def _post(
        self, pod: str, op: str, body: dict[str, Any], keys: list[str], extra_answer_bytes: int = 0
    ) -> dict[str, Any]:
        begin = time.perf_counter()
        try:
            return await super()._post(pod, op, body, keys, extra_answer_bytes)
        finally:
            self.pod_calls.append((pod, op, begin, time.perf_counter()))

    def take_pod_calls(self) -> list[tuple[str, str, float, float]]:
        """Return the requests recorded since the last take, and forget them."""
        calls, self.pod_calls = self.pod_calls, []
        return calls


_METRIC = re.compile(r"^(vecsim_pod_[a-z_]+?)(?:\{[^}]*\})? (\S+)$", re.M)
POD_COUNTERS = (
    "vecsim_pod_env_steps_total",
    "vecsim_pod_step_seconds_sum",
    "vecsim_pod_step_seconds_count",
    "vecsim_pod_physics_seconds_total",
    "vecsim_pod_render_seconds_total",
)


def scrape_per_pod(urls: Sequence[str]) -> dict[str, dict[str, float]]:
    """Return each pod's step counters (``POD_COUNTERS``), by URL."""
    out = {}
    for url in urls:
        totals = dict.fromkeys(POD_COUNTERS, 0.0)
        for name, value in _METRIC.findall(httpx.get(f"{url}/metrics", timeout=10).text):
            if name in totals:
                totals[name] += float(value)
        out[url] = totals
    return out


def scrape(urls: Sequence[str]) -> dict[str, float]:
    """Return the pods' step counters (``POD_COUNTERS``), summed over ``urls``."""
    per_pod = scrape_per_pod(urls)
    return {name: sum(pod[name] for pod in per_pod.values()) for name in POD_COUNTERS}


@dataclasses.dataclass
class Measured:
    """One rollout: its stats, the pods' counters over it (summed, and per pod name) and the
    client's per-pod requests."""

    stats: RolloutStats
    pods: dict[str, float]
    per_pod: dict[str, dict[str, float]] = dataclasses.field(default_factory=dict)
    pod_calls: list[tuple[str, str, float, float]] = dataclasses.field(default_factory=list)
    stage_of_pod: dict[str, int] = dataclasses.field(default_factory=dict)
    # The rollout's clock origin (``time.perf_counter()`` as ``EnvLoop.run`` was entered), by which
    # ``pod_calls`` line up with the stats' times; None where the run was not a loop.
    started: float | None = None

    @property
    def env_steps_per_s(self) -> float:
        return self.stats.env_steps_per_s


def _pod_urls(client: StageClient) -> dict[str, str]:
    return {p.pod: p.url for stage in client.routing.stages for p in stage.pods}


@contextlib.contextmanager
def counted(client: StageClient) -> Iterator[dict[str, Any]]:
    """Scrape the client's pods before and after the body; yield a dict that then holds
    ``pods`` (the counters' increase, summed), ``per_pod`` (by pod name), ``pod_calls`` (the
    client's requests, when it is a TimedStageClient) and ``stage_of_pod``."""
    urls = _pod_urls(client)
    if isinstance(client, TimedStageClient):
        client.take_pod_calls()
    before = scrape_per_pod(list(urls.values()))
    out: dict[str, Any] = {}
    yield out
    after = scrape_per_pod(list(urls.values()))
    out["per_pod"] = {pod: {k: after[url][k] - before[url][k] for k in POD_COUNTERS} for pod, url in urls.items()}
    out["pods"] = {k: sum(p[k] for p in out["per_pod"].values()) for k in POD_COUNTERS}
    out["pod_calls"] = client.take_pod_calls() if isinstance(client, TimedStageClient) else []
    out["stage_of_pod"] = {p.pod: stage.stage_id for stage in client.routing.stages for p in stage.pods}


class Chunked:
    """A policy acting in chunks of ``k`` actions: its one action per observation, repeated ``k``
    times (``[n, k, action_dim]``); ``k`` 1 is the policy itself."""

    def __init__(self, policy: Callable[..., torch.Tensor], k: int) -> None:
        self.policy, self.k = policy, k

    def __call__(self, obs: dict[str, Any], instructions: list[str], task_ids: list[str]) -> torch.Tensor:
        actions = self.policy(obs, instructions, task_ids)
        return actions if self.k == 1 else actions.unsqueeze(1).expand(-1, self.k, -1).contiguous()


def loop_rollout(
    client: StageClient,
    policy: Callable[..., torch.Tensor],
    horizon: int,
    device: str,
    batch_wait_s: float | str = 0.0,
    waves: int = 1,
) -> Measured:
    """Run one EnvLoop rollout (reset, then ``horizon`` steps of every env; with ``waves`` > 1,
    that many trajectories per env, refilled as envs free up); return its stats with the pods'
    counters and the client's per-pod requests over it.

    Raises:
        RuntimeError: trajectories were lost (a pod failed).
    """
    with counted(client) as seen:
        loop = EnvLoop(
            client, policy, horizon=horizon, device=device, keep_obs=(), log_every_s=60, batch_wait_s=batch_wait_s
        )
        started = time.perf_counter()  # EnvLoop.run takes its own a few microseconds later
        result = loop.run(requests_for(client.routing, waves))
    if result.lost:
        raise RuntimeError(f"{len(result.lost)} trajectories lost: {next(iter(result.lost.values())).reason}")
    return Measured(result.stats, **seen, started=started)


def scripted_actions(space: spaces.Box, step: int, n: int) -> np.ndarray:
    """``[n, action_dim]`` open-loop actions of step ``step``: a slow sine per dimension."""
    low, high = np.asarray(space.low, np.float32), np.asarray(space.high, np.float32)
    bounded = np.isfinite(low) & np.isfinite(high)
    center, scale = np.where(bounded, (low + high) / 2, 0.0), np.where(bounded, (high - low) / 2, 1.0)
    action = center + 0.5 * scale * np.sin(0.35 * step + 0.9 * np.arange(len(low)))
    return np.broadcast_to(action.astype(np.float32), (n, len(low)))


def scripted_chunks(space: spaces.Box, step: int, n: int, chunk: int) -> np.ndarray:
    """``scripted_actions`` of step ``step``; with ``chunk`` > 1, ``[n, chunk, action_dim]``
    (steps ``step * chunk`` onwards)."""
    if chunk == 1:
        return scripted_actions(space, step, n)
    return np.stack([scripted_actions(space, step * chunk + k, n) for k in range(chunk)], axis=1)


def service_rollout(client: StageClient, steps: int, timeout_s: float, chunk: int = 1) -> Measured:
    """The service alone, no policy: reset every env of the client's table, then ``steps`` calls
    stepping all of them with scripted actions, ``chunk`` per env and call (every stage's call
    sent at once, then all awaited). Env-steps/s count the steps' time only; the stats' timeline
    holds every call.

    Raises:
        TimeoutError: a call took longer than ``timeout_s``.
    """
    routes = client.reset_trajectories(requests_for(client.routing))
    stages = [s for s in range(client.num_stages) if client.stage_traj_keys(s)]
    action_space = client.action_space
    timeline: list[tuple[str, int, float, float]] = []
    with counted(client) as seen:
        started = time.perf_counter()
        for stage, batch in zip(stages, [c.result(timeout_s) for c in [client.reset_stage(s) for s in stages]]):
            timeline.append(("sim", stage, batch.submitted_at - started, batch.finished_at - started))
        stepping = time.perf_counter()
        for step in range(steps):
            keys = {s: client.stage_traj_keys(s) for s in stages}
            calls = {s: client.step_stage(s, dict(zip(keys[s], scripted_chunks(action_space, step, len(keys[s]), chunk))))
                     for s in stages}  # fmt: skip
            for stage, call in calls.items():
                batch = call.result(timeout_s)
                timeline.append(("sim", stage, batch.submitted_at - started, batch.finished_at - started))
                if batch.terminated.any() or batch.truncated.any():  # stepped on all the same: the pod's work
                    log.warning("stage %d: %d envs ended at step %d", stage,
                                int((batch.terminated | batch.truncated).sum()), step)
        ended = time.perf_counter()
    env_steps = steps * len(routes) * chunk
    stats = RolloutStats(num_trajectories=len(routes), env_steps=env_steps, wall_s=ended - started,
                         env_steps_per_s=env_steps / max(ended - stepping, 1e-9), simulation_s=ended - started,
                         timeline=sorted(timeline, key=lambda item: item[2]))  # fmt: skip
    return Measured(stats, **seen)


def breakdown(measured: Sequence[Measured]) -> dict[str, float]:
    """Milliseconds per loop step (one policy call + one stage call), median over rollouts:
    policy, the client's stage call, the pods' step wall time, physics and render worker
    seconds per pod, and serving = the call beyond the pod's wall time; also the env-steps per
    policy call (its rows times K)."""
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
            # The policy's batch: K actions per row, so rows per call = this / K.
            "env_steps_per_policy_call": stats.env_steps / max(len(policy_calls), 1),
        })  # fmt: skip
    return {key: round(statistics.median(r[key] for r in rows), 2) for key in rows[0]}


def slowest_pod(measured: Sequence[Measured]) -> dict[str, Any]:
    """What waiting for the slowest pod costs. Per stage call (steps only): the client's round
    trips to the call's pods, their mean and the slowest one, medians over every call of the
    rollouts; ``wait_for_slowest_ms`` = slowest - mean. Also how often each pod was the slowest,
    and each pod's mean step wall time by its own ``/metrics`` (no HTTP)."""
    means, worsts, waits = [], [], []
    slowest_counts: dict[str, int] = {}
    sums: dict[str, list[float]] = {}
    for m in measured:
        by_pod: dict[str, list[float]] = {}
        for pod, op, begin, end in m.pod_calls:
            if op == "step":
                by_pod.setdefault(pod, []).append(end - begin)
        stages: dict[int, list[str]] = {}
        for pod in by_pod:
            stages.setdefault(m.stage_of_pod.get(pod, 0), []).append(pod)
        for pods in stages.values():
            for k in range(min(len(by_pod[p]) for p in pods)):
                times = {p: by_pod[p][k] for p in pods}
                mean, worst = statistics.mean(times.values()), max(times.values())
                means.append(mean)
                worsts.append(worst)
                waits.append(worst - mean)
                name = max(times, key=lambda p: times[p])
                slowest_counts[name] = slowest_counts.get(name, 0) + 1
        for pod, counters in m.per_pod.items():
            total = sums.setdefault(pod, [0.0, 0.0])
            total[0] += counters["vecsim_pod_step_seconds_sum"]
            total[1] += counters["vecsim_pod_step_seconds_count"]
    step_ms = {pod: round(1000 * s / c, 2) for pod, (s, c) in sums.items() if c > 0}

    def ms(values: list[float]) -> float | None:
        return round(1000 * statistics.median(values), 2) if values else None

    return {
        "calls": len(means),
        "pod_round_trip_mean_ms": ms(means),
        "pod_round_trip_slowest_ms": ms(worsts),
        "wait_for_slowest_ms": ms(waits),
        "slowest_pod_counts": dict(sorted(slowest_counts.items(), key=lambda item: -item[1])),
        "pod_step_ms_by_pod": step_ms,
        "pod_step_ms_spread": (
            {"min": min(step_ms.values()), "mean": round(statistics.mean(step_ms.values()), 2),
             "max": max(step_ms.values())} if step_ms else {}  # fmt: skip
        ),
    }


class Deadline:
    """Seconds left of the run's budget; measurements stop adding rounds once it is spent."""

    def __init__(self, seconds: float) -> None:
        self.end = time.monotonic() + seconds

    def left(self) -> float:
        return self.end - time.monotonic()


def interleave(contenders: dict[str, Callable[[], Measured]], rounds: int, deadline: Deadline,
               reserve_s: float) -> dict[str, list[Measured]]:  # fmt: skip
    """Run each contender once per round, the order rotating; start another round only while
    the last round's duration plus ``reserve_s`` fits in what is left (one round always runs)."""
    names = list(contenders)
    out: dict[str, list[Measured]] = {name: [] for name in names}
    last_s = 0.0
    for r in range(rounds):
        if r and deadline.left() < 1.1 * last_s + reserve_s:
            log.warning("deadline near (%.0f s left, a round takes %.0f s): %d of %d rounds run",
                        deadline.left(), last_s, r, rounds)  # fmt: skip
            break
        began = time.monotonic()
        for name in names[r % len(names):] + names[: r % len(names)]:
            out[name].append(contenders[name]())
        last_s = time.monotonic() - began
        log.info("round %d (%.0f s): %s", r + 1, last_s, {n: round(v[-1].env_steps_per_s, 1) for n, v in out.items()})
    return out


def core_overlap(runs: Sequence[Measured], core_of: Mapping[str, int]) -> float:
    """The share of the pods' time in flight (the client's step and reset calls, summed over the
    pods) during which another pod pinned to the same core had a call in flight too, median over
    the rollouts: 0 when the pods of a core take turns, 1 when they always simulate together."""
    shares = []
    for m in runs:
        by_pod: dict[str, list[tuple[float, float]]] = {}
        for pod, _, begin, end in m.pod_calls:
            by_pod.setdefault(pod, []).append((begin, end))
        flights = {pod: merge(intervals) for pod, intervals in by_pod.items()}
        busy = together = 0.0
        for pod, own in flights.items():
            others = merge(i for p, f in flights.items() if p != pod and core_of.get(p) == core_of.get(pod) for i in f)
            busy += covered(own)
            together += intersection(own, others)
        shares.append(together / busy if busy > 0 else 0.0)
    return round(statistics.median(shares), 3) if shares else 0.0


def handoff(runs: Sequence[Measured]) -> dict[str, float | None]:
    """The trainer's side of a stage's turn, ms, medians over the rollouts' step calls (each a
    lane's call: its ``submitted_at`` to ``finished_at``, the client's whole call):

    - ``send``: from the end of the policy call that made a step call's actions to the call
      being submitted (the loop handing it to the client);
    - ``last_answer_to_policy``: from the last answer a policy call takes being in (its call
      finished) to that policy call starting;
    - ``last_answer_to_policy_idle``: the part of that spent outside any other stage's policy
      call: what waking, taking the answers and starting the policy cost, not the GPU being busy;
    - ``send_spread``: from the first to the last step call a policy call's actions went out in;
    - ``call_beyond_request``: a step call's time beyond its HTTP request to the pod (the
      client's work before and after it, and its wait to be run on the client's loop).
    """
    sends: list[float] = []
    handoffs: list[float] = []
    idles: list[float] = []
    spreads: list[float] = []
    beyond: list[float] = []
    for m in runs:
        requests: dict[str, list[tuple[float, float]]] = {}
        if m.started is not None:
            for pod, op, begin, end in m.pod_calls:
                if op == "step":
                    requests.setdefault(pod, []).append((begin - m.started, end - m.started))
        policies: dict[int, list[tuple[float, float]]] = {}
        for what, stage, begin, end in m.stats.timeline:
            if what == "policy":
                policies.setdefault(stage, []).append((begin, end))
        for calls in policies.values():
            calls.sort()
        last_in: dict[tuple[int, int], float] = {}  # (stage, policy call) -> its last answer's end
        sent: dict[tuple[int, float], list[float]] = {}  # (stage, the policy call's end) -> submit times
        for stage, pod, submitted, finished, _resets, steps in m.stats.pod_calls:
            if not steps:
                continue
            inside = [e - b for b, e in requests.get(pod, ()) if submitted <= b and e <= finished]
            if len(inside) == 1:
                beyond.append(finished - submitted - inside[0])
            own = policies.get(stage, [])
            if not own:
                continue
            made = [end for _, end in own if end <= submitted]
            if made:
                sends.append(submitted - made[-1])
                sent.setdefault((stage, made[-1]), []).append(submitted)
            taker = next((j for j, (begin, _) in enumerate(own) if begin >= finished), None)
            if taker is not None:
                last_in[(stage, taker)] = max(last_in.get((stage, taker), finished), finished)
        spreads.extend(max(times) - min(times) for times in sent.values())
        others = {stage: merge(call for s, calls in policies.items() if s != stage for call in calls) for stage in policies}
        for (stage, j), landed in last_in.items():
            begin = policies[stage][j][0]
            handoffs.append(begin - landed)
            idles.append(begin - landed - intersection([(landed, begin)], others[stage]))

    def ms(values: list[float]) -> float | None:
        return round(1000 * statistics.median(values), 2) if values else None

    return {"send": ms(sends), "send_spread": ms(spreads), "call_beyond_request": ms(beyond),
            "last_answer_to_policy": ms(handoffs), "last_answer_to_policy_idle": ms(idles)}  # fmt: skip


def thread_share(runs: Sequence[Measured]) -> dict[str, float]:
    """Where the trainer's thread spent a rollout's wall time, as fractions, medians over the
    rollouts: in policy calls (the inputs' preparation and the forward pass), waiting
    for a pod's answer, and on the rest of the loop (taking answers, buffering, sending actions)."""
    shares = []
    for m in runs:
        wall = max(m.stats.wall_s, 1e-9)
        policy, wait = m.stats.policy_s / wall, m.stats.wait_s / wall
        shares.append({"policy": policy, "wait": wait, "loop": max(1.0 - policy - wait, 0.0)})
    return {key: round(statistics.median(s[key] for s in shares), 3) for key in ("policy", "wait", "loop")}


def summarise(runs: Sequence[Measured]) -> dict[str, Any]:
    """Env-steps/s of one contender's rounds, its time split and the slowest-pod figures."""
    out = {
        "env_steps_per_s": rate_spread([m.env_steps_per_s for m in runs]),
        "time_split_ms": breakdown(runs),
        "slowest_pod": slowest_pod(runs),
        "overlap_fraction": round(statistics.median(m.stats.overlap_fraction for m in runs), 3),
        "thread_share": thread_share(runs),
        "handoff_ms": handoff(runs),
        "trajectories": int(statistics.median(m.stats.num_trajectories for m in runs)),
    }
    # With refill, how many trajectories each pod started (resets), in the first round: a pod on a
    # faster core takes more.
    started: dict[str, int] = {}
    for _, pod, _, _, resets, _ in runs[0].stats.pod_calls:
        started[pod] = started.get(pod, 0) + resets
    if started:
        out["trajectories_per_pod"] = {"min": min(started.values()), "max": max(started.values())}
    return out


# -- scaling -------------------------------------------------------------------------------------


def measure_scaling(plan: Plan, job: Any, table: RoutingTable, deadline: Deadline) -> dict[str, Any]:
    """For each pod count P, the first P pods in one stage: the service alone (scripted actions)
    and the EnvLoop with the graphed ResNet-18 policy; and the EnvLoop with a stage per pod (P
    stages of one pod: a slow pod holds up its own stage only). Interleaved rounds."""
    names = [f"sim-{i}" for i in range(plan.pods)]
    clients: dict[int, TimedStageClient] = {}
    per_pod: dict[int, TimedStageClient] = {}
    try:
        for p in plan.pod_counts:
            clients[p] = TimedStageClient(regroup(table, names[:p], 1), token=job.token, timeout_s=300, ended_envs="step")
            if p > 1:
                per_pod[p] = TimedStageClient(regroup(table, names[:p], p), token=job.token, timeout_s=300, ended_envs="step")
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
            "forward_ms": {str(b): round(forward_ms(graphed, space, b, 5, plan.device), 2)
                           for b in sorted(set(sizes.values()))},  # fmt: skip
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
                    c, graphed, plan.horizon, plan.device)
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
                    [m.env_steps_per_s for m in rounds], [p * x for x in one])
        result[kind] = section
    result["per_round"] = {name: [round(m.env_steps_per_s, 2) for m in v] for name, v in runs.items()}
    return result


# -- pipelining ----------------------------------------------------------------------------------


def calibrate_vit(plan: Plan, space: spaces.Dict, action: spaces.Box, batch: int, target_ms: float,
                  batch_sizes: Sequence[int], pad_sizes: Sequence[int] = ()) -> tuple[GraphedPolicy, dict[str, Any]]:  # fmt: skip
    """Return a ViT policy, graphed for ``batch_sizes``, whose forward pass on ``batch``
    observations lasts about ``target_ms``, and what the calibration found. The depth is
    extrapolated from two shallow ViTs, then corrected once by the time the first pick takes;
    never above ``plan.vit_max_depth``. With ``pad_sizes``, the picked policy is then also
    captured for those sizes and pads a batch of any other size to the next captured one."""

    def build(depth: int, sizes: Sequence[int]) -> GraphedPolicy:
        policy = VisionPolicy(space, action, encoder="vit", vit_depth=depth, vit_width=plan.vit_width,
                              device=plan.device, dtype=plan.torch_dtype)  # fmt: skip
        return GraphedPolicy(policy, space, plan.device, sizes)

    def release() -> None:
        if plan.device.startswith("cuda"):
            torch.cuda.synchronize()
            torch.cuda.empty_cache()

    def timed(depth: int) -> float:
        probe = build(depth, [batch])
        ms = forward_ms(probe, space, batch, 3, plan.device)
        del probe
        release()
        return ms

    low_depth, high_depth = 1, min(5, max(plan.vit_max_depth, 2))
    low, high = timed(low_depth), timed(high_depth)
    per_block = max((high - low) / (high_depth - low_depth), 1e-3)
    wanted = round(low_depth + (target_ms - low) / per_block)
    picks: list[tuple[int, float]] = []
    for attempt in range(3):  # pick, time, and correct by the time taken (about linear in depth)
        depth = int(min(max(wanted, 1), plan.vit_max_depth))
        graphed = build(depth, batch_sizes)
        achieved = {str(b): round(forward_ms(graphed, space, b, 3, plan.device), 2) for b in sorted(set(batch_sizes))}
        took = achieved[str(batch)]
        picks.append((depth, took))
        wanted = round(depth * target_ms / max(took, 1e-3))
        if abs(took - target_ms) <= CALIBRATION_TOLERANCE * target_ms or attempt == 2:
            break
        if int(min(max(wanted, 1), plan.vit_max_depth)) == depth:
            break  # the cap (or depth 1) stops it here
        graphed = None  # type: ignore[assignment]  # its weights and graphs go before the next build
        release()
    info = {
        "name": f"ViT-B/16-style per camera (width {plan.vit_width}, {depth} blocks) + proprio MLP + MLP head",
        "parameters_m": parameters_m(graphed.policy),
        "dtype": plan.dtype,
        "device": plan.device,
        "cuda_graphs": graphed.graphed,
        "target_ms": round(target_ms, 2),
        "target_batch": batch,
        "depth": depth,
        "depth_wanted": wanted,
        "capped": wanted > plan.vit_max_depth,
        "ms_per_block": round(per_block, 3),
        "picks_depth_ms": picks,
        "forward_ms": achieved,
    }
    if pad_sizes:
        started = time.perf_counter()
        graphed.pad = True
        for size in pad_sizes:
            graphed.capture(size)
        info["pad_capture_s"] = round(time.perf_counter() - started, 1)
    if plan.device.startswith("cuda"):
        info["gpu_memory_gib"] = round(torch.cuda.max_memory_allocated() / 2**30, 1)
    log.info("calibrated policy: %s", info)
    return graphed, info


WARMUP_HORIZON = 32  # pipeline: actions per trajectory in each contender's warm-up rollout


def waiting(layout: str, wait_s: float, stages: int = 2) -> str:
    """The name of a contender of ``stages`` stages run with a ``--compare-batch-wait-s`` value."""
    return f"{layout}/stages={stages}/batch_wait={wait_s:g}s"


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
        service = interleave({"service/stages=1": lambda: service_rollout(one, plan.service_steps, 300, k),
                              "service/half": lambda: service_rollout(clients["half"], plan.service_steps, 300, k)},
                             plan.rounds, deadline, reserve_s=0.6 * max(deadline.left(), 0))  # fmt: skip
        target_ms = breakdown(service["service/stages=1"])["stage_call_ms"]
        batch = one.routing.num_envs
        stage_sizes = sorted({stage.num_envs for layout in plan.stage_layouts for stage in two_stages[layout].stages}
                             | {stage.num_envs for routing in more_stages.values() for stage in routing.stages})
        space, action = one.observation_space, one.action_space
        # Without lockstep the loop's policy calls take batches of many sizes, mostly whole lanes'
        # answers (a lane: one stage's envs on one pod); a size met first inside a timed round would
        # be captured there (seconds for this ViT). So every multiple of a lane's envs is captured
        # up front and other sizes padded. More stages' lanes are not (a pod's envs split three
        # ways leave lanes of one env); their whole stages are, and part stages are padded.
        lane = math.gcd(*(p.num_envs for layout in plan.stage_layouts for stage in two_stages[layout].stages
                          for p in stage.pods), plan.envs_per_pod)  # fmt: skip
        graphed, policy_info = calibrate_vit(plan, space, action, batch, target_ms, [batch, *stage_sizes],
                                             pod_multiples(lane, batch))  # fmt: skip
        policy = Chunked(graphed, k)
        # Each contender: (its client, its batch_wait_s); for each compare_batch_wait_s, each
        # 2-stage layout again, waiting that long for more of a stage's pods before the policy runs.
        contenders = {name: (name, plan.batch_wait_s)
                      for name in ["stages=1", *(f"{layout}/stages=2" for layout in plan.stage_layouts)]}  # fmt: skip
        contenders.update({waiting(layout, wait): (f"{layout}/stages=2", wait)
                           for wait in plan.compare_batch_wait_s for layout in plan.stage_layouts})  # fmt: skip
        for n in plan.compare_stages:
            contenders[f"slices/stages={n}"] = (f"slices/stages={n}", plan.batch_wait_s)
            contenders.update({waiting("slices", wait, n): (f"slices/stages={n}", wait)
                               for wait in plan.compare_batch_wait_s})  # fmt: skip
        # Warm-up: a short rollout per contender (connections, the pods' first renders); the
        # policy's batch sizes are all captured already.
        for client_name, wait in contenders.values():
            loop_rollout(clients[client_name], policy, min(plan.horizon, WARMUP_HORIZON), plan.device, wait)
        log.info("warm-up done, %.0f s left", deadline.left())
        runs = {name: (lambda c=clients[client_name], w=wait: loop_rollout(c, policy, plan.horizon, plan.device, w))
                for name, (client_name, wait) in contenders.items()}  # fmt: skip
        # One stage in lockstep: the whole stage's answers before each policy call.
        runs["stages=1/lockstep"] = lambda: loop_rollout(one, policy, plan.horizon, plan.device, LOCKSTEP_WAIT_S)
        loops = interleave(runs, plan.rounds, deadline, reserve_s=20)
    finally:
        for client in clients.values():
            client.close()
    rates = {name: [m.env_steps_per_s for m in runs] for name, runs in loops.items()}
    compared = [{
        "batch_wait_s": wait,
        # Over the same layout at --batch-wait-s (default 0: no wait).
        "speedup_over_same_layout": {
            layout: paired_ratio(rates[waiting(layout, wait)], rates[f"{layout}/stages=2"]) for layout in plan.stage_layouts},
        "speedup_2_vs_1_lockstep": {
            layout: paired_ratio(rates[waiting(layout, wait)], rates["stages=1/lockstep"]) for layout in plan.stage_layouts},
    } for wait in plan.compare_batch_wait_s]  # fmt: skip
    return {
        **({"batch_wait": compared} if compared else {}),
        "policy": {**policy_info, "chunk": plan.chunk, "graphs": graphed.describe()},
        "service": {name.split("/")[1]: summarise(runs) for name, runs in service.items()},
        # Pods i and i+C share core i: how often they simulate at once (0 with a pod a core).
        "loop": {name: {**summarise(runs), "core_overlap": core_overlap(runs, core_of)} for name, runs in loops.items()},
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
            for name, values in rates.items() if name != "stages=1/lockstep"
        },
        "stage_envs": {
            **{layout: [[p.num_envs for p in stage.pods] for stage in two_stages[layout].stages]
               for layout in plan.stage_layouts},
            **{f"slices/stages={n}": [[p.num_envs for p in stage.pods] for stage in routing.stages]
               for n, routing in more_stages.items()},
        },
        "per_round": {name: [round(m.env_steps_per_s, 2) for m in runs] for name, runs in {**service, **loops}.items()},
    }


# -- GPU against software rendering ----------------------------------------------------------------


RENDER_PROBE_CODE = (
    "import json; from vecsim.engine.batch_render import gl_info; info = gl_info(); "
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
    config = job_config(plan, pins, f"render-{name}", 1)
    with running_job(config, env=env) as job:
        table = wait_for_job(job, max(60.0, min(600.0, deadline.left())))
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
        mode="render", tasks=(task,), size=args.size or 256, envs_per_task=args.envs_per_task or 4, pods=1,
        pod_counts=(1,), pipeline_cores=0, horizon=args.horizon or 10, service_steps=0, rounds=args.rounds or 3,
        device="cpu", dtype="float32", vit_width=768, vit_max_depth=0, max_memory_gib=args.max_memory_gib,
        deadline_s=args.deadline,
    )  # fmt: skip
    pins, trainer = split_cores(cores_first(cpu_topology()), 1)
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


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_scaling(summary: dict[str, Any], tag: str) -> list[Path]:
    """Env-steps/s against pods (service alone and the loop, each against its linear), and
    where a step's time goes; return the PNG paths."""
    plt = _pyplot()
    setup = summary["setup"]
    counts = list(setup["pod_counts"])
    fig, ax = plt.subplots(figsize=(6.0, 4.0))
    for kind, color, label in (("service", "tab:blue", "service alone (scripted actions)"),
                               ("loop", "tab:orange", "EnvLoop + ResNet-18 (graphed), 1 stage"),
                               ("loop_per_pod", "tab:green", "EnvLoop + ResNet-18, a stage per pod")):  # fmt: skip
        if kind not in summary:
            continue
        rates = [summary[kind][f"pods={p}"]["env_steps_per_s"] for p in counts]
        med = [r["median"] for r in rates]
        ax.errorbar(counts, med, yerr=[[m - r["min"] for m, r in zip(med, rates)], [r["max"] - m for m, r in
                    zip(med, rates)]], marker="o", capsize=3, color=color, label=label)  # fmt: skip
        if counts[0] == 1 and kind != "loop_per_pod":  # its 1-pod figure is the loop's
            ax.plot(counts, [med[0] * p for p in counts], "--", color=color, alpha=0.5, label=f"linear ({kind})")
    physical = summary["topology"]["physical_cores"]
    if counts[-1] > physical:
        ax.axvline(physical + 0.5, color="grey", linestyle=":", label=f"{physical} physical cores")
    ax.set_xticks(counts)
    ax.set_xlabel("pods (one CPU each)")
    ax.set_ylabel("env-steps/s")
    ax.set_title(f"{setup['suite']}: {setup['envs_per_pod']} envs/pod ({len(setup['tasks'])} tasks), "
                 f"{setup['size']}px x {len(camera_names(setup))} cameras", fontsize=9)  # fmt: skip
    ax.legend(fontsize=7)
    fig.tight_layout()
    paths = [img_dir() / f"gpu_scale{tag}_pods.png"]
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    fig, (left, right) = plt.subplots(1, 2, figsize=(10.0, 4.0))
    x = np.arange(len(counts))
    split = [summary["loop"][f"pods={p}"]["time_split_ms"] for p in counts]
    bottom = np.zeros(len(counts))
    for label, values in (
        ("policy", [s["policy_ms"] for s in split]),
        ("physics", [s["physics_ms_per_pod"] for s in split]),
        ("render", [s["render_ms_per_pod"] for s in split]),
        ("pod: rest (IPC)", [max(s["pod_step_ms"] - s["physics_ms_per_pod"] - s["render_ms_per_pod"], 0)
                             for s in split]),
        ("serving (HTTP, codec, slowest pod)", [s["serving_ms"] for s in split]),
    ):
        left.bar(x, values, bottom=bottom, label=label)
        bottom += np.array(values)
    left.set_xticks(x, [str(p) for p in counts])
    left.set_xlabel("pods")
    left.set_ylabel("ms per loop step")
    left.set_title("EnvLoop: where a step goes (physics/render: worker s per pod)", fontsize=9)
    left.legend(fontsize=7)
    service = [summary["service"][f"pods={p}"] for p in counts]
    width = 0.27
    for offset, (label, values) in enumerate((
        ("pod step (its /metrics)", [s["time_split_ms"]["pod_step_ms"] for s in service]),
        ("round trip, mean pod", [s["slowest_pod"]["pod_round_trip_mean_ms"] or 0 for s in service]),
        ("round trip, slowest pod", [s["slowest_pod"]["pod_round_trip_slowest_ms"] or 0 for s in service]),
    )):  # fmt: skip
        right.bar(x + (offset - 1) * width, values, width, label=label)
    right.plot(x, [s["time_split_ms"]["stage_call_ms"] for s in service], "k_", markersize=18, label="stage call")
    right.set_xticks(x, [str(p) for p in counts])
    right.set_xlabel("pods")
    right.set_ylabel("ms per call")
    right.set_title("service alone: a call waits for its slowest pod", fontsize=9)
    right.legend(fontsize=7)
    fig.tight_layout()
    paths.append(img_dir() / f"gpu_scale{tag}_split.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)
    return paths


def plot_pipeline(summary: dict[str, Any], tag: str) -> list[Path]:
    """1 against 2 stages (env-steps/s) and the per-call times behind them; return the PNG path."""
    plt = _pyplot()
    loop, policy = summary["loop"], summary["policy"]
    fig, (left, right) = plt.subplots(1, 2, figsize=(10.0 + 1.5 * len(summary.get("batch_wait", [])), 4.0))
    layouts = list(summary["speedup_2_vs_1"])
    lockstep = ["stages=1/lockstep"] if "stages=1/lockstep" in loop else []
    waits = [entry["batch_wait_s"] for entry in summary.get("batch_wait", [])]  # --compare-batch-wait-s
    names = [*lockstep, "stages=1", *(f"{layout}/stages=2" for layout in layouts)]
    labels = [*(["1 stage\n(lockstep)"] if lockstep else []), "1 stage\n(all pods)",
              *(f"2 stages\n({layout})" for layout in layouts)]  # fmt: skip
    for wait in waits:
        names += [waiting(layout, wait) for layout in layouts]
        labels += [f"2 stages\n({layout},\nwait {wait:g} s)" for layout in layouts]
    base = len(names) - len(waits) * len(layouts)
    more = summary["setup"].get("compare_stages", [])  # --compare-stages: slices in n stages
    for n in more:
        names += [f"slices/stages={n}", *(waiting("slices", wait, n) for wait in waits)]
        labels += [f"{n} stages\n(slices)", *(f"{n} stages\n(slices,\nwait {wait:g} s)" for wait in waits)]
    rates = [loop[name]["env_steps_per_s"]["median"] for name in names]
    extra = ["tab:red", "tab:purple", "tab:brown", "tab:pink", "tab:olive", "tab:cyan"]
    colours = ["tab:gray", "tab:blue", "tab:orange", "tab:green"][-base:] + [
        extra[i % len(extra)] for i in range(len(names) - base)]  # fmt: skip
    bars = left.bar(labels, rates, color=colours)
    left.bar_label(bars, fmt="%.1f", fontsize=8)
    left.tick_params(axis="x", labelsize=7 if len(names) > 4 else 10)
    left.set_ylabel("env-steps/s")
    ratios = ", ".join(f"{layout} {r['median']:.2f}x" for layout, r in summary["speedup_2_vs_1"].items())
    if lockstep:
        over = summary["speedup_2_vs_1_lockstep"]
        ratios += "\n(over 1 stage in lockstep: " + ", ".join(f"{layout} {r['median']:.2f}x" for layout, r in over.items()) + ")"
    left.set_title(f"pipelining at K={policy.get('chunk', 1)}: {ratios} (target {PIPELINE_TARGET}x)", fontsize=9)
    x = np.arange(len(names))
    width = 0.27
    sizes = summary["setup"]["stage_envs_by_layout"]
    alone = [policy["forward_ms"].get(str(policy["target_batch"]), 0)] * (1 + len(lockstep)) + [
        statistics.mean(policy["forward_ms"].get(str(sum(stage)), 0) for stage in sizes[layout])
        for layout in [*layouts * (1 + len(waits)),
                       *(f"slices/stages={n}" for n in more for _ in range(1 + len(waits)))]  # fmt: skip
    ]
    for offset, (label, values) in enumerate((
        ("stage call (loop)", [loop[name]["time_split_ms"]["stage_call_ms"] for name in names]),
        ("policy per call (loop)", [loop[name]["time_split_ms"]["policy_ms"] for name in names]),
        ("policy alone" + (" (CUDA graph)" if policy["cuda_graphs"] else " (eager)"), alone),
    )):  # fmt: skip
        right.bar(x + (offset - 1) * width, values, width, label=label)
    right.set_xticks(x, labels if waits else [label.replace("\n", " ") for label in labels], fontsize=7)
    right.set_ylabel("ms")
    right.set_title(f"{policy['name'].split(' + ')[0]}", fontsize=8)
    right.legend(fontsize=7)
    fig.tight_layout()
    path = img_dir() / f"gpu_scale{tag}_stages.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return [path]


def camera_names(setup: dict[str, Any]) -> list[str]:
    """The cameras of a run's setup."""
    return list(setup["camera"]["names"])


# -- main ----------------------------------------------------------------------------------------


def make_plan(args: argparse.Namespace) -> Plan:
    """The run's sizes: ``--gpu``, ``--cpu-small`` or ``--quick`` defaults, ``--dry`` shrinks,
    then overrides."""
    from vecsim.engine.tasks import suite_tasks

    gpu, dry, quick = args.gpu, args.dry, args.quick
    if args.tasks:
        tasks = tuple(t for t in args.tasks.split(",") if t)
    elif quick:
        tasks = QUICK_TASKS
    else:
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
        given = tuple(int(c) for c in args.pod_counts.split(",")) if args.pod_counts else (
            (1, 2, 4, 8, 12) if gpu else (1, 2))  # fmt: skip
        counts = tuple(sorted({c for c in given if 1 <= c <= pods} | {1, pods}))
    cuda = torch.cuda.is_available()
    max_depth = args.vit_max_depth or (512 if gpu else 256)
    chunk = args.chunk
    if chunk < 1:
        raise SystemExit(f"--chunk must be at least 1, got {chunk}")
    layouts = parse_stage_layouts(args.stage_layout)
    # The horizon counts actions: by default as many calls at K as at K=1.
    horizon = 2 * chunk if dry else args.horizon or (30 if gpu else 6 if quick else 3) * chunk
    plan = Plan(
        mode=args.only,
        tasks=tasks[:per_pod],
        size=args.size or (256 if gpu else 16 if quick else 64),
        envs_per_task=args.envs_per_task or (QUICK_ENVS_PER_TASK if quick else 1),
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
    envs = plan.pods * plan.envs_per_pod
    for n in plan.compare_stages:
        # The loop gives request i to stage i % n: the stages must be of one size.
        if envs % n:
            raise SystemExit(f"--compare-stages {n}: the job's {envs} envs do not split into {n} equal stages "
                             "(change --tasks-per-pod, --envs-per-task or the pods)")  # fmt: skip
    return plan


def parse_stage_layouts(text: str) -> tuple[str, ...]:
    """``--stage-layout``'s comma-separated layouts, in order, each once.

    Raises:
        SystemExit: none given, or one that is not in ``STAGE_LAYOUTS``.
    """
    layouts = tuple(dict.fromkeys(x for x in text.split(",") if x))
    if not layouts or set(layouts) - set(STAGE_LAYOUTS):
        raise SystemExit(f"--stage-layout: a comma-separated list of {list(STAGE_LAYOUTS)}, got {text!r}")
    return layouts


def physical_core_of(topology: dict[str, Any], cpu: str) -> str:
    """``package:core`` of a CPU (the CPU itself where the topology does not say)."""
    info = topology["per_cpu"].get(cpu, {})
    return f"{info.get('package')}:{info.get('core')}" if info.get("core") is not None else f"cpu{cpu}"


def run_mode(args: argparse.Namespace) -> int:
    """``--only scaling`` or ``--only pipeline`` (with ``--gpu``, ``--cpu-small``, ``--dry``)."""
    deadline = Deadline(args.deadline)
    plan = make_plan(args)
    tag = ("_dry" if args.dry else "" if args.gpu else "_quick" if args.quick else "_cpu") + (
        f"_{args.tag}" if args.tag else "")  # fmt: skip
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
    log.info("topology: %d CPUs, %d physical cores; pods pinned to %s; trainer on %s", topology["cpus"],
             topology["physical_cores"], pod_pins, trainer)  # fmt: skip

    started = time.monotonic()
    config = job_config(plan, pins, f"gpu-{plan.mode}", plan.pods)
    with running_job(config, args.copy_to) as job, MemoryWatch(plan.max_memory_gib) as memory:
        table = wait_for_job(job, max(60.0, min(600.0, deadline.left())))
        build_s = time.monotonic() - started
        used = memory_gib()
        processes = pod_processes(job)
        gpu_processes = gpu_process_table()
        log.info("%d pods ready in %.0f s; memory used %.1f GiB; per pod %s", plan.pods, build_s, used,
                 next(iter(processes.values())))  # fmt: skip
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
        summary.update({
            "baseline": "1 pod of the same job (same task mix), same round; linear = pods x that",
            "ratio": service,
            "ratio_loop": loop,
            "ratio_loop_stage_per_pod": loop_per_pod,
            "ratio_at_physical_cores": measured["service"][at_cores].get("fraction_of_linear", {}).get("median")
            if at_cores else None,
            "largest_pod_count_on_distinct_physical_cores": max(within) if within else None,
            "pod_counts_beyond_physical_cores": [p for p in plan.pod_counts if p not in within],
            "target": f"scaling >= {SCALING_TARGET} of linear at {plan.pods} pods ({physical} physical cores)",
            "met": {"scaling_service": service is not None and service >= SCALING_TARGET,
                    "scaling_loop": loop is not None and loop >= SCALING_TARGET,
                    "scaling_loop_stage_per_pod": loop_per_pod is not None and loop_per_pod >= SCALING_TARGET},
        })  # fmt: skip
    else:
        speedups = {layout: ratio["median"] for layout, ratio in measured["speedup_2_vs_1"].items()}
        setup["stage_envs"] = [plan.envs_per_pod * (plan.pods // 2)] * 2
        setup["stage_envs_by_layout"] = measured.pop("stage_envs")
        summary.update({
            "baseline": "1 stage over the same pods (both pods of a core simulate at once), same policy; "
                        "also 1 stage in lockstep (speedup_2_vs_1_lockstep)",
            # The headline: the first layout measured (--stage-layout's order; 'slices' by default).
            "ratio": speedups[plan.stage_layouts[0]],
            "ratio_by_layout": speedups,
            "ratio_over_lockstep_by_layout": {
                layout: ratio["median"] for layout, ratio in measured["speedup_2_vs_1_lockstep"].items()},
            "target": f"2 stages >= {PIPELINE_TARGET}x 1 stage at K={plan.chunk}",
            "met": {f"pipelining_{layout}": speedup >= PIPELINE_TARGET for layout, speedup in speedups.items()},
        })  # fmt: skip
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


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    mode = parser.add_mutually_exclusive_group(required=True)
    mode.add_argument("--gpu", action="store_true", help="LIBERO-10 at 256x256 with its defaults; GL must be NVIDIA's")
    mode.add_argument("--cpu-small", action="store_true", help="2 LIBERO-10 tasks per pod, 64x64, few pods (Mesa)")
    mode.add_argument("--quick", action="store_true",
                      help="--only pipeline on this machine in about 2 min: a cheap gym scene, 16x16, a tiny ViT")
    mode.add_argument("--render-compare", action="store_true",
                      help="one pod of one scene (default libero_10/0, 256x256, 4 envs): default EGL, then Mesa's")
    parser.add_argument("--only", choices=("scaling", "pipeline"),
                        help="which measurement (one job each; required with --gpu and --cpu-small)")
    parser.add_argument("--dry", action="store_true",
                        help="the same code at the smallest size (1 pod / 1 core, 2 steps, a 4-block ViT): fails fast")
    parser.add_argument("--tasks", help="comma-separated task ids (default: LIBERO-10; --cpu-small: its first 2)")
    parser.add_argument("--tasks-per-pod", type=int,
                        help="how many of --tasks every pod serves (default: all; --gpu --only pipeline: 5)")
    parser.add_argument("--envs-per-task", type=int, help="envs per task per pod (default 1; --render-compare 4)")
    parser.add_argument("--pods", type=int, help="scaling: the most pods (default 12; --cpu-small 2)")
    parser.add_argument("--pod-counts", help="scaling: comma-separated pod counts (default 1,2,4,8,12)")
    parser.add_argument("--pipeline-cores", type=int, help="pipeline: C cores, 2C pods (default 8; --cpu-small 1)")
    parser.add_argument("--size", type=int, help="camera height and width")
    parser.add_argument("--horizon", type=int, help="steps per trajectory in each EnvLoop rollout")
    parser.add_argument("--service-steps", type=int, help="steps per service-alone rollout")
    parser.add_argument("--rounds", type=int)
    parser.add_argument("--batch-wait-s", type=float, default=0.0,
                        help="pipeline: EnvLoop's batch_wait_s, how long the loop waits for more of a stage's "
                        "answers before the policy runs (default 0: at once)")
    parser.add_argument("--compare-batch-wait-s", default="",
                        help="pipeline: also run each 2-stage layout with each of these batch_wait_s (seconds, "
                        "comma-separated), side by side in the same rounds (contenders "
                        "'<layout>/stages=2/batch_wait=<W>s'): fuller policy batches against the time the loop "
                        "waits for them; a wait longer than a stage call is each stage in lockstep")
    parser.add_argument("--chunk", type=int, default=1,
                        help="pipeline: actions per env per call, the policy's chunk K (default 1; issue 27: 8)")
    parser.add_argument("--stage-layout", default=",".join(STAGE_LAYOUTS),
                        help="pipeline: the 2-stage layouts to measure against 1 stage, comma-separated "
                        "(slices, pods; default both, side by side)")
    parser.add_argument("--compare-stages", default="",
                        help="pipeline: also run 'slices' in each of these stage counts (3 or more, comma-separated), "
                        "at --batch-wait-s and each --compare-batch-wait-s (contenders 'slices/stages=<N>[...]')")
    parser.add_argument("--pods-per-core", type=int, default=2,
                        help="pipeline: pods pinned to each core (2: one of each 'pods' stage a core; 1: one pod a "
                             "core, its envs split between the stages in 'slices')")
    parser.add_argument("--vit-width", type=int, help="pipeline: the ViT's width (default 768; --cpu-small 192)")
    parser.add_argument("--vit-max-depth", type=int,
                        help="pipeline: the calibration's cap (default 512; --cpu-small 256)")
    parser.add_argument("--max-memory-gib", type=float, default=100.0,
                        help="stop when memory in use passes this while the pods build")
    parser.add_argument("--render-preset", default="lean", choices=("full", "fast", "lean", "lowpoly"),
                        help="the pods' render preset (default lean)")
    parser.add_argument("--render-gpu", type=int,
                        help="the EGL device (GPU index) pods render on (pods.render_gpus); the policy stays on cuda:0")
    parser.add_argument("--tag", help="suffix of the output files' names (e.g. lowpoly)")
    parser.add_argument("--deadline", type=float, default=480.0, help="seconds: stop adding rounds after this")
    parser.add_argument("--soft-rounds", type=int, default=1, help="--render-compare: rollouts with Mesa")
    parser.add_argument("--copy-to", type=Path, help="also copy the JSON and plots (and a failed job's logs) here")
    args = parser.parse_args()
    setup_logging()
    os.environ.setdefault("MUJOCO_GL", "egl")
    if args.gpu and not torch.cuda.is_available():
        # Before anything starts (GL probe, pods): a machine without a GPU fails at once.
        log.error("--gpu: torch sees no CUDA device on this machine (torch %s); run --quick or --cpu-small here",
                  torch.__version__)  # fmt: skip
        return 2
    if args.render_compare:
        return render_compare(args)
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
    for flag, wait in (("--batch-wait-s", args.batch_wait_s), *(("--compare-batch-wait-s", w) for w in args.compare_batch_wait_s)):
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
        parser.error(f"--compare-stages: stage counts of 3 or more (1 and 2 are always measured), "
                     f"got {args.compare_stages}")
    if args.compare_stages and (args.only != "pipeline" or "slices" not in args.stage_layout.split(",")):
        parser.error("--compare-stages runs the 'slices' layout in more stages: "
                     "say --only pipeline with slices in --stage-layout")
    return run_mode(args)


if __name__ == "__main__":
    sys.exit(main())
