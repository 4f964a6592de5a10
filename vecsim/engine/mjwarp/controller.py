"""robosuite 1.4's ``OSC_POSE`` arm controller and the Panda gripper, batched over worlds in Warp.

LIBERO drives its Panda through robosuite's ``OSC_POSE`` (delta pose, kp 150, critical damping,
``uncouple_pos_ori``, nullspace pull to the arm's reset pose, no interpolator) and a gripper whose
command moves by ``0.01 * sign(a)`` per physics substep. An env action sets the goal once, from
the state at its first substep; torques are recomputed from the current state at each of the 25
substeps. This module is that math, written from robosuite's equations, for many worlds at once:

- :class:`~vecsim.engine.mjwarp.tables.PandaIndex`: where the arm lives in one model (site, joints,
  dofs, actuators, mass matrix), read without warp (:mod:`vecsim.engine.mjwarp.tables`);
- :class:`PandaController`: per-world goal, nullspace target and gripper command, and the calls
  ``reset(mask, initial_joint, goal_pos, goal_ori)`` (where ``mask`` is 1), ``set_goal(action,
  site_xpos, site_xmat)`` (first substep of an env action) and ``apply(action, ..., ctrl)``
  (every substep: arm torques and gripper command into ``ctrl``).

Inputs are MuJoCo Warp ``Data`` fields with a leading world dimension, float32, as the position
and velocity stages at the current state leave them (``step1``: kinematics, ``M``, ``qfrc_bias``);
the mass matrix is viewed 2-D per world (``d.M`` or ``d.qM`` reshaped to ``(nworld, -1)``, with
``PandaIndex.mass_index`` built for that layout). The math runs in float64 inside each kernel::

    ctl = PandaController(PandaIndex.from_robosuite(env), nworld, device)
    ctl.reset(mask, initial_joint, goal_pos, goal_ori)
    ctl.set_goal(action, d.site_xpos, d.site_xmat)
    ctl.apply(action, d.qpos, d.qvel, mass, d.qfrc_bias, d.site_xpos, d.site_xmat,
              d.xanchor, d.xaxis, d.ctrl)
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import warp as wp

from vecsim.engine.mjwarp.tables import ARM_DOF, PandaIndex

GRIPPER_ACTUATORS = 2
ACTION_DIM = 7

mat77d = wp.types.matrix(shape=(ARM_DOF, ARM_DOF), dtype=wp.float64)
mat67d = wp.types.matrix(shape=(6, ARM_DOF), dtype=wp.float64)
vec7d = wp.types.vector(length=ARM_DOF, dtype=wp.float64)
vec6d = wp.types.vector(length=6, dtype=wp.float64)


@dataclasses.dataclass(frozen=True)
class OscPoseConfig:
    """robosuite's ``osc_pose.json`` as LIBERO loads it (``impedance_mode: fixed``)."""

    input_min: float = -1.0
    input_max: float = 1.0
    # Position (m) then rotation (rad) reached by a full-scale action.
    output_max: tuple[float, ...] = (0.05, 0.05, 0.05, 0.5, 0.5, 0.5)
    output_min: tuple[float, ...] = (-0.05, -0.05, -0.05, -0.5, -0.5, -0.5)
    kp: float = 150.0
    damping_ratio: float = 1.0
    # robosuite's ``nullspace_torques`` default gain (critically damped).
    nullspace_kp: float = 10.0
    # The Panda gripper's command step per substep (``PandaGripper.speed``).
    gripper_speed: float = 0.01


@wp.func
def axis_angle_matrix(v: wp.vec3d) -> wp.mat33d:
    """Rotation of the axis-angle vector ``v`` (robosuite: identity when its norm is exactly 0)."""
    angle = wp.length(v)
    if angle == wp.float64(0.0):
        return wp.identity(n=3, dtype=wp.float64)
    q = wp.quat_from_axis_angle(v / angle, angle)
    return wp.quat_to_matrix(q)


@wp.func
def orientation_error(desired: wp.mat33d, current: wp.mat33d) -> wp.vec3d:
    """robosuite's ``orientation_error``: half the sum of column cross products."""
    e = wp.vec3d()
    for c in range(3):
        e += wp.cross(
            wp.vec3d(current[0, c], current[1, c], current[2, c]),
            wp.vec3d(desired[0, c], desired[1, c], desired[2, c]),
        )
    return wp.float64(0.5) * e


@wp.func
def cholesky7(a: mat77d) -> mat77d:
    """Lower Cholesky factor of a symmetric positive definite 7x7 matrix."""
    low = mat77d()
    for j in range(ARM_DOF):
        s = a[j, j]
        for k in range(j):
            s -= low[j, k] * low[j, k]
        low[j, j] = wp.sqrt(s)
        for i in range(j + 1, ARM_DOF):
            t = a[i, j]
            for k in range(j):
                t -= low[i, k] * low[j, k]
            low[i, j] = t / low[j, j]
    return low


@wp.func
def cholesky7_solve(low: mat77d, b: vec7d) -> vec7d:
    """Solve ``(low low^T) x = b``."""
    y = vec7d()
    for i in range(ARM_DOF):
        s = b[i]
        for k in range(i):
            s -= low[i, k] * y[k]
        y[i] = s / low[i, i]
    x = vec7d()
    for ii in range(ARM_DOF):
        i = ARM_DOF - 1 - ii
        s = y[i]
        for k in range(i + 1, ARM_DOF):
            s -= low[k, i] * x[k]
        x[i] = s / low[i, i]
    return x


@wp.kernel
def osc_goal_from_action(
    action: wp.array2d(dtype=wp.float32),
    site_xpos: wp.array2d(dtype=wp.vec3),
    site_xmat: wp.array2d(dtype=wp.mat33),
    eef_site: int,
    input_min: float,
    input_max: float,
    action_scale: wp.array(dtype=wp.float64),
    action_offset: wp.array(dtype=wp.float64),
    goal_pos: wp.array(dtype=wp.vec3),
    goal_ori: wp.array(dtype=wp.mat33),
):
    """A new OSC goal per world from its delta-pose action and the current end-effector pose."""
    w = wp.tid()
    mid = wp.float64(0.5) * (wp.float64(input_max) + wp.float64(input_min))
    delta = vec6d()
    for i in range(6):
        a = wp.float64(wp.clamp(action[w, i], input_min, input_max))
        delta[i] = (a - mid) * action_scale[i] + action_offset[i]
    pos = wp.vec3d(site_xpos[w, eef_site])
    goal_pos[w] = wp.vec3(pos + wp.vec3d(delta[0], delta[1], delta[2]))
    rot = wp.vec3d(delta[3], delta[4], delta[5])
    # robosuite keeps the previous orientation goal when every rotation delta is exactly 0.
    if rot[0] != wp.float64(0.0) or rot[1] != wp.float64(0.0) or rot[2] != wp.float64(0.0):
        goal_ori[w] = wp.mat33(axis_angle_matrix(rot) * wp.mat33d(site_xmat[w, eef_site]))


@wp.kernel
def osc_pose_torques(
    qpos: wp.array2d(dtype=wp.float32),
    qvel: wp.array2d(dtype=wp.float32),
    mass: wp.array2d(dtype=wp.float32),
    qfrc_bias: wp.array2d(dtype=wp.float32),
    site_xpos: wp.array2d(dtype=wp.vec3),
    site_xmat: wp.array2d(dtype=wp.mat33),
    xanchor: wp.array2d(dtype=wp.vec3),
    xaxis: wp.array2d(dtype=wp.vec3),
    eef_site: int,
    arm_joints: wp.array(dtype=wp.int32),
    arm_qpos: wp.array(dtype=wp.int32),
    arm_dofs: wp.array(dtype=wp.int32),
    arm_actuators: wp.array(dtype=wp.int32),
    mass_idx: wp.array2d(dtype=wp.int32),
    kp: float,
    kd: float,
    nullspace_kp: float,
    torque_low: wp.array(dtype=wp.float32),
    torque_high: wp.array(dtype=wp.float32),
    goal_pos: wp.array(dtype=wp.vec3),
    goal_ori: wp.array(dtype=wp.mat33),
    initial_joint: wp.array2d(dtype=wp.float32),
    ctrl: wp.array2d(dtype=wp.float32),
):
    """Operational-space torques of the arm toward its goal, clipped to the actuators' range."""
    w = wp.tid()
    pos = wp.vec3d(site_xpos[w, eef_site])
    rot = wp.mat33d(site_xmat[w, eef_site])
    # The site Jacobian over the arm's hinge dofs (all its ancestors): linear part
    # axis x (site - anchor), angular part the axis.
    jac = mat67d()
    qd = vec7d()
    q = vec7d()
    arm_mass = mat77d()
    for k in range(ARM_DOF):
        jnt = arm_joints[k]
        axis = wp.vec3d(xaxis[w, jnt])
        lin = wp.cross(axis, pos - wp.vec3d(xanchor[w, jnt]))
        for r in range(3):
            jac[r, k] = lin[r]
            jac[r + 3, k] = axis[r]
        qd[k] = wp.float64(qvel[w, arm_dofs[k]])
        q[k] = wp.float64(qpos[w, arm_qpos[k]])
        for c in range(ARM_DOF):
            arm_mass[k, c] = wp.float64(mass[w, mass_idx[k, c]])
    vel = jac * qd
    kp64 = wp.float64(kp)
    kd64 = wp.float64(kd)
    force = kp64 * (wp.vec3d(goal_pos[w]) - pos) - kd64 * wp.vec3d(vel[0], vel[1], vel[2])
    torque = kp64 * orientation_error(wp.mat33d(goal_ori[w]), rot) - kd64 * wp.vec3d(vel[3], vel[4], vel[5])

    # x = M^-1 J^T, column by column; lambda^-1 = J x.
    low = cholesky7(arm_mass)
    minv_jt = mat67d()  # stored transposed: row r is M^-1 times row r of J
    for r in range(6):
        row = vec7d()
        for k in range(ARM_DOF):
            row[k] = jac[r, k]
        sol = cholesky7_solve(low, row)
        for k in range(ARM_DOF):
            minv_jt[r, k] = sol[k]
    lam_inv = mat77d()  # the 6x6 J M^-1 J^T, padded to 7x7 with a unit diagonal entry
    for r in range(6):
        for c in range(6):
            s = wp.float64(0.0)
            for k in range(ARM_DOF):
                s += jac[r, k] * minv_jt[c, k]
            lam_inv[r, c] = s
    lam_inv[6, 6] = wp.float64(1.0)
    lam_pos_inv = wp.mat33d()
    lam_ori_inv = wp.mat33d()
    for r in range(3):
        for c in range(3):
            lam_pos_inv[r, c] = lam_inv[r, c]
            lam_ori_inv[r, c] = lam_inv[r + 3, c + 3]
    # uncouple_pos_ori: position and orientation each through their own lambda.
    f = wp.inverse(lam_pos_inv) * force
    t = wp.inverse(lam_ori_inv) * torque
    wrench = vec6d(f[0], f[1], f[2], t[0], t[1], t[2])
    tau = wp.transpose(jac) * wrench

    # Nullspace: N^T tau0 = tau0 - J^T lambda (M^-1 J^T)^T tau0, tau0 = M (kp (q0 - q) - kv qd).
    kv = wp.float64(2.0) * wp.sqrt(wp.float64(nullspace_kp))
    pull = vec7d()
    for k in range(ARM_DOF):
        pull[k] = wp.float64(nullspace_kp) * (wp.float64(initial_joint[w, k]) - q[k]) - kv * qd[k]
    tau0 = arm_mass * pull
    y = vec7d()
    for r in range(6):
        s = wp.float64(0.0)
        for k in range(ARM_DOF):
            s += minv_jt[r, k] * tau0[k]
        y[r] = s
    z = cholesky7_solve(cholesky7(lam_inv), y)
    z6 = vec6d(z[0], z[1], z[2], z[3], z[4], z[5])
    tau += tau0 - wp.transpose(jac) * z6

    for k in range(ARM_DOF):
        total = wp.float32(tau[k] + wp.float64(qfrc_bias[w, arm_dofs[k]]))
        # np.clip keeps a NaN (a broken world stays visibly broken); wp.clamp would not.
        ctrl[w, arm_actuators[k]] = wp.where(wp.isnan(total), total, wp.clamp(total, torque_low[k], torque_high[k]))


@wp.kernel
def panda_gripper_ctrl(
    action: wp.array2d(dtype=wp.float32),
    speed: float,
    gripper_actuators: wp.array(dtype=wp.int32),
    ctrl_low: wp.array(dtype=wp.float32),
    ctrl_high: wp.array(dtype=wp.float32),
    command: wp.array2d(dtype=wp.float32),
    ctrl: wp.array2d(dtype=wp.float32),
):
    """One substep of the Panda gripper: step its command by ``speed * sign(a)``, map to ctrl."""
    w = wp.tid()
    a = action[w, ACTION_DIM - 1]
    step = speed * wp.sign(a)
    if a == 0.0:
        step = 0.0
    for i in range(GRIPPER_ACTUATORS):
        # robosuite's [-1, 1] * speed * sign(a): the fingers' commands move oppositely.
        direction = wp.float32(2 * i - 1)
        c = wp.clamp(command[w, i] + direction * step, -1.0, 1.0)
        command[w, i] = c
        lo = ctrl_low[i]
        hi = ctrl_high[i]
        ctrl[w, gripper_actuators[i]] = 0.5 * (hi + lo) + 0.5 * (hi - lo) * c


@wp.kernel
def controller_reset(
    mask: wp.array(dtype=wp.int32),
    initial_joint_in: wp.array2d(dtype=wp.float32),
    goal_pos_in: wp.array(dtype=wp.vec3),
    goal_ori_in: wp.array(dtype=wp.mat33),
    initial_joint: wp.array2d(dtype=wp.float32),
    goal_pos: wp.array(dtype=wp.vec3),
    goal_ori: wp.array(dtype=wp.mat33),
    command: wp.array2d(dtype=wp.float32),
):
    """Where ``mask`` is set: the controller a LIBERO reset builds, and a gripper command of 0."""
    w = wp.tid()
    if mask[w] == 0:
        return
    for k in range(ARM_DOF):
        initial_joint[w, k] = initial_joint_in[w, k]
    goal_pos[w] = goal_pos_in[w]
    goal_ori[w] = goal_ori_in[w]
    for i in range(GRIPPER_ACTUATORS):
        command[w, i] = 0.0


class PandaController:
    """The OSC_POSE arm and Panda gripper controllers of ``nworld`` worlds on one Warp device.

    Holds per world what robosuite's controller objects hold between calls: the goal position
    and orientation, the nullspace target (the arm's joints when LIBERO's reset built the
    controller) and the gripper's integrated command.
    """

    def __init__(self, index: PandaIndex, nworld: int, device: Any = None, config: OscPoseConfig = OscPoseConfig()):
        if len(index.arm_dofs) != ARM_DOF or len(index.gripper_actuators) != GRIPPER_ACTUATORS:
            raise ValueError(f"a Panda has {ARM_DOF} arm dofs and {GRIPPER_ACTUATORS} gripper actuators")
        self.index, self.nworld, self.config = index, nworld, config
        self.device = wp.get_device(device)
        out_max, out_min = np.asarray(config.output_max), np.asarray(config.output_min)
        scale = np.abs(out_max - out_min) / abs(config.input_max - config.input_min)

        def ints(values: np.ndarray) -> wp.array:
            return wp.array(np.asarray(values, dtype=np.int32), dtype=wp.int32, device=self.device)

        def floats(values: np.ndarray, dtype: Any = wp.float32) -> wp.array:
            return wp.array(np.asarray(values), dtype=dtype, device=self.device)

        self._action_scale = floats(scale, wp.float64)
        self._action_offset = floats((out_max + out_min) / 2.0, wp.float64)
        self._arm_joints, self._arm_qpos = ints(index.arm_joints), ints(index.arm_qpos)
        self._arm_dofs, self._arm_actuators = ints(index.arm_dofs), ints(index.arm_actuators)
        self._mass_index = wp.array(index.mass_index.astype(np.int32), dtype=wp.int32, device=self.device)
        self._torque_low, self._torque_high = floats(index.torque_low), floats(index.torque_high)
        self._gripper_actuators = ints(index.gripper_actuators)
        self._gripper_low, self._gripper_high = floats(index.gripper_ctrl_low), floats(index.gripper_ctrl_high)
        self.goal_pos = wp.zeros(nworld, dtype=wp.vec3, device=self.device)
        self.goal_ori = wp.zeros(nworld, dtype=wp.mat33, device=self.device)
        self.initial_joint = wp.zeros((nworld, ARM_DOF), dtype=wp.float32, device=self.device)
        self.gripper_command = wp.zeros((nworld, GRIPPER_ACTUATORS), dtype=wp.float32, device=self.device)

    def reset(self, mask: wp.array, initial_joint: wp.array, goal_pos: wp.array, goal_ori: wp.array) -> None:
        """Set the worlds where ``mask`` is 1 to a fresh controller: target joints and goal pose."""
        wp.launch(
            controller_reset,
            dim=self.nworld,
            device=self.device,
            inputs=[mask, initial_joint, goal_pos, goal_ori],
            outputs=[self.initial_joint, self.goal_pos, self.goal_ori, self.gripper_command],
        )

    def set_goal(self, action: wp.array, site_xpos: wp.array, site_xmat: wp.array) -> None:
        """Take a new env action's arm goal from the current pose (its first substep only)."""
        cfg = self.config
        wp.launch(
            osc_goal_from_action,
            dim=self.nworld,
            device=self.device,
            inputs=[
                action,
                site_xpos,
                site_xmat,
                self.index.eef_site,
                cfg.input_min,
                cfg.input_max,
                self._action_scale,
                self._action_offset,
            ],
            outputs=[self.goal_pos, self.goal_ori],
        )

    def apply(
        self,
        action: wp.array,
        qpos: wp.array,
        qvel: wp.array,
        mass: wp.array,
        qfrc_bias: wp.array,
        site_xpos: wp.array,
        site_xmat: wp.array,
        xanchor: wp.array,
        xaxis: wp.array,
        ctrl: wp.array,
    ) -> None:
        """One substep: write the arm's torques and the gripper's command into ``ctrl``."""
        cfg = self.config
        kd = 2.0 * np.sqrt(cfg.kp) * cfg.damping_ratio
        wp.launch(
            osc_pose_torques,
            dim=self.nworld,
            device=self.device,
            inputs=[
                qpos,
                qvel,
                mass,
                qfrc_bias,
                site_xpos,
                site_xmat,
                xanchor,
                xaxis,
                self.index.eef_site,
                self._arm_joints,
                self._arm_qpos,
                self._arm_dofs,
                self._arm_actuators,
                self._mass_index,
                cfg.kp,
                float(kd),
                cfg.nullspace_kp,
                self._torque_low,
                self._torque_high,
                self.goal_pos,
                self.goal_ori,
                self.initial_joint,
            ],
            outputs=[ctrl],
        )
        wp.launch(
            panda_gripper_ctrl,
            dim=self.nworld,
            device=self.device,
            inputs=[action, cfg.gripper_speed, self._gripper_actuators, self._gripper_low, self._gripper_high],
            outputs=[self.gripper_command, ctrl],
        )
