"""Build a real LIBERO env and record, at each physics substep, what robosuite's controller read.

The recording wraps the robot's own ``control`` (robosuite's code runs unchanged) and copies the
``MjData`` fields a MuJoCo Warp ``Data`` holds, taken after robosuite's forward pass, together
with what robosuite made of them: the goal and the ``ctrl`` it wrote.
"""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Iterator
from typing import Any

import mujoco
import numpy as np

from vecsim.engine.tasks import get_task
from vecsim.engine.tasks._libero import SETTLE_ACTION, ensure_config, init_states, libero_benchmark

# MjData fields the kernels take, as MuJoCo Warp names them.
FIELDS = ("qpos", "qvel", "M", "qM", "qfrc_bias", "site_xpos", "site_xmat", "xanchor", "xaxis", "xpos", "xquat", "ctrl")


@dataclasses.dataclass
class Substep:
    """One call of robosuite's ``control``: its inputs, its goal after the call and its ctrl."""

    action: np.ndarray
    policy_step: bool
    data: dict[str, np.ndarray]
    goal_pos: np.ndarray
    goal_ori: np.ndarray
    gripper_command: np.ndarray


def snapshot(data: Any) -> dict[str, np.ndarray]:
    """Copy the recorded fields of an ``MjData`` (``site_xmat`` as ``[nsite, 3, 3]``)."""
    fields = {name: np.array(getattr(data, name)) for name in FIELDS}
    fields["site_xmat"] = fields["site_xmat"].reshape(-1, 3, 3)
    return fields


@contextlib.contextmanager
def libero_env(task_id: str, state_id: int = 0) -> Iterator[Any]:
    """LIBERO's own env of ``task_id`` after an evaluation's reset and ``set_init_state``."""
    ensure_config()
    from libero.libero.envs import OffScreenRenderEnv

    suite, index = task_id.split("/")
    bddl = libero_benchmark(suite).get_task_bddl_file_path(int(index))
    env = OffScreenRenderEnv(bddl_file_name=bddl, camera_heights=32, camera_widths=32)
    try:
        env.seed(0)
        env.reset()
        env.set_init_state(init_states(get_task(task_id))[state_id])
        yield env
    finally:
        env.close()
        mujoco.mj_clearCache(mujoco.mj_getCache())


@contextlib.contextmanager
def recording(env: Any) -> Iterator[list[Substep]]:
    """Record every substep of ``env.step`` while inside (the robot's ``control``, wrapped)."""
    inner = env.env
    robot = inner.robots[0]
    original = robot.control
    substeps: list[Substep] = []

    def control(action: np.ndarray, policy_step: bool = False) -> None:
        original(action, policy_step=policy_step)
        ctl = robot.controller
        substeps.append(
            Substep(
                action=np.array(action, dtype=np.float64),
                policy_step=policy_step,
                data=snapshot(inner.sim.data._data),
                goal_pos=np.array(ctl.goal_pos),
                goal_ori=np.array(ctl.goal_ori),
                gripper_command=np.array(robot.gripper.current_action),
            )
        )

    robot.control = control
    try:
        yield substeps
    finally:
        del robot.control


def settle(env: Any, steps: int = 5) -> None:
    """LIBERO's evaluation settle: arm still, gripper opening."""
    for _ in range(steps):
        env.step(SETTLE_ACTION.tolist())
