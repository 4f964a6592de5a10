"""The batched LIBERO goal predicates against LIBERO's own, on warp's CPU device, every libero_10 task.

A real LIBERO env of each task is driven into states near success: each placed goal object is
dropped into its region (yawed to fit) or just above whatever lies under its target, then just
past the target's edge, and recorded while it falls and settles; joints are set on both sides
of their thresholds; then every atom is made true at once (objects sharing a region spread
across it). The atoms: In a region (tasks 0, 1, 3, 5, 7, 9), On a region with a parent to touch
(2, 8) or without (6), On an object (4, 6), Close (3, 9), TurnOn (2, 8). Every recorded
``MjData`` becomes one world; LIBERO's ``_eval_predicate`` of each atom and ``_check_success``
are the oracle. Every atom and the success are seen both true and false, and each contact an
atom reads decides some verdict. (Task 5's book rests in its caddy compartment with its origin
below the region's box, so LIBERO holds it In only while it falls in.)

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
    IN_REGION,
    JOINT_RULES,
    JOINTS,
    MAX_JOINTS,
    ON_OBJECT,
    GoalTable,
    UnsupportedGoal,
    compile_goal,
    supported_tasks,
)

from support.libero_recording import libero_env
from vecsim.engine.tasks._libero import ensure_config

pytestmark = pytest.mark.libero

CPU = "cpu"
TASKS = tuple(f"libero_10/{i}" for i in range(10))
# Physics steps of 2 ms between recorded frames while an object settles, and how many frames.
STEPS_PER_FRAME, FRAMES = 25, 8
# How far above its target's top an object is dropped, and past which multiple of a target's
# half-size (or of On's reach in x-y, LIBERO's 3 cm) a near miss lands.
CLEARANCE, MISS, ON_OBJECT_RADIUS = 0.01, 1.25, 0.03
# How far towards its edges (a fraction of its half-size) objects sharing a region are spread.
SPREAD = 0.6
# Yaws tried to fit an object into its region, and the corners of a box about its centre.
YAWS = np.radians(np.arange(0.0, 180.0, 5.0))
CORNER_SIGNS = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
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


def _boxes(model, data, geoms: np.ndarray) -> np.ndarray:
    """World corners of the bounding boxes of ``geoms``, ``[geoms, 8, 3]``."""
    local = model.geom_aabb[geoms, None, :3] + CORNER_SIGNS * model.geom_aabb[geoms, None, 3:]
    rot = data.geom_xmat[geoms].reshape(-1, 3, 3)
    return data.geom_xpos[geoms, None] + np.einsum("gij,gcj->gci", rot, local)


def _support(inner, body: int, low: np.ndarray, high: np.ndarray) -> float:
    """The highest top of a colliding geom's bounding box over the x-y box ``low``-``high``,
    the robot's and those of the free ``body`` aside."""
    model, data = inner.sim.model._model, inner.sim.data._data
    robot = model.body(inner.robots[0].robot_model.root_body).id
    roots = model.body_rootid[model.geom_bodyid]
    collides = (model.geom_contype | model.geom_conaffinity) != 0
    geoms = np.flatnonzero(collides & (roots != model.body_rootid[robot]) & (roots != body))
    boxes = _boxes(model, data, geoms)
    over = np.all((boxes.min(axis=1)[:, :2] < high) & (low < boxes.max(axis=1)[:, :2]), axis=1)
    return float(boxes[over, :, 2].max())


def _yaw_to_fit(offsets: np.ndarray, shift: np.ndarray, half: np.ndarray) -> float:
    """The yaw about z that keeps ``offsets`` (corners about the origin) most inside a box of
    half-sizes ``half`` whose centre is ``shift`` away from the origin."""

    def overflow(yaw: float) -> float:
        c, s = np.cos(yaw), np.sin(yaw)
        xy = offsets[:, :2] @ np.array([[c, s], [-s, c]]) + shift[:2]
        return float((np.abs(xy) - half[:2]).max())

    return min(YAWS, key=overflow)


def _drop(env, table: GoalTable, atom: int, shift: np.ndarray, inside: bool) -> None:
    """Put the object of a placement atom at rest ``shift`` away from its target's centre:
    inside its region (origin at the centre's height, bottom clear of the region's floor), or
    ``CLEARANCE`` above whatever lies under it there."""
    inner = env.env
    model, data = inner.sim.model._model, inner.sim.data._data
    mujoco.mj_forward(model, data)  # the target where the joints now put it (a drawer's region moves)
    _, placed, _ = inner.parsed_problem["goal_state"][atom]
    body = table.body[atom]
    geoms = np.array([model.geom(name).id for name in inner.get_object(placed).contact_geoms])
    offsets = _boxes(model, data, geoms).reshape(-1, 3) - data.xpos[body]
    yaw = 0.0
    if table.kind[atom] == ON_OBJECT:
        centre = np.array(data.xpos[table.other_body[atom]])
    else:
        site = table.site[atom]
        centre = np.array(data.site_xpos[site])
        half = np.abs(data.site_xmat[site].reshape(3, 3) @ table.size[atom])
        yaw = _yaw_to_fit(offsets, shift, half)
        c, s = np.cos(yaw), np.sin(yaw)
        offsets = offsets @ np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    point = centre + shift
    if inside:
        point[2] = max(centre[2], centre[2] - half[2] + CLEARANCE - offsets[:, 2].min())
    else:
        under = _support(inner, body, point[:2] + offsets[:, :2].min(0), point[:2] + offsets[:, :2].max(0))
        point[2] = under + CLEARANCE - offsets[:, 2].min()
    joint = model.joint(inner.get_object(placed).joints[0])
    qpos = data.qpos[joint.qposadr[0] : joint.qposadr[0] + 7]
    turn = np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])
    quat = np.zeros(4)
    mujoco.mju_mulQuat(quat, turn, qpos[3:].copy())
    qpos[:3], qpos[3:] = point, quat
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


def _miss(env, table: GoalTable, atom: int) -> np.ndarray:
    """A shift just past the edge of an atom's target in x: its region, or LIBERO's 3 cm."""
    if table.kind[atom] == ON_OBJECT:
        return np.array([MISS * ON_OBJECT_RADIUS, 0.0, 0.0])
    data = env.env.sim.data._data
    half = np.abs(data.site_xmat[table.site[atom]].reshape(3, 3) @ table.size[atom])
    return np.array([MISS * half[0], 0.0, 0.0])


def _spread(env, table: GoalTable) -> dict[int, np.ndarray]:
    """Shifts for the placement atoms when all are made true: those sharing a region spread
    along its longer side, ``SPREAD`` of the way to its edges."""
    data = env.env.sim.data._data
    shifts = {int(i): np.zeros(3) for i in np.flatnonzero(table.kind != JOINTS)}
    regions = [i for i in shifts if table.kind[i] != ON_OBJECT]
    for site in {table.site[i] for i in regions}:
        sharing = [i for i in regions if table.site[i] == site]
        if len(sharing) < 2:
            continue
        half = np.abs(data.site_xmat[site].reshape(3, 3) @ table.size[sharing[0]])
        axis = int(np.argmax(half[:2]))
        for i, k in zip(sharing, np.linspace(-SPREAD, SPREAD, len(sharing))):
            shifts[i][axis] = k * half[axis]
    return shifts


def _near_success(env, table: GoalTable) -> list[dict]:
    """Frames of ``env`` from its init state through each atom made true alone and just missed,
    then all of them at once."""
    inner = env.env
    model, data = inner.sim.model._model, inner.sim.data._data
    start = inner.sim.get_state().flatten()
    frames = [_frame(env)]
    for i in range(len(table.atoms)):
        inner.sim.set_state_from_flattened(start)
        if table.kind[i] == JOINTS:
            for offset in (-0.05, -0.001, 0.001, 0.05):
                _set_joints(env, table, i, offset)
                mujoco.mj_forward(model, data)
                frames.append(_frame(env))
            continue
        _drop(env, table, i, np.zeros(3), inside=table.kind[i] == IN_REGION)
        _settle(env, frames)
        inner.sim.set_state_from_flattened(start)
        _drop(env, table, i, _miss(env, table, i), inside=False)
        _settle(env, frames)
    inner.sim.set_state_from_flattened(start)
    mujoco.mj_forward(model, data)
    shifts = _spread(env, table)
    for i in range(len(table.atoms)):
        if table.kind[i] == JOINTS:
            _set_joints(env, table, i, 0.05)
        else:
            _drop(env, table, i, shifts[i], inside=table.kind[i] == IN_REGION)
    _settle(env, frames)
    inner.sim.set_state_from_flattened(start)
    mujoco.mj_forward(model, data)
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


def test_contact_decides_a_verdict_of_every_atom_that_reads_one(scene):
    """Some state has an atom's geometry right but no contact (an object still falling onto it)."""
    _, table, frames = scene
    touching = np.flatnonzero(table.needs_contact)
    if not touching.size:
        pytest.skip("this task's goal reads no contacts")
    # Every world given one contact between the two geom sets of each such atom.
    pairs = [(np.flatnonzero(table.geom_side[t] & 1)[0], np.flatnonzero(table.geom_side[t] & 2)[0]) for t in touching]
    geometry = _evaluate(table, [dict(f, contacts=np.array(pairs)) for f in frames]).holds.numpy()
    expected = np.array([f["atoms"] for f in frames])
    for t in touching:
        assert (geometry[:, t].astype(bool) & ~expected[:, t]).any(), table.atoms[t]


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
