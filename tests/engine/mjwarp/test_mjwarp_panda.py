"""The batched Panda controller and observables against robosuite's and LIBERO's, on warp's CPU.

A real LIBERO env (libero_10/0, state 0) settles and then takes ``ACTIONS``; every substep's
``MjData`` is recorded with what robosuite's ``OSC_POSE`` and gripper controllers wrote, and every
step's observation as LIBERO returns it. The kernels get the same fields, cast to float32 as
MuJoCo Warp holds them. A closed-loop run then drives the same env with the kernels' torques.

Tolerances: the kernels compute in float64 from float32 inputs, so the gap is the inputs'
rounding (relative 6e-8) carried through the operational-space inverse, whose gain is the
condition number of ``J M^-1 J^T`` (about 75 on these poses) times gains of up to 150 on
errors of a few cm: 1e-3 N m on torques of up to 80 N m, where the nullspace term alone is
about 1 N m. Goals and observables pass through no inverse: 1e-6 (1e-5 for angles from acos).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import warp as wp

from vecsim.engine.mjwarp.controller import PandaController
from vecsim.engine.mjwarp.observables import LIBERO_SAMPLE_SUBSTEP, PandaObservables
from vecsim.engine.mjwarp.tables import ObservableIndex, PandaIndex, mass_index
from vecsim.engine.tasks._libero import quat_to_axis_angle
from vecsim.engine.tasks._robot import PROPRIO_KEYS

from support.libero_recording import libero_env, recording, settle, snapshot

pytestmark = pytest.mark.libero

CPU = "cpu"
TORQUE_ATOL = 1e-3
POSE_ATOL = 1e-6
ANGLE_ATOL = 1e-5


def _actions() -> np.ndarray:
    """Deltas past the input range (clipped), one without rotation, gripper closing then opening."""
    rng = np.random.default_rng(40)
    actions = rng.uniform(-1.3, 1.3, size=(10, 7))
    actions[3, 3:6] = 0.0  # robosuite keeps the previous orientation goal
    actions[:5, 6], actions[5:, 6] = 1.0, -1.0
    actions[7, 6] = 0.0  # the gripper's command holds
    return actions


ACTIONS = _actions()


@dataclasses.dataclass
class Recorded:
    """The env after :data:`ACTIONS`, what it started from, and what was recorded on the way."""

    env: object
    index: PandaIndex
    legacy_mass_index: np.ndarray  # the same block in MuJoCo's legacy sparse qM
    obs_index: ObservableIndex
    start: dict[str, np.ndarray]
    substeps: list
    returned: list  # what env.step returned: robosuite's observables as LIBERO samples them


@pytest.fixture(scope="module")
def recorded():
    with libero_env("libero_10/0") as env:
        inner = env.env
        settle(env)
        robot = inner.robots[0]
        start = {
            "sim": inner.sim.get_state().flatten(),
            "initial_joint": np.array(robot.controller.initial_joint),
            "goal_pos": np.array(robot.controller.goal_pos),
            "goal_ori": np.array(robot.controller.goal_ori),
            "gripper": np.array(robot.gripper.current_action),
        }
        returned = []
        with recording(env) as substeps:
            for action in ACTIONS:
                raw, _, _, _ = env.step(action.tolist())
                returned.append(raw)
        index = PandaIndex.from_robosuite(inner)
        legacy = mass_index(inner.sim.model._model, index.arm_dofs, "qM")
        obs_index = ObservableIndex.from_robosuite(inner)
        yield Recorded(env, index, legacy, obs_index, start, substeps, returned)


def _stack(frames: list[dict[str, np.ndarray]], name: str, dtype=None) -> wp.array:
    values = np.stack([frame[name] for frame in frames]).astype(np.float32)
    return wp.array(values, dtype=dtype, device=CPU) if dtype else wp.array(values, device=CPU)


def _data(frames: list[dict[str, np.ndarray]]) -> dict[str, wp.array]:
    """The recorded fields as a MuJoCo Warp ``Data`` holds them: one world per frame."""
    arrays = {name: _stack(frames, name) for name in ("qpos", "qvel", "M", "qM", "qfrc_bias", "ctrl")}
    for name in ("site_xpos", "xanchor", "xaxis", "xpos"):
        arrays[name] = _stack(frames, name, wp.vec3)
    arrays["site_xmat"] = _stack(frames, "site_xmat", wp.mat33)
    arrays["xquat"] = _stack(frames, "xquat", wp.quat)
    return arrays


def _controller(index: PandaIndex, start: dict[str, np.ndarray], nworld: int) -> PandaController:
    ctl = PandaController(index, nworld, CPU)
    ctl.reset(
        wp.array(np.ones(nworld, dtype=np.int32), device=CPU),
        wp.array(np.tile(start["initial_joint"], (nworld, 1)).astype(np.float32), device=CPU),
        wp.array(np.tile(start["goal_pos"], (nworld, 1)).astype(np.float32), dtype=wp.vec3, device=CPU),
        wp.array(np.tile(start["goal_ori"], (nworld, 1, 1)).astype(np.float32), dtype=wp.mat33, device=CPU),
    )
    return ctl


def _apply(ctl: PandaController, actions: np.ndarray, data: dict[str, wp.array], mass: str = "M") -> None:
    ctl.apply(
        wp.array(actions.astype(np.float32), device=CPU),
        data["qpos"],
        data["qvel"],
        data[mass],
        data["qfrc_bias"],
        data["site_xpos"],
        data["site_xmat"],
        data["xanchor"],
        data["xaxis"],
        data["ctrl"],
    )


@pytest.mark.parametrize("mass", ["M", "qM"])
def test_arm_torques_match_robosuite_at_every_recorded_substep(recorded, mass):
    """From MuJoCo's CSR mass matrix (MuJoCo Warp 4's) and from its legacy sparse one."""
    index, start, substeps = recorded.index, recorded.start, recorded.substeps
    if mass == "qM":
        index = dataclasses.replace(index, mass_index=recorded.legacy_mass_index)
    data = _data([s.data for s in substeps])
    ctl = _controller(index, start, len(substeps))
    ctl.goal_pos.assign(np.stack([s.goal_pos for s in substeps]).astype(np.float32))
    ctl.goal_ori.assign(np.stack([s.goal_ori for s in substeps]).astype(np.float32))
    _apply(ctl, np.stack([s.action for s in substeps]), data, mass)
    expected = np.stack([s.data["ctrl"][index.arm_actuators] for s in substeps])
    got = data["ctrl"].numpy()[:, index.arm_actuators]
    assert np.abs(expected).max() > 1.0  # the torques compared are not all near zero
    np.testing.assert_allclose(got, expected, rtol=0, atol=TORQUE_ATOL)


def test_goals_gripper_and_ctrl_follow_robosuite_through_the_actions(recorded):
    index, start, substeps = recorded.index, recorded.start, recorded.substeps
    ctl = _controller(index, start, 1)
    ctl.gripper_command.assign(start["gripper"][None].astype(np.float32))
    kept = 0
    for number, sub in enumerate(substeps):
        data = _data([sub.data])
        action = sub.action[None]
        if sub.policy_step:
            previous = ctl.goal_ori.numpy()[0].copy()
            ctl.set_goal(wp.array(action.astype(np.float32), device=CPU), data["site_xpos"], data["site_xmat"])
            if not sub.action[3:6].any():
                np.testing.assert_array_equal(ctl.goal_ori.numpy()[0], previous)
                kept += 1
        _apply(ctl, action, data)
        np.testing.assert_allclose(ctl.goal_pos.numpy()[0], sub.goal_pos, atol=POSE_ATOL, err_msg=f"substep {number}")
        np.testing.assert_allclose(ctl.goal_ori.numpy()[0], sub.goal_ori, atol=POSE_ATOL, err_msg=f"substep {number}")
        np.testing.assert_allclose(ctl.gripper_command.numpy()[0], sub.gripper_command, atol=POSE_ATOL)
        np.testing.assert_allclose(
            data["ctrl"].numpy()[0], sub.data["ctrl"], atol=TORQUE_ATOL, err_msg=f"substep {number}"
        )
    assert kept == 1


def test_a_world_with_nan_state_leaves_the_other_worlds_torques_unchanged(recorded):
    index, start, substeps = recorded.index, recorded.start, recorded.substeps
    frames = [s.data for s in substeps[:4]]
    actions = np.stack([s.action for s in substeps[:4]])
    clean, broken = _data(frames), _data(frames)
    qvel = broken["qvel"].numpy()
    qvel[1] = np.nan
    broken["qvel"].assign(qvel)
    for data in (clean, broken):
        _apply(_controller(index, start, len(frames)), actions, data)
    assert np.isnan(broken["ctrl"].numpy()[1, index.arm_actuators]).any()
    np.testing.assert_array_equal(broken["ctrl"].numpy()[[0, 2, 3]], clean["ctrl"].numpy()[[0, 2, 3]])


def test_reset_sets_only_the_masked_worlds(recorded):
    index, start = recorded.index, recorded.start
    ctl = _controller(index, start, 3)
    ctl.gripper_command.fill_(0.5)
    ones = np.ones((3, 7), dtype=np.float32)
    ctl.reset(
        wp.array(np.array([0, 1, 0], dtype=np.int32), device=CPU),
        wp.array(ones, device=CPU),
        wp.array(ones[:, :3], dtype=wp.vec3, device=CPU),
        wp.array(np.tile(np.eye(3, dtype=np.float32), (3, 1, 1)), dtype=wp.mat33, device=CPU),
    )
    np.testing.assert_array_equal(ctl.initial_joint.numpy()[1], ones[1])
    np.testing.assert_array_equal(ctl.gripper_command.numpy()[:, 0], [0.5, 0.0, 0.5])
    np.testing.assert_allclose(ctl.initial_joint.numpy()[[0, 2]], np.tile(start["initial_joint"], (2, 1)), atol=1e-6)


def test_state_and_proprio_match_what_libero_returns(recorded):
    """``env.step``'s observation, rebuilt from MuJoCo Warp's view of the data right after the
    physics step of substep ``LIBERO_SAMPLE_SUBSTEP``: that substep's kinematics (recorded at
    its forward) and the joints after its integration (recorded at the next substep)."""
    per_action = len(recorded.substeps) // len(ACTIONS)
    frames = []
    for number in range(len(ACTIONS)):
        subs = recorded.substeps[number * per_action : (number + 1) * per_action]
        frame = dict(subs[LIBERO_SAMPLE_SUBSTEP].data)
        frame["qpos"] = subs[LIBERO_SAMPLE_SUBSTEP + 1].data["qpos"]
        frames.append(frame)
    data = _data(frames)
    obs = PandaObservables(recorded.obs_index, len(frames), CPU)
    obs.compute(data["qpos"], data["site_xpos"], data["xquat"])
    raws = recorded.returned
    state = np.stack(
        [
            np.concatenate([r["robot0_eef_pos"], quat_to_axis_angle(r["robot0_eef_quat"]), r["robot0_gripper_qpos"]])
            for r in raws
        ]
    )
    proprio = np.stack([np.concatenate([r[key] for key in PROPRIO_KEYS]) for r in raws])
    # The Panda's gripper points down: w is near 0 and changes sign, where a conversion that
    # folds q and -q together would disagree (docs/libero.md).
    assert (proprio[:, 20] < 0).any() and (proprio[:, 20] > 0).any()
    np.testing.assert_allclose(obs.state.numpy(), state, rtol=0, atol=ANGLE_ATOL)
    np.testing.assert_allclose(obs.proprio.numpy(), proprio, rtol=0, atol=POSE_ATOL)


def _eef_trajectory(recorded: Recorded, actions: np.ndarray, kernels: bool) -> np.ndarray:
    """The grip site after each action from the recording's start, robosuite's torques replaced
    by the kernels' when ``kernels`` (robosuite's controller still runs for its bookkeeping)."""
    inner = recorded.env.env
    robot, start = inner.robots[0], recorded.start
    inner.sim.set_state_from_flattened(start["sim"])
    inner.sim.forward()
    robot.controller.goal_pos, robot.controller.goal_ori = start["goal_pos"].copy(), start["goal_ori"].copy()
    robot.gripper.current_action = start["gripper"].copy()
    ctl = _controller(recorded.index, start, 1)
    ctl.gripper_command.assign(start["gripper"][None].astype(np.float32))
    original = robot.control

    def control(action: np.ndarray, policy_step: bool = False) -> None:
        original(action, policy_step=policy_step)
        data = _data([snapshot(inner.sim.data._data)])
        batch = np.asarray(action, dtype=np.float32)[None]
        if policy_step:
            ctl.set_goal(wp.array(batch, device=CPU), data["site_xpos"], data["site_xmat"])
        _apply(ctl, batch, data)
        inner.sim.data.ctrl[:] = data["ctrl"].numpy()[0]

    if kernels:
        robot.control = control
    try:
        trajectory = []
        for action in actions:
            recorded.env.step(action.tolist())
            trajectory.append(np.array(inner.sim.data.site_xpos[recorded.index.eef_site]))
        return np.array(trajectory)
    finally:
        if kernels:
            del robot.control


def test_an_arm_driven_by_the_kernels_follows_robosuites_trajectory(recorded):
    """Closed loop on CPU MuJoCo: the kernels' torques each substep (float32 inputs) against
    robosuite's own. The controlled arm damps the per-substep gap (below 1e-4 N m): over 20
    actions (1 s) the grip site stays within 1e-5 m of robosuite's (measured: under 1e-7 m)."""
    actions = np.random.default_rng(41).uniform(-1.0, 1.0, size=(20, 7))
    reference = _eef_trajectory(recorded, actions, kernels=False)
    driven = _eef_trajectory(recorded, actions, kernels=True)
    assert np.linalg.norm(reference[-1] - reference[0]) > 0.02  # the arm moved
    np.testing.assert_allclose(driven, reference, rtol=0, atol=1e-5)
