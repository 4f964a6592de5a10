"""The trainer's side of a GPU bench: vision policies (a ResNet-18 and a ViT-style encoder per
camera, bf16), their CUDA graphs per batch size, a ViT whose depth is calibrated to a target
forward time (:func:`calibrate_vit`), open-loop scripted policies, a policy acting in chunks of K
(:class:`ChunkedPolicy`) and tables of random actions.
"""

from __future__ import annotations

import logging
import statistics
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from gymnasium import spaces
from torch import nn

from .jobs import Plan


log = logging.getLogger("bench.policies")
PIPELINE_K = 8  # the chunk length of issue 27's case, the chunked benches' headline K
RANDOM_ACTIONS = 64  # random_actions: a table of this many actions per env, cycled
# How close the calibrated policy's forward pass must come to its target before the picking stops
# (within 3 picks). At 10% the picks ran 3-8% over the simulation call they stood for.
CALIBRATION_TOLERANCE = 0.04


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
            nn.Conv2d(3, 64, 7, 2, 3, bias=False),
            nn.BatchNorm2d(64),
            nn.ReLU(),
            nn.MaxPool2d(3, 2, 1),
        ]
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
            self.head = nn.Sequential(
                nn.Linear(feature + 128, 512), nn.GELU(), nn.Linear(512, 256), nn.GELU(), nn.Linear(256, actions)
            )
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

    def __init__(
        self, policy: nn.Module, space: spaces.Dict, device: str, batch_sizes: Sequence[int], pad: bool = False
    ) -> None:
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
        return {
            "graph_sizes": sorted(self.graphs),
            "pad": self.pad,
            "padded_calls": self.padded_calls,
            "padded_rows": self.padded_rows,
        }


def pod_multiples(per_pod: int, largest: int, extra: Sequence[int] = ()) -> list[int]:
    """Batch sizes to capture for a loop that hands the policy whole pods' answers: every multiple
    of ``per_pod`` up to ``largest``, ``largest`` itself and ``extra``."""
    step = max(per_pod, 1)
    return sorted({*range(step, largest + 1, step), largest, *extra})


def parameters_m(policy: nn.Module) -> float:
    """Return the policy's parameter count in millions."""
    return round(sum(p.numel() for p in policy.parameters()) / 1e6, 2)


def calibrate_vit(
    plan: Plan,
    space: spaces.Dict,
    action: spaces.Box,
    batch: int,
    target_ms: float,
    batch_sizes: Sequence[int],
    pad_sizes: Sequence[int] = (),
) -> tuple[GraphedPolicy, dict[str, Any]]:
    """Return a ViT policy, graphed for ``batch_sizes``, whose forward pass on ``batch``
    observations lasts about ``target_ms``, and what the calibration found. The depth is
    extrapolated from two shallow ViTs, then corrected once by the time the first pick takes;
    never above ``plan.vit_max_depth``. With ``pad_sizes``, the picked policy is then also
    captured for those sizes and pads a batch of any other size to the next captured one."""

    def build(depth: int, sizes: Sequence[int]) -> GraphedPolicy:
        policy = VisionPolicy(
            space,
            action,
            encoder="vit",
            vit_depth=depth,
            vit_width=plan.vit_width,
            device=plan.device,
            dtype=plan.torch_dtype,
        )
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


class ChunkedPolicy:
    """A policy of one action per call acting in chunks of ``k``: one forward pass per chunk,
    its action followed by ``k - 1`` more along a small sine around it, within the bounds."""

    def __init__(self, policy: Callable[..., torch.Tensor], action_space: spaces.Box, k: int) -> None:
        self.policy = policy
        self.k = k
        low = torch.as_tensor(np.asarray(action_space.low, np.float32))
        high = torch.as_tensor(np.asarray(action_space.high, np.float32))
        self.low, self.high = low, high
        self.offsets = chunk_offsets(action_space, k)  # [k, action_dim]

    def __call__(self, obs: dict[str, Any], instructions: list[str], task_ids: list[str]) -> torch.Tensor:
        action = self.policy(obs, instructions, task_ids).float()  # [n, action_dim]
        device = action.device
        chunk = action[:, None, :] + self.offsets.to(device)
        return torch.maximum(torch.minimum(chunk, self.high.to(device)), self.low.to(device))


def chunk_offsets(action_space: spaces.Box, k: int) -> torch.Tensor:
    """``[k, action_dim]``: what :class:`ChunkedPolicy` adds to a policy's action at each place of
    a chunk of ``k``, a small sine of 2% of each dimension's width."""
    low = torch.as_tensor(np.asarray(action_space.low, np.float32))
    high = torch.as_tensor(np.asarray(action_space.high, np.float32))
    steps, dims = torch.arange(k, dtype=torch.float32)[:, None], torch.arange(low.numel(), dtype=torch.float32)
    width = torch.where(torch.isfinite(high - low), high - low, torch.ones_like(low))
    return 0.02 * width * torch.sin(0.35 * steps + 0.9 * dims)


def random_actions(rng: np.random.Generator, shape: Sequence[int]) -> np.ndarray:
    """Random actions for one env (the chunks bench's ceiling, the action-cost bench): ``RANDOM_ACTIONS`` of ``shape``, uniform within +-0.3."""
    return rng.uniform(-0.3, 0.3, (RANDOM_ACTIONS, *shape)).astype(np.float32)
