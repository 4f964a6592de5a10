"""What a rollout answers: per-trajectory tensors (:class:`Trajectory`), the ones lost with their
route (:class:`LostTrajectory`), and the timing statistics (:class:`RolloutStats`), together a
:class:`RolloutResult`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from vecsim.client import TrajRoute


@dataclass
class Trajectory:
    """One finished trajectory of T actions, taken over C policy calls.

    ``observations`` holds the kept keys of the observation (``images`` and/or ``proprio``),
    each ``[C+1, ...]``: what the policy saw at each call, and the last one; ``actions``
    ``[T, A]``; ``rewards`` ``[T]``; ``dones`` ``[T]`` (True at the last step); ``num_steps``
    ``[C]``: the actions applied after each observation (all ones, and C = T, for a policy of
    one action per call). ``success``: the task was solved at some step.
    """

    traj_key: str
    route: TrajRoute
    observations: dict[str, Any]
    actions: torch.Tensor
    rewards: torch.Tensor
    dones: torch.Tensor
    terminated: bool
    truncated: bool
    success: bool
    num_steps: torch.Tensor = field(default_factory=lambda: torch.zeros(0, dtype=torch.int32))

    @property
    def length(self) -> int:
        return int(self.actions.shape[0])


@dataclass
class RolloutStats:
    """How a rollout spent its time.

    ``policy_s``: time in the policy (including moving observations to tensors);
    ``simulation_s``: time with at least one stage call in flight; ``wait_s``: time the loop
    blocked waiting for observations; ``overlap_fraction``: share of ``policy_s`` during which
    some stage was simulating (1.0 = the policy never ran alone).
    """

    num_trajectories: int = 0
    env_steps: int = 0
    wall_s: float = 0.0
    env_steps_per_s: float = 0.0
    policy_s: float = 0.0
    simulation_s: float = 0.0
    wait_s: float = 0.0
    overlap_s: float = 0.0
    overlap_fraction: float = 0.0
    success_per_task: dict[str, float] = field(default_factory=dict)
    # (what, stage_id, begin_s, end_s) from the rollout's start; what is "policy" or "sim".
    timeline: list[tuple[str, int, float, float]] = field(default_factory=list)
    # One per pod call, in the order they landed: (stage_id, pod, begin_s, end_s, resets, steps),
    # the call's time in flight from the rollout's start and how many trajectories it reset and
    # stepped (a first step's cost against later ones: service/demo.py's step_costs).
    pod_calls: list[tuple[int, str, float, float, int, int]] = field(default_factory=list)


@dataclass(frozen=True)
class LostTrajectory:
    """A trajectory that did not finish: its pod died, did not answer within the client's
    timeout or rebuilt its envs, or its env raised in a reset or step. ``route`` names what to
    resample (its task and state id); ``steps`` is how many actions it had taken; ``reason`` is
    the client's error, or the env's exception (type and message)."""

    traj_key: str
    route: TrajRoute
    steps: int
    reason: str


@dataclass
class RolloutResult:
    """Finished trajectories keyed by traj_key (in request order), the lost ones (neither
    finished nor failed the rollout: resample them), stats, and the videos written."""

    trajectories: dict[str, Trajectory]
    stats: RolloutStats
    videos: dict[str, Path] = field(default_factory=dict)
    lost: dict[str, LostTrajectory] = field(default_factory=dict)
