"""The robot observables a LIBERO policy reads, batched over worlds in Warp.

What vecsim's CPU engine returns (``vecsim.engine.tasks._libero``, docs/libero.md):

- ``state`` ``[nworld, 8]``: end-effector position, the axis-angle of its quaternion (robosuite's
  ``quat2axisangle``, sign kept: ``2 acos(w)`` along ``(x, y, z)``), the two finger joints;
- ``proprio`` ``[nworld, 23]``: cos and sin of the 7 arm joints, end-effector position, its
  quaternion ``(x, y, z, w)``, the two finger joints (``PROPRIO_KEYS``).

The end-effector position is the grip site's; its quaternion is the hand body's (robosuite's
``eef_pos`` and ``eef_quat``). Inputs are MuJoCo Warp ``Data`` fields (``xquat`` in MuJoCo's
``(w, x, y, z)`` order, as MuJoCo Warp keeps it). LIBERO samples them right after the physics
step of substep :data:`LIBERO_SAMPLE_SUBSTEP` (0-based, of 25), not at the end of the action:
there, ``Data`` holds that substep's kinematics and the joints after its integration, which is
what robosuite's observables read. Example::

    obs = PandaObservables(ObservableIndex.from_robosuite(env), nworld, device)
    obs.compute(d.qpos, d.site_xpos, d.xquat)   # fills obs.state and obs.proprio
"""

from __future__ import annotations

from typing import Any

import numpy as np
import warp as wp

from vecsim.engine.mjwarp.tables import ObservableIndex

STATE_DIM = 8
# After LIBERO's reset and set_init_state each force a sample, robosuite's observable clock
# (20 Hz over 500 Hz physics) samples after this substep's physics step of every action.
LIBERO_SAMPLE_SUBSTEP = 23
PROPRIO_DIM = 7 + 7 + 3 + 4 + 2
ARM_DOF = 7


@wp.func
def quat_axis_angle(x: float, y: float, z: float, w: float) -> wp.vec3:
    """robosuite's ``quat2axisangle`` of ``(x, y, z, w)``: no sign folding, 0 at ``|w| == 1``."""
    wc = wp.clamp(w, -1.0, 1.0)
    den = wp.sqrt(1.0 - wc * wc)
    if den == 0.0:
        return wp.vec3(0.0, 0.0, 0.0)
    return wp.vec3(x, y, z) * (2.0 * wp.acos(wc) / den)


@wp.kernel
def libero_robot_state(
    qpos: wp.array2d(dtype=wp.float32),
    site_xpos: wp.array2d(dtype=wp.vec3),
    xquat: wp.array2d(dtype=wp.quat),
    eef_site: int,
    eef_body: int,
    arm_qpos: wp.array(dtype=wp.int32),
    gripper_qpos: wp.array(dtype=wp.int32),
    state: wp.array2d(dtype=wp.float32),
    proprio: wp.array2d(dtype=wp.float32),
):
    """Each world's 8-float LIBERO state and 23-float proprio."""
    w = wp.tid()
    pos = site_xpos[w, eef_site]
    q = xquat[w, eef_body]  # MuJoCo order: w, x, y, z
    qw = q[0]
    qx = q[1]
    qy = q[2]
    qz = q[3]
    aa = quat_axis_angle(qx, qy, qz, qw)
    g0 = qpos[w, gripper_qpos[0]]
    g1 = qpos[w, gripper_qpos[1]]
    for i in range(3):
        state[w, i] = pos[i]
        state[w, 3 + i] = aa[i]
        proprio[w, 14 + i] = pos[i]
    state[w, 6] = g0
    state[w, 7] = g1
    for k in range(ARM_DOF):
        angle = qpos[w, arm_qpos[k]]
        proprio[w, k] = wp.cos(angle)
        proprio[w, ARM_DOF + k] = wp.sin(angle)
    proprio[w, 17] = qx
    proprio[w, 18] = qy
    proprio[w, 19] = qz
    proprio[w, 20] = qw
    proprio[w, 21] = g0
    proprio[w, 22] = g1


class PandaObservables:
    """``state`` and ``proprio`` of ``nworld`` worlds, refreshed by :meth:`compute`."""

    def __init__(self, index: ObservableIndex, nworld: int, device: Any = None):
        self.index, self.nworld = index, nworld
        self.device = wp.get_device(device)
        self._arm_qpos = wp.array(index.arm_qpos.astype(np.int32), dtype=wp.int32, device=self.device)
        self._gripper_qpos = wp.array(index.gripper_qpos.astype(np.int32), dtype=wp.int32, device=self.device)
        self.state = wp.zeros((nworld, STATE_DIM), dtype=wp.float32, device=self.device)
        self.proprio = wp.zeros((nworld, PROPRIO_DIM), dtype=wp.float32, device=self.device)

    def compute(self, qpos: wp.array, site_xpos: wp.array, xquat: wp.array) -> None:
        """Fill :attr:`state` and :attr:`proprio` from the worlds' current kinematics."""
        wp.launch(
            libero_robot_state,
            dim=self.nworld,
            device=self.device,
            inputs=[
                qpos,
                site_xpos,
                xquat,
                self.index.eef_site,
                self.index.eef_body,
                self._arm_qpos,
                self._gripper_qpos,
            ],
            outputs=[self.state, self.proprio],
        )
