"""A robosuite env-step with robosuite's arithmetic and less around it (the ``exact`` step path).

robosuite 1.4's ``step`` runs, per physics substep: ``mj_forward``; the arm controller's
``update``, which runs ``mj_forward`` again on the same state; the OSC math in Python; ``mj_step``,
which runs a third full forward before integrating; and an ``update`` of every observable.
:class:`ExactStep` does the same arithmetic on the same inputs, so every state, observation,
reward and success is bit-identical to robosuite's (and LIBERO's, whose step is robosuite's):

- One forward's worth of MuJoCo work per substep, as ``mj_step`` alone. The two extra forwards
  recompute, from the same ``qpos``, ``qvel``, ``ctrl`` and ``qacc_warmstart``, what ``mj_step``'s
  own forward computes again before anything reads it, except their position and velocity
  stages, which the controller reads: those run once (``mj_fwdPosition``, ``mj_fwdVelocity`` and
  their sensors), and ``mj_checkPos``/``mj_checkVel`` + ``mj_step2`` finish ``mj_step``. Their
  acceleration stages leave nothing behind: MuJoCo (3.3) saves the solver's warmstart in the
  integrator, not in ``mj_forward``. The policy substep keeps its full ``mj_forward``: there
  ``robot.control`` reads the wrist's force/torque sensors, which the acceleration stage computes.
- The OSC controller's per-substep work is the same numpy and numba calls on arrays of the same
  shapes and memory layouts (numba compiles per layout), without robosuite's per-call lookups,
  property rebuilds and four Jacobian evaluations where one gives the same numbers. On every
  substep that work (after one ``mj_jacSite``) is one compiled call,
  :func:`vecsim.engine.tasks._osc_kernel.osc_substep`, which calls robosuite's numba kernels and numpy's
  own BLAS as robosuite's step does; where it cannot (:func:`vecsim.engine.tasks._osc_kernel.available`,
  a gripper other than robosuite's Panda gripper) the same calls run from Python. The controller,
  robot and gripper attributes the compiled call fills are handed over as fresh arrays after the
  policy substep, after the last substep and before any observable samples. After the policy
  substep, the other substeps run in one loop (:meth:`ExactStep._fused_substeps`).
- Observables run their sampling arithmetic per group of identical timers and their sensors only
  at the substeps where robosuite's would sample; success is checked once after ``_post_action``
  (LIBERO's step and vecsim both asked, with nothing in between).

On the policy substep (the first of each env-step) robosuite's ``set_goal`` sets the goal before
the compiled call, and the robot's recent-value buffers are pushed after it as robosuite's
``robot.control`` pushes them; where the compiled call is not used, or the controller was not
updated at that substep (as after a reset), that substep runs robosuite's own ``robot.control``.
Envs this does not cover (another controller, interpolators, an RK4 integrator, a control
callback, plugins, energy, a viewer) take the ``library`` path: the env's own ``step``. Observables with a delayer are updated every substep.
"""

from __future__ import annotations

import functools
import sys
from collections.abc import Callable
from typing import Any

import mujoco
import numpy as np

from vecsim.engine.tasks._base import log

STEP_PATHS: tuple[str, ...] = ("exact", "library")
DEFAULT_STEP_PATH = "exact"

StepFn = Callable[[np.ndarray], tuple[dict[str, Any], float, bool]]

_BADQPOS = int(mujoco.mjtWarning.mjWARN_BADQPOS)
_BADQVEL = int(mujoco.mjtWarning.mjWARN_BADQVEL)


def library_step(inner: Any) -> StepFn:
    """Return a step function that runs the env's own ``step`` and then its success check."""

    def step(action: np.ndarray) -> tuple[dict[str, Any], float, bool]:
        raw, reward, _, _ = inner.step(action)
        return raw, float(reward), bool(inner._check_success())

    return step


def make_step(inner: Any, path: str) -> tuple[StepFn, str]:
    """Return ``(step function, the path it takes)`` for ``path`` on the robosuite env ``inner``.

    ``exact`` falls back to ``library`` (logged) where :class:`ExactStep` does not cover the env.

    Raises:
        ValueError: ``path`` is not one of :data:`STEP_PATHS`.
    """
    if path not in STEP_PATHS:
        raise ValueError(f"step path must be one of {list(STEP_PATHS)}, got {path!r}")
    if path != "library":
        reason = ExactStep.unsupported(inner)
        if reason is None:
            return ExactStep(inner), path
        log.info("%s: the %s step path does not cover this env (%s): library step", type(inner).__name__, path, reason)
    return library_step(inner), "library"


class _Arm:
    """What the fast controller needs of one single-arm robot that does not change between steps."""

    def __init__(self, robot: Any, model: Any, data: Any) -> None:
        controller = robot.controller
        self.robot = robot
        self.site = model.site(controller.eef_name).id
        self.qpos_index = np.asarray(controller.qpos_index, dtype=np.intp)
        self.qvel_index = np.asarray(controller.qvel_index, dtype=np.intp)
        nv = model.nv
        self.jacp = np.zeros((3, nv))
        self.jacr = np.zeros((3, nv))
        # mj_fullM only copies entries of the sparse qM into a dense matrix; find where each
        # entry of the arm's block comes from by running it on qM's own indices (+1; 0 = none).
        marks = np.zeros((nv, nv))
        mujoco.mj_fullM(model, marks, np.arange(1, model.nM + 1, dtype=np.float64))
        block = marks[np.ix_(self.qvel_index, self.qvel_index)].astype(np.intp)
        if not block.all():
            raise _Unsupported("the arm's mass matrix block has structural zeros")
        # Gathered transposed and viewed back: the block comes out Fortran-ordered, the layout
        # robosuite's fancy indexing gives (its numba kernels are compiled per layout).
        self.mass_gather_t = np.ascontiguousarray((block - 1).T)
        self.gripper_ids = np.asarray([model.actuator(name).id for name in robot.gripper.actuators], dtype=np.intp)
        self.arm_ids = np.asarray(robot._ref_joint_actuator_indexes, dtype=np.intp)
        self.control_dim = controller.control_dim
        self.action_dim = robot.action_dim
        # What osc_substep fills, in the layouts robosuite's update gives (Fortran-ordered
        # Jacobian and mass-matrix copies), handed to the controller by ArmStep.hand_over.
        dof = len(self.qvel_index)
        self.ee_pos = np.zeros(3)
        self.ee_ori_mat = np.zeros((3, 3))
        self.ee_pos_vel = np.zeros(3)
        self.ee_ori_vel = np.zeros(3)
        self.joint_pos = np.zeros(dof)
        self.joint_vel = np.zeros(dof)
        self.j_pos = np.zeros((3, dof), order="F")
        self.j_ori = np.zeros((3, dof), order="F")
        self.j_full = np.zeros((6, dof), order="F")
        self.mass_matrix = np.zeros((dof, dof), order="F")
        self.torques = np.zeros(dof)
        self.clipped = np.zeros(dof)
        self.gripper_action = np.zeros(len(self.gripper_ids))
        self.wrench = np.zeros(6)


class _Unsupported(Exception):
    pass


@functools.cache
def osc_kernel() -> Any:
    # Imports robosuite and numba: loaded with the first exact step, not with vecsim.engine.tasks.
    from vecsim.engine.tasks import _osc_kernel

    return _osc_kernel


@functools.cache
def _fused_controller_available() -> bool:
    """Whether the compiled controller can run here; False (logged once) where its module cannot
    even be loaded, e.g. numba finding no writable place for its cache."""
    try:
        return bool(osc_kernel().available())
    except Exception as exc:  # noqa: BLE001 - the controller from Python is the same arithmetic
        log.warning(
            "the compiled OSC controller cannot be loaded (%s: %s): the controller runs from Python",
            type(exc).__name__,
            exc,
        )
        return False


@functools.cache
def _robosuite() -> Any:
    # robosuite is imported when the first env is made, not with vecsim.engine.tasks.
    import robosuite.controllers.base_controller
    import robosuite.controllers.osc
    import robosuite.models.grippers.panda_gripper
    import robosuite.robots.manipulator
    import robosuite.robots.single_arm
    import robosuite.utils.control_utils
    import robosuite.utils.transform_utils

    return robosuite


def _check_arm(robot: Any) -> None:
    rs = _robosuite()
    Controller = rs.controllers.base_controller.Controller
    OperationalSpaceController = rs.controllers.osc.OperationalSpaceController
    Manipulator = rs.robots.manipulator.Manipulator
    SingleArm = rs.robots.single_arm.SingleArm
    controller = robot.controller
    if type(robot).control is not SingleArm.control or type(robot).grip_action is not Manipulator.grip_action:
        raise _Unsupported(f"robot {type(robot).__name__} is not a plain single arm")
    if not robot.has_gripper:
        raise _Unsupported("an arm without a gripper")
    if type(controller) is not OperationalSpaceController or type(controller).update is not Controller.update:
        raise _Unsupported(f"controller {type(controller).__name__} is not robosuite's OSC")
    if controller.impedance_mode != "fixed":
        raise _Unsupported(f"impedance mode {controller.impedance_mode!r}")
    if controller.interpolator_pos is not None or controller.interpolator_ori is not None:
        raise _Unsupported("controller interpolators")


class ExactStep:
    """robosuite's ``step`` for one env, bit-identical, with less work per physics substep.

    Called with an action it returns ``(observations, reward, success)``: ``observations`` maps
    each enabled, active observable to its value (robosuite's observation dict without the
    per-modality concatenations). The env's own step counters, ``done``, controller, gripper and
    observable state advance exactly as its ``step`` advances them.
    """

    def __init__(self, inner: Any) -> None:
        reason = self.unsupported(inner)
        if reason is not None:
            raise ValueError(f"the exact step path does not cover this env: {reason}")
        self.env = inner
        self.model = inner.sim.model._model
        self.data = inner.sim.data._data
        self.arms = [_Arm(robot, self.model, self.data) for robot in inner.robots]
        data = self.data
        # MjData's arrays for osc_substep (views of buffers MuJoCo never moves).
        self.data_arrays = (data.qpos, data.qvel, data.qM, data.qfrc_bias, data.ctrl, data.site_xpos, data.site_xmat)
        # The warning counters mj_checkPos/mj_checkVel raise (views of MjData's, as the arrays).
        self.bad_qpos, self.bad_qvel = data.warning[_BADQPOS], data.warning[_BADQVEL]
        # False: the non-policy substeps' controller runs from Python (bench/bench_controller_parts.py).
        self.fused = _fused_controller_available()
        # False: the policy substep runs robosuite's robot.control; the other substeps the
        # general loop (bench/bench_robot_step.py --second-pass, the step before those changes).
        self.fused_policy = True
        self.substep_loop = True

    @staticmethod
    def unsupported(inner: Any) -> str | None:
        """Return why :class:`ExactStep` does not cover ``inner``, or None where it does."""
        from robosuite.environments.base import MujocoEnv
        from robosuite.environments.robot_env import RobotEnv
        from robosuite.utils.observables import Observable

        steps = {MujocoEnv.step}
        pre_actions = {RobotEnv._pre_action}
        # A LIBERO env's module is loaded already; importing LIBERO otherwise may ask on stdin.
        libero_domain = sys.modules.get("libero.libero.envs.bddl_base_domain")
        if libero_domain is not None:
            steps.add(libero_domain.BDDLBaseDomain.step)
            pre_actions.add(libero_domain.BDDLBaseDomain._pre_action)
        env_type = type(inner)
        if env_type.step not in steps or env_type._pre_action not in pre_actions:
            return f"{env_type.__name__} overrides step or _pre_action"
        if env_type._update_observables is not MujocoEnv._update_observables:
            return f"{env_type.__name__} overrides _update_observables"
        if getattr(inner, "viewer", None) is not None:
            return "an on-screen viewer"
        model = inner.sim.model._model
        if model.opt.integrator == int(mujoco.mjtIntegrator.mjINT_RK4):
            return "the RK4 integrator (mj_step2 integrates with Euler)"
        if mujoco.get_mjcb_control() is not None:
            return "a MuJoCo control callback"
        if model.nplugin:
            return "MuJoCo plugins"
        energy_sensors = (int(mujoco.mjtSensor.mjSENS_E_POTENTIAL), int(mujoco.mjtSensor.mjSENS_E_KINETIC))
        if (
            model.opt.enableflags & int(mujoco.mjtEnableBit.mjENBL_ENERGY)
            or np.isin(model.sensor_type, energy_sensors).any()
        ):
            return "energy computation (mj_forward's energy stages)"
        if mujoco.get_mjcb_sensor() is not None:
            return "a MuJoCo sensor callback"
        if any(type(obs).update is not Observable.update for obs in inner._observables.values()):
            return "an observable with its own update"
        if inner.action_dim == 4:
            return "a 4-dim action (LIBERO's step converts 7-dim ones to it)"
        try:
            for robot in inner.robots:
                _check_arm(robot)
        except _Unsupported as exc:
            return str(exc)
        return None

    def __call__(self, action: np.ndarray) -> tuple[dict[str, Any], float, bool]:
        env, model, data = self.env, self.model, self.data
        if env.viewer is not None:
            raw, reward, _, _ = env.step(action)
            return raw, float(reward), bool(env._check_success())
        if env.done:
            raise ValueError("executing action in terminated episode")
        if len(action) != env.action_dim:
            raise ValueError(f"expected an action of {env.action_dim} floats, got {len(action)}")
        env.timestep += 1
        substeps = int(env.control_timestep / env.model_timestep)
        plan = self._observable_plan(substeps)
        arms = []
        cutoff = 0
        for arm in self.arms:
            _check_arm(arm.robot)
            arms.append(ArmStep(arm, action[cutoff : cutoff + arm.action_dim], model))
            cutoff += arm.action_dim
        fused: list[ArmStep] = []
        for substep in range(substeps):
            policy_step = substep == 0
            if substep == 1 and self.substep_loop and fused and len(fused) == len(arms):
                self._fused_substeps(fused, substeps, plan)
                break
            self._forward(policy_step)
            for arm in arms:
                controller = arm.arm.robot.controller
                if arm.fused:
                    arm.fused_control(model, data)
                    continue
                updated = controller.new_update
                if updated:
                    self._update(arm.arm, controller)
                if policy_step:
                    # The compiled policy substep computes its update from the state now; without
                    # a new update robosuite steps from the controller's last one (after a reset,
                    # another pose's), so that substep stays robosuite's own.
                    fuse = self.fused and self.fused_policy and updated
                    if fuse and arm.start_fused(controller, self.data_arrays, policy_step=True):
                        arm.policy_control(model, data)
                        fused.append(arm)
                        continue
                    arm.arm.robot.control(arm.action, policy_step=True)
                    if self.fused and arm.start_fused(controller, self.data_arrays):
                        fused.append(arm)
                else:
                    arm.control(controller, data)
            self._integrate()
            if substep and (substep == substeps - 1 or plan is None or plan.fires[substep]):
                # At the end of the step, and where observables (which may read the controller) sample.
                for arm in fused:
                    arm.hand_over()
            if plan is None:
                env._update_observables()
            else:
                plan.sample(substep, env)
        if plan is not None:
            plan.finish()
        env.cur_time += env.control_timestep
        reward, _, _ = env._post_action(action)
        success = bool(env._check_success())
        observations = {name: obs.obs for name, obs in env._observables.items() if obs._enabled and obs._active}
        return observations, float(reward), success

    def _fused_substeps(self, fused: list[ArmStep], substeps: int, plan: _ObservablePlan | None) -> None:
        # Substeps 1.. of an env-step whose arms all run the compiled controller: the loop's
        # _forward(False), fused_control, _integrate, hand_over and observable updates, the same
        # calls in the same order, with the loop's lookups done once.
        env, model, data = self.env, self.model, self.data
        fwd_position, sensor_pos = mujoco.mj_fwdPosition, mujoco.mj_sensorPos
        fwd_velocity, sensor_vel = mujoco.mj_fwdVelocity, mujoco.mj_sensorVel
        check_pos, check_vel, step1, step2 = mujoco.mj_checkPos, mujoco.mj_checkVel, mujoco.mj_step1, mujoco.mj_step2
        jac_site, osc_substep = mujoco.mj_jacSite, osc_kernel().osc_substep
        bad_qpos, bad_qvel = self.bad_qpos, self.bad_qvel
        calls = [(arm.arm.jacp, arm.arm.jacr, arm.arm.site, arm.kernel_args) for arm in fused]
        last = substeps - 1
        for substep in range(1, substeps):
            fwd_position(model, data)
            sensor_pos(model, data)
            fwd_velocity(model, data)
            sensor_vel(model, data)
            for jacp, jacr, site, kernel_args in calls:
                jac_site(model, data, jacp, jacr, site)
                osc_substep(*kernel_args)
            bad = bad_qpos.number + bad_qvel.number
            check_pos(model, data)
            check_vel(model, data)
            if bad_qpos.number + bad_qvel.number != bad:
                step1(model, data)
            step2(model, data)
            if plan is None:
                for arm in fused:
                    arm.hand_over()
                env._update_observables()
                continue
            fires = plan.fires[substep]
            if fires or substep == last:
                for arm in fused:
                    arm.hand_over()
                for _, obs, elapsed, sampled in fires:
                    obs._time_since_last_sample = elapsed
                    obs._sampled = sampled
                    obs.update(timestep=plan.timestep, obs_cache=env._obs_cache)

    def _forward(self, policy_step: bool) -> None:
        # The substep's mj_forward, and Controller.update's. Non-policy substeps need only the
        # position and velocity stages with their sensors: the acceleration stage's outputs are
        # computed again by mj_step2, from the same inputs, before anything reads them. The
        # policy substep's robot.control reads acceleration-stage sensors: a full forward there.
        model, data = self.model, self.data
        if policy_step:
            mujoco.mj_forward(model, data)
        else:
            mujoco.mj_fwdPosition(model, data)
            mujoco.mj_sensorPos(model, data)
            mujoco.mj_fwdVelocity(model, data)
            mujoco.mj_sensorVel(model, data)

    def _integrate(self) -> None:
        # mj_step = checks + mj_forward + integration; the forward's position and velocity
        # stages are current (only ctrl changed since, read in the acceleration stage), so
        # mj_step2 finishes it.
        model, data = self.model, self.data
        bad_qpos, bad_qvel = self.bad_qpos, self.bad_qvel
        bad = bad_qpos.number + bad_qvel.number
        mujoco.mj_checkPos(model, data)
        mujoco.mj_checkVel(model, data)
        if bad_qpos.number + bad_qvel.number != bad:
            # The checks reset the data; mj_step's forward then starts from the reset state.
            mujoco.mj_step1(model, data)
        mujoco.mj_step2(model, data)

    def _observable_plan(self, substeps: int) -> _ObservablePlan | None:
        return _observable_plan(self.env, substeps)

    def _update(self, arm: _Arm, controller: Any) -> None:
        # Controller.update with the same copies and layouts; its mj_forward is the substep's
        # (the same state, ctrl and warmstart: the same numbers).
        model, data = self.model, self.data
        site = arm.site
        controller.ee_pos = np.array(data.site_xpos[site])
        controller.ee_ori_mat = np.array(data.site_xmat[site].reshape([3, 3]))
        jacp, jacr = arm.jacp, arm.jacr
        # One call fills both Jacobians with the numbers robosuite's four separate calls give.
        mujoco.mj_jacSite(model, data, jacp, jacr, site)
        controller.ee_pos_vel = np.dot(jacp, data.qvel)
        controller.ee_ori_vel = np.dot(jacr, data.qvel)
        controller.joint_pos = data.qpos[arm.qpos_index]
        controller.joint_vel = data.qvel[arm.qvel_index]
        j_pos = jacp[:, arm.qvel_index]
        j_ori = jacr[:, arm.qvel_index]
        controller.J_pos = j_pos
        controller.J_ori = j_ori
        controller.J_full = np.concatenate((j_pos, j_ori))
        controller.mass_matrix = data.qM[arm.mass_gather_t].T
        controller.new_update = False


class ArmStep:
    """One arm's share of one env-step: its action and what stays fixed over the substeps."""

    def __init__(self, arm: _Arm, action: np.ndarray, model: Any) -> None:
        controller = arm.robot.controller
        self.arm = arm
        self.action = action
        self.gripper_action = action[arm.control_dim :]
        self.kp_pos = np.array(controller.kp[0:3])
        self.kp_ori = np.array(controller.kp[3:6])
        self.kd_pos = controller.kd[0:3]
        self.kd_ori = controller.kd[3:6]
        self.uncoupling = controller.uncoupling
        self.torque_low = model.actuator_ctrlrange[arm.arm_ids, 0]
        self.torque_high = model.actuator_ctrlrange[arm.arm_ids, 1]
        gripper = arm.robot.gripper
        self.gripper_step = None
        if type(gripper).format_action is _robosuite().models.grippers.panda_gripper.PandaGripper.format_action:
            # PandaGripper.format_action's increment, which depends on the action only.
            self.gripper_step = np.array([-1.0, 1.0]) * gripper.speed * np.sign(self.gripper_action)
        ctrl_range = model.actuator_ctrlrange[arm.gripper_ids]
        self.gripper_bias = 0.5 * (ctrl_range[:, 1] + ctrl_range[:, 0])
        self.gripper_weight = 0.5 * (ctrl_range[:, 1] - ctrl_range[:, 0])
        self.fused = False
        self.kernel_args: tuple[Any, ...] = ()

    def start_fused(self, controller: Any, data_arrays: tuple[np.ndarray, ...], policy_step: bool = False) -> bool:
        """Run this step's substeps from here on through ``osc_substep`` if it can.

        It can for robosuite's Panda gripper (whose ``format_action`` it computes) with one
        action per gripper actuator. The call's arguments are fixed for the rest of the step and
        gathered now: MuJoCo's arrays (``data_arrays``, see :class:`ExactStep`), the arm's, the
        controller's goal (as ``run_controller`` copies it, which keeps its layout), gains and
        initial joints, and the buffers it fills. After the policy substep's ``robot.control``,
        or (``policy_step``) in its place, where it first sets the goal with robosuite's
        ``set_goal`` (:meth:`policy_control` does the rest).
        """
        arm = self.arm
        current = arm.robot.gripper.current_action
        shape = arm.gripper_action.shape
        if self.gripper_step is None or self.gripper_step.shape != shape or np.shape(current) != shape:
            return False
        if not controller.new_update and not policy_step:
            return False
        if policy_step:
            # The goal osc_substep reads is the one set_goal is about to set: gathered then.
            controller.set_goal(self.action[: arm.control_dim])
        arm.gripper_action[:] = current
        self.kernel_args = (
            arm.site,
            *data_arrays,
            arm.jacp,
            arm.jacr,
            arm.qpos_index,
            arm.qvel_index,
            arm.mass_gather_t,
            arm.arm_ids,
            arm.gripper_ids,
            np.array(controller.goal_pos),
            np.array(controller.goal_ori),
            controller.kp,
            controller.kd,
            controller.initial_joint,
            self.torque_low,
            self.torque_high,
            self.uncoupling,
            self.gripper_step,
            self.gripper_bias,
            self.gripper_weight,
            arm.ee_pos,
            arm.ee_ori_mat,
            arm.ee_pos_vel,
            arm.ee_ori_vel,
            arm.joint_pos,
            arm.joint_vel,
            arm.j_pos,
            arm.j_ori,
            arm.j_full,
            arm.mass_matrix,
            arm.torques,
            arm.clipped,
            arm.gripper_action,
            arm.wrench,
        )
        self.fused = True
        return True

    def fused_control(self, model: Any, data: Any) -> None:
        """Controller.update and :meth:`control` for a non-policy substep, in one compiled call."""
        arm = self.arm
        mujoco.mj_jacSite(model, data, arm.jacp, arm.jacr, arm.site)
        osc_kernel().osc_substep(*self.kernel_args)

    def policy_control(self, model: Any, data: Any) -> None:
        """SingleArm.control for the policy substep, after :meth:`start_fused` set the goal.

        robosuite's ``run_controller``, torque clip and ``grip_action`` are what ``osc_substep``
        computes (its update is the one :meth:`ExactStep._update` just made, from the same
        state); then the robot's recent-value buffers take what ``control`` pushes, computed as
        it computes them.
        """
        self.fused_control(model, data)
        self.hand_over()
        robot = self.arm.robot
        controller = robot.controller
        transform = _robosuite().utils.transform_utils
        robot.recent_qpos.push(robot._joint_positions)
        robot.recent_actions.push(self.action)
        robot.recent_torques.push(robot.torques)
        robot.recent_ee_forcetorques.push(np.concatenate((robot.ee_force, robot.ee_torque)))
        robot.recent_ee_pose.push(np.concatenate((controller.ee_pos, transform.mat2quat(controller.ee_ori_mat))))
        robot.recent_ee_vel.push(np.concatenate((controller.ee_pos_vel, controller.ee_ori_vel)))
        # The end effector's acceleration: the mean of the recent velocities' differences.
        robot.recent_ee_vel_buffer.push(np.concatenate((controller.ee_pos_vel, controller.ee_ori_vel)))
        diffs = np.vstack(
            [robot.recent_ee_acc.current, robot.control_freq * np.diff(robot.recent_ee_vel_buffer.buf, axis=0)]
        )
        window = np.ones(10) / 10.0
        robot.recent_ee_acc.push(np.array([np.convolve(column, window, mode="valid")[0] for column in diffs.T]))

    def hand_over(self) -> None:
        """Leave the controller, robot and gripper holding what the last ``osc_substep`` computed.

        As fresh arrays, as robosuite's update and control leave them: nothing handed out before
        changes when the next substep's call refills the buffers.
        """
        arm = self.arm
        robot = arm.robot
        controller = robot.controller
        controller.ee_pos = arm.ee_pos.copy()
        controller.ee_ori_mat = arm.ee_ori_mat.copy()
        controller.ee_pos_vel = arm.ee_pos_vel.copy()
        controller.ee_ori_vel = arm.ee_ori_vel.copy()
        controller.joint_pos = arm.joint_pos.copy()
        controller.joint_vel = arm.joint_vel.copy()
        controller.J_pos = arm.j_pos.copy(order="F")
        controller.J_ori = arm.j_ori.copy(order="F")
        controller.J_full = arm.j_full.copy(order="F")
        controller.mass_matrix = arm.mass_matrix.copy(order="F")
        controller.torques = arm.torques.copy()
        controller.new_update = True
        robot.torques = arm.clipped.copy()
        robot.gripper.current_action = arm.gripper_action.copy()

    def control(self, controller: Any, data: Any) -> None:
        # SingleArm.control for a non-policy substep with OSC's run_controller inside: the same
        # operations, in the same order, on arrays of the same shapes and layouts.
        utils = _robosuite().utils.control_utils
        arm = self.arm
        robot = arm.robot
        ori_error = utils.orientation_error(np.array(controller.goal_ori), controller.ee_ori_mat)
        position_error = np.array(controller.goal_pos) - controller.ee_pos
        desired_force = np.multiply(position_error, self.kp_pos) + np.multiply(-controller.ee_pos_vel, self.kd_pos)
        desired_torque = np.multiply(ori_error, self.kp_ori) + np.multiply(-controller.ee_ori_vel, self.kd_ori)
        mass_matrix = controller.mass_matrix
        j_full = controller.J_full
        lambda_full, lambda_pos, lambda_ori, nullspace_matrix = utils.opspace_matrices(
            mass_matrix, j_full, controller.J_pos, controller.J_ori
        )
        if self.uncoupling:
            decoupled_wrench = np.concatenate([np.dot(lambda_pos, desired_force), np.dot(lambda_ori, desired_torque)])
        else:
            decoupled_wrench = np.dot(lambda_full, np.concatenate([desired_force, desired_torque]))
        torques = np.dot(j_full.T, decoupled_wrench) + data.qfrc_bias[arm.qvel_index]
        torques += utils.nullspace_torques(
            mass_matrix, nullspace_matrix, controller.initial_joint, controller.joint_pos, controller.joint_vel
        )
        controller.torques = torques
        controller.new_update = True
        robot.torques = np.clip(torques, self.torque_low, self.torque_high)
        gripper = robot.gripper
        if self.gripper_step is None:
            gripper_action = gripper.format_action(self.gripper_action)
        else:
            gripper_action = gripper.current_action = np.clip(gripper.current_action + self.gripper_step, -1.0, 1.0)
        data.ctrl[arm.gripper_ids] = self.gripper_bias + self.gripper_weight * gripper_action
        data.ctrl[arm.arm_ids] = robot.torques


class _ObservablePlan:
    """When each observable samples during one env-step, worked out before the substeps run.

    robosuite's ``Observable.update`` advances a timer by the physics timestep and samples its
    sensor at the first substep of each sampling period. With no delayer the timers' arithmetic
    depends only on their own values, so observables whose timers agree form a group whose
    arithmetic runs once; a sampling observable is handed its timer as it was before that
    substep and runs its own ``update`` (sensor, corrupter, filter, in robosuite's order).
    """

    def __init__(self, env: Any, substeps: int) -> None:
        timestep = env.model_timestep
        groups: dict[tuple[float, bool, float, float], list[tuple[int, Any]]] = {}
        for index, obs in enumerate(env._observables.values()):
            if obs._enabled:
                key = (obs._time_since_last_sample, obs._sampled, obs._sampling_timestep, obs._current_delay)
                groups.setdefault(key, []).append((index, obs))
        self.timestep = timestep
        self.fires: list[list[tuple[int, Any, float, bool]]] = [[] for _ in range(substeps)]
        self.finals: list[tuple[list[tuple[int, Any]], float, bool]] = []
        for (elapsed, sampled, period, delay), members in groups.items():
            for substep in range(substeps):
                advanced = elapsed + timestep
                if not sampled and (period - delay >= advanced or advanced >= period):
                    self.fires[substep].extend((index, obs, elapsed, sampled) for index, obs in members)
                    sampled, delay = True, 0.0
                if advanced >= period:
                    advanced %= period
                    sampled = False
                elapsed = advanced
            self.finals.append((members, elapsed, sampled))
        for fired in self.fires:
            fired.sort(key=lambda item: item[0])

    def sample(self, substep: int, env: Any) -> None:
        """Run the ``update`` of each observable that samples at ``substep``, in the env's order."""
        for _, obs, elapsed, sampled in self.fires[substep]:
            obs._time_since_last_sample = elapsed
            obs._sampled = sampled
            obs.update(timestep=self.timestep, obs_cache=env._obs_cache)

    def finish(self) -> None:
        """Leave every observable's timer where robosuite's per-substep updates leave it."""
        for members, elapsed, sampled in self.finals:
            for _, obs in members:
                obs._time_since_last_sample = elapsed
                obs._sampled = sampled


def _observable_plan(env: Any, substeps: int) -> _ObservablePlan | None:
    from robosuite.utils.observables import NO_DELAY

    # A delayer draws a new delay at every sample, which moves the next sampling time: those
    # envs update every observable at every substep, as robosuite does.
    if any(obs._enabled and obs._delayer is not NO_DELAY for obs in env._observables.values()):
        return None
    return _ObservablePlan(env, substeps)
