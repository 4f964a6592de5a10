"""The example policy of the rollout (the demo's, the tests'): a small CNN over a job's cameras,
its instruction hashed into an embedding, acting through a tanh squashed into the action bounds.

    policy = ExampleCNNPolicy(client.observation_space, client.action_space)
"""

from __future__ import annotations

import zlib
from typing import Any

import numpy as np
import torch
from gymnasium import spaces
from torch import nn


def _hash_bucket(text: str, buckets: int) -> int:
    # crc32, not hash(): Python salts str hashes per process.
    return zlib.crc32(text.encode()) % buckets


class ExampleCNNPolicy(nn.Module):
    """A small CNN policy over vecsim's observation: camera images, proprio, instruction, task id.

    Each camera goes through one shared conv encoder; proprio through a linear layer; the
    instruction as a hashed bag of words and the task id as a hashed embedding. A tanh head maps
    to the action space's bounds. With ``noise_std > 0`` Gaussian noise explores around it.
    """

    def __init__(
        self,
        observation_space: spaces.Dict,
        action_space: spaces.Box,
        hidden: int = 64,
        noise_std: float = 0.0,
        buckets: int = 1024,
        seed: int = 0,
    ) -> None:
        super().__init__()
        torch.manual_seed(seed)
        image_space = observation_space.spaces.get("images")
        self.cameras = list(image_space.spaces) if image_space is not None else []
        self.encoder = nn.Sequential(
            nn.Conv2d(3, 16, kernel_size=5, stride=2, padding=2),
            nn.ReLU(),
            nn.Conv2d(16, 32, kernel_size=3, stride=2, padding=1),
            nn.ReLU(),
            nn.AdaptiveAvgPool2d(1),
            nn.Flatten(),
        )
        proprio_dim = int(np.prod(observation_space["proprio"].shape))
        self.proprio = nn.Linear(proprio_dim, hidden)
        self.buckets = buckets
        self.words = nn.EmbeddingBag(buckets, 16, mode="mean")
        self.tasks = nn.Embedding(buckets, 16)
        action_dim = int(np.prod(action_space.shape))
        self.head = nn.Sequential(
            nn.Linear(32 * len(self.cameras) + hidden + 32, hidden), nn.ReLU(), nn.Linear(hidden, action_dim)
        )
        low, high = np.asarray(action_space.low, np.float32), np.asarray(action_space.high, np.float32)
        bounded = np.isfinite(low) & np.isfinite(high)
        self.register_buffer("center", torch.from_numpy(np.where(bounded, (low + high) / 2, 0.0).astype(np.float32)))
        self.register_buffer("scale", torch.from_numpy(np.where(bounded, (high - low) / 2, 1.0).astype(np.float32)))
        self.noise_std = float(noise_std)

    def forward(self, obs: dict[str, Any], instructions: list[str], task_ids: list[str]) -> torch.Tensor:
        """Return actions ``[n, action_dim]`` for a batch of observations (tensors on the module's device)."""
        device = self.center.device
        features = []
        for camera in self.cameras:
            image = obs["images"][camera].to(device=device, dtype=torch.float32) / 255.0
            features.append(self.encoder(image.permute(0, 3, 1, 2)))
        features.append(torch.relu(self.proprio(obs["proprio"].to(device=device, dtype=torch.float32))))
        words = [[_hash_bucket(w, self.buckets) for w in text.lower().split()] or [0] for text in instructions]
        flat = torch.tensor([b for ws in words for b in ws], device=device, dtype=torch.long)
        offsets = torch.tensor(np.cumsum([0] + [len(ws) for ws in words[:-1]]), device=device, dtype=torch.long)
        features.append(self.words(flat, offsets))
        features.append(self.tasks(torch.tensor([_hash_bucket(t, self.buckets) for t in task_ids], device=device)))
        mean = torch.tanh(self.head(torch.cat(features, dim=1)))
        if self.noise_std > 0:
            mean = (mean + self.noise_std * torch.randn_like(mean)).clamp(-1.0, 1.0)
        return self.center + self.scale * mean
