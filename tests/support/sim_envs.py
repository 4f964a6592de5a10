"""What the sim tests share: cameras, an assignment of task blocks laid out from env index 0 on
pod sim-0, and the rows of a batched observation that tell envs apart."""

from __future__ import annotations

import os
import select
import signal
from typing import Any

import numpy as np

from vecsim.config import Assignment, CameraConfig

from .service_procs import assignment

NO_CAMERA = CameraConfig(names=())
TINY_CAMERA = CameraConfig(height=8, width=8)
CAMERAS = ("agentview", "robot0_eye_in_hand")


def sim_assignment(blocks: list[tuple[str, int]], camera: CameraConfig = NO_CAMERA, **fields: Any) -> Assignment:
    """Generation 1 of pod sim-0, stage 0: ``blocks`` of ``[(task_id, num_envs), ...]``."""
    return assignment("sim-0", blocks, generation=1, camera=camera, **fields)


def env_rows(obs: Any) -> list[bytes]:
    """One byte string per env of a batched observation: equal strings mean bit-identical envs."""
    if isinstance(obs, np.ndarray):  # a gym task without cameras: the env's own Box observation
        return [row.tobytes() for row in obs]
    leaves = [obs["proprio"]] + [obs["images"][name] for name in sorted(obs.get("images", {}))]
    return [b"".join(leaf[i].tobytes() for leaf in leaves) for i in range(len(obs["proprio"]))]


def kill_worker(pid: int) -> None:
    """SIGKILL a worker process and return once it has ended (its pidfd reads ready): the pod
    checks its workers before and after each call, and no call of the test races the kill."""
    pidfd = os.pidfd_open(pid)
    try:
        os.kill(pid, signal.SIGKILL)
        select.select([pidfd], [], [], 60)
    finally:
        os.close(pidfd)
