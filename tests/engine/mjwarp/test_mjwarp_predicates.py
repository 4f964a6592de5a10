"""The batched LIBERO goal predicates against LIBERO's own, on warp's CPU device.

For libero_10 tasks 0 (In a region), 2 (TurnOn, On a region of an object that must touch), 3
(Close a drawer's region, In that region as the drawer moves) and 4 (On an object), a real
LIBERO env is driven into states near success: each goal object is
dropped onto or into its target and recorded while it falls and settles, joints are set on
both sides of their thresholds, then everything at once. Every recorded ``MjData`` becomes one
world; LIBERO's ``_eval_predicate`` of each atom and ``_check_success`` are the oracle.

Values agree exactly on these states: the tests avoid qpos within float32 rounding of a
threshold, where a float32 engine and LIBERO's float64 may differ by design.
"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
import warp as wp

from vecsim.engine.mjwarp.predicates import GoalEvaluator
from vecsim.engine.mjwarp.tables import (
    GREATER,
    JOINT_RULES,
    JOINTS,
    MAX_JOINTS,
    GoalTable,
    UnsupportedGoal,
    compile_goal,
    supported_tasks,
)

from support.libero_recording import libero_env
from vecsim.engine.tasks._libero import ensure_config

pytestmark = pytest.mark.libero

CPU = "cpu"
TASKS = ("libero_10/0", "libero_10/2", "libero_10/3", "libero_10/4")
# Physics steps of 2 ms between recorded frames while an object settles, and how many frames.
STEPS_PER_FRAME, FRAMES = 25, 8
# The method of LIBERO's articulated object classes behind each joint predicate.
LIBERO_METHODS = {"open": "is_open", "close": "is_close", "turnon": "turn_on", "turnoff": "turn_off"}


def _frame(env) -> dict:
    """What the kernels read of the env now, and LIBERO's verdicts on it."""
    inner = env.env
    data = inner.sim.data._data
    goal = inner.parsed_problem["goal_state"]
    return {
        "qpos": np.array(data.qpos),
        "xpos": np.array(data.xpos),
        "site_xpos": np.array(data.site_xpos),
        "site_xmat": np.array(data.site_xmat).reshape(-1, 3, 3),
        "contacts": np.array(data.contact.geom[: data.ncon]).reshape(-1, 2),
        "atoms": [bool(inner._eval_predicate(atom)) for atom in goal],
        "success": bool(inner._check_success()),
    }


def _place(env, placed: str, target: str, lift: float) -> None:
    """Put ``placed``'s free joint ``lift`` metres above ``target``, at rest."""
    inner = env.env
    model, data = inner.sim.model._model, inner.sim.data._data
    mujoco.mj_forward(model, data)  # the target where the joints now put it (a drawer's region moves)
    if target in inner.object_sites_dict:
        point = np.array(data.site_xpos[model.site(target).id])
    else:
        point = np.array(data.xpos[inner.obj_body_id[target]])
    joint = model.joint(inner.get_object(placed).joints[0])
    data.qpos[joint.qposadr[0] : joint.qposadr[0] + 3] = point + [0.0, 0.0, lift]
    data.qvel[joint.dofadr[0] : joint.dofadr[0] + 6] = 0.0


def _set_joints(env, table: GoalTable, atom: int, offset: float) -> None:
    """Set an articulated atom's joints ``offset`` past its threshold (negative: short of it)."""
    data = env.env.sim.data._data
    sign = 1.0 if table.compare[atom] >= GREATER else -1.0
    for k in range(table.joint_count[atom]):
        data.qpos[table.joint_qpos[atom, k]] = table.threshold[atom] + sign * offset


def _settle(env, frames: list[dict]) -> None:
    inner = env.env
    model, data = inner.sim.model._model, inner.sim.data._data
    mujoco.mj_forward(model, data)
    frames.append(_frame(env))
    for _ in range(FRAMES):
        mujoco.mj_step(model, data, nstep=STEPS_PER_FRAME)
        frames.append(_frame(env))


def _near_success(env, table: GoalTable) -> list[dict]:
    """Frames of ``env`` from its init state through each atom made true alone, then all of them."""
    inner = env.env
    goal = inner.parsed_problem["goal_state"]
    start = inner.sim.get_state().flatten()
    frames = [_frame(env)]

    def make_true(i: int, predicate: str, args: list[str]) -> None:
        if table.kind[i] == JOINTS:
            _set_joints(env, table, i, 0.05)
        else:
            _place(env, args[0], args[1], 0.03 if predicate == "on" else 0.0)

    for i, (predicate, *args) in enumerate(goal):
        inner.sim.set_state_from_flattened(start)
        if table.kind[i] == JOINTS:
            for offset in (-0.05, -0.001, 0.001, 0.05):
                _set_joints(env, table, i, offset)
                mujoco.mj_forward(inner.sim.model._model, inner.sim.data._data)
                frames.append(_frame(env))
            continue
        make_true(i, predicate, args)
        _settle(env, frames)
    inner.sim.set_state_from_flattened(start)
    for i, (predicate, *args) in enumerate(goal):
        make_true(i, predicate, args)
    _settle(env, frames)
    inner.sim.set_state_from_flattened(start)
    mujoco.mj_forward(inner.sim.model._model, inner.sim.data._data)
    return frames


@pytest.fixture(scope="module", params=TASKS)
def scene(request):
    with libero_env(request.param) as env:
        table = compile_goal(env.env)
        yield env, table, _near_success(env, table)


def _evaluate(table: GoalTable, frames: list[dict], live: int | None = None) -> GoalEvaluator:
    """Each frame as one world, contacts concatenated with their world ids (MuJoCo Warp's layout)."""

    def stack(name: str, dtype) -> wp.array:
        return wp.array(np.stack([f[name] for f in frames]).astype(np.float32), dtype=dtype, device=CPU)

    geoms = np.concatenate([f["contacts"] for f in frames]).astype(np.int32)
    worlds = np.concatenate([np.full(len(f["contacts"]), w, np.int32) for w, f in enumerate(frames)])
    goal = GoalEvaluator(table, len(frames), CPU)
    goal.evaluate(
        stack("qpos", wp.float32),
        stack("xpos", wp.vec3),
        stack("site_xpos", wp.vec3),
        stack("site_xmat", wp.mat33),
        wp.array([len(geoms) if live is None else live], dtype=wp.int32, device=CPU),
        wp.array(geoms, dtype=wp.vec2i, device=CPU),
        wp.array(worlds, dtype=wp.int32, device=CPU),
    )
    return goal


def test_every_atom_matches_libero_on_states_near_success(scene):
    _, table, frames = scene
    expected = np.array([f["atoms"] for f in frames], dtype=np.int32)
    # The states exercise both verdicts of every atom.
    assert expected.any(axis=0).all() and (~expected.astype(bool)).any(axis=0).all(), expected
    holds = _evaluate(table, frames).holds.numpy()
    for atom, name in enumerate(table.atoms):
        np.testing.assert_array_equal(holds[:, atom], expected[:, atom], err_msg=name)


def test_success_matches_libero_on_states_near_success(scene):
    _, table, frames = scene
    expected = np.array([f["success"] for f in frames], dtype=np.int32)
    assert expected.any() and not expected.all()
    np.testing.assert_array_equal(_evaluate(table, frames).success.numpy(), expected)


def test_contacts_past_the_live_count_are_ignored(scene):
    _, table, frames = scene
    if not table.needs_contact.any():
        pytest.skip("this task's goal reads no contacts")
    assert _evaluate(table, frames).touching.numpy().any()
    # The same contact buffer with a live count of 0: its entries are stale.
    assert not _evaluate(table, frames, live=0).touching.numpy().any()


def test_compile_refuses_a_predicate_without_a_batched_form(scene):
    env, _, _ = scene
    inner = env.env
    goal = inner.parsed_problem["goal_state"]
    inner.parsed_problem["goal_state"] = [["up", goal[0][1]]]
    try:
        with pytest.raises(UnsupportedGoal, match="up"):
            compile_goal(inner)
    finally:
        inner.parsed_problem["goal_state"] = goal


def test_every_libero_10_task_compiles():
    assert supported_tasks("libero_10") == list(range(10))


@pytest.mark.parametrize("category", sorted(JOINT_RULES))
def test_joint_thresholds_follow_libero_objects(category):
    """Each articulated category's rule against its LIBERO class's own method, over a sweep."""
    ensure_config()
    from libero.libero.envs.base_object import OBJECTS_DICT
    from libero.libero.envs import objects  # noqa: F401  (registers LIBERO's object classes)

    obj = OBJECTS_DICT[category]()
    values = np.round(np.linspace(-2.5, 2.5, 501), 4)
    for predicate, (compare, ranges, end) in JOINT_RULES[category].items():
        threshold = end(obj.object_properties["articulation"][ranges])
        values = values[np.abs(values - threshold) > 1e-6]
        table = GoalTable(
            atoms=(f"({predicate} {category})",),
            kind=np.array([JOINTS], np.int32),
            body=np.zeros(1, np.int32),
            other_body=np.zeros(1, np.int32),
            site=np.zeros(1, np.int32),
            size=np.zeros((1, 3), np.float32),
            needs_contact=np.zeros(1, np.int32),
            geom_side=np.zeros((1, 1), np.int32),
            joint_qpos=np.zeros((1, MAX_JOINTS), np.int32),
            joint_count=np.ones(1, np.int32),
            any_joint=np.array([predicate in ("open", "turnon")], np.int32),
            compare=np.array([compare], np.int32),
            threshold=np.array([threshold], np.float32),
        )
        method = getattr(obj, LIBERO_METHODS[predicate])
        expected = np.array([bool(method(v)) for v in values], dtype=np.int32)
        goal = GoalEvaluator(table, len(values), CPU)
        goal.evaluate(
            wp.array(values[:, None].astype(np.float32), device=CPU),
            wp.zeros((len(values), 1), dtype=wp.vec3, device=CPU),
            wp.zeros((len(values), 1), dtype=wp.vec3, device=CPU),
            wp.zeros((len(values), 1), dtype=wp.mat33, device=CPU),
            wp.zeros(1, dtype=wp.int32, device=CPU),
            wp.zeros(0, dtype=wp.vec2i, device=CPU),
            wp.zeros(0, dtype=wp.int32, device=CPU),
        )
        np.testing.assert_array_equal(goal.holds.numpy()[:, 0], expected, err_msg=f"{category} {predicate}")
