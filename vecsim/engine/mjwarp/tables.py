"""The index tables the batched ``mjwarp`` modules read, taken from a built LIBERO env: no warp.

A scene's export (:mod:`vecsim.engine.mjwarp.scene`) runs in the CPU stack's environment, which
has no warp (the pod image's CPU venv), and writes these tables to ``tables.npz``; the ``mjwarp``
engine reads them back into the same dataclasses for its kernels:

- :class:`PandaIndex` (and :func:`mass_index`): the arm and gripper, for
  :class:`~vecsim.engine.mjwarp.controller.PandaController`;
- :class:`ObservableIndex`: what :class:`~vecsim.engine.mjwarp.observables.PandaObservables` reads;
- :class:`GoalTable` (:func:`compile_goal`, :func:`supported_tasks`): LIBERO's goal atoms, for
  :class:`~vecsim.engine.mjwarp.predicates.GoalEvaluator`.

Example::

    index = PandaIndex.from_robosuite(libero_env.env)
    table = compile_goal(libero_env.env)   # raises UnsupportedGoal, naming the atom
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

ARM_DOF = 7


@dataclasses.dataclass(frozen=True)
class PandaIndex:
    """Where one Panda arm and gripper sit in a compiled model (ids, not names).

    ``mass_index`` is ``[7, 7]``: the flat index in one world's mass matrix of each entry of the
    arm's (:func:`mass_index`; MuJoCo Warp 4's CSR ``M`` unless built for another layout).
    """

    eef_site: int
    arm_joints: np.ndarray
    arm_qpos: np.ndarray
    arm_dofs: np.ndarray
    arm_actuators: np.ndarray
    gripper_actuators: np.ndarray
    mass_index: np.ndarray
    torque_low: np.ndarray
    torque_high: np.ndarray
    gripper_ctrl_low: np.ndarray
    gripper_ctrl_high: np.ndarray

    @classmethod
    def from_robosuite(cls, env: Any, field: str = "M") -> PandaIndex:
        """Read the index from a robosuite (LIBERO) env's first robot and its compiled model,
        with ``mass_index`` into ``field`` (:func:`mass_index`).

        Raises:
            ValueError: the arm is not 7 hinges that are the grip site's only moving ancestors
                (the kernel's Jacobian and end-effector velocity assume a fixed base).
        """
        import mujoco

        robot = env.robots[0]
        ctl = robot.controller
        model = env.sim.model._model
        dofs = np.asarray(ctl.qvel_index, dtype=np.int32)
        site = int(model.site(ctl.eef_name).id)
        ancestors, body = [], int(model.site_bodyid[site])
        while body > 0:
            start = int(model.body_dofadr[body])
            ancestors += range(start, start + int(model.body_dofnum[body]))
            body = int(model.body_parentid[body])
        hinges = model.jnt_type[model.dof_jntid[dofs]] == mujoco.mjtJoint.mjJNT_HINGE
        if len(dofs) != ARM_DOF or sorted(ancestors) != sorted(dofs.tolist()) or not hinges.all():
            raise ValueError(f"{ctl.eef_name}: the arm's dofs {dofs.tolist()} are not the site's {ARM_DOF} hinges")
        gripper = np.array([model.actuator(name).id for name in robot.gripper.actuators], dtype=np.int32)
        arm_act = np.asarray(robot._ref_joint_actuator_indexes, dtype=np.int32)
        return cls(
            eef_site=site,
            arm_joints=np.asarray(model.dof_jntid[dofs], dtype=np.int32),
            arm_qpos=np.asarray(ctl.qpos_index, dtype=np.int32),
            arm_dofs=dofs,
            arm_actuators=arm_act,
            gripper_actuators=gripper,
            mass_index=mass_index(model, dofs, field),
            torque_low=model.actuator_ctrlrange[arm_act, 0].copy(),
            torque_high=model.actuator_ctrlrange[arm_act, 1].copy(),
            gripper_ctrl_low=model.actuator_ctrlrange[gripper, 0].copy(),
            gripper_ctrl_high=model.actuator_ctrlrange[gripper, 1].copy(),
        )


def mass_index(model: Any, dofs: np.ndarray, field: str = "M", dense_stride: int | None = None) -> np.ndarray:
    """Return the ``[len(dofs)]^2`` flat indexes of the dofs' mass-matrix block in one world's
    ``field``: ``"M"``, MuJoCo's CSR lower triangle (``M_rowadr``, ``M_colind``, what MuJoCo Warp
    4 holds); ``"qM"``, MuJoCo's legacy sparse layout (``dof_Madr`` walking ``dof_parentid``), or
    with ``dense_stride``, a dense ``qM`` of that row stride.

    Raises:
        ValueError: two dofs whose entry is structurally zero (not on one kinematic chain).
    """
    n = len(dofs)
    index = np.empty((n, n), dtype=np.int32)
    for a, i in enumerate(dofs):
        for b, j in enumerate(dofs):
            row, col = (int(i), int(j)) if i >= j else (int(j), int(i))
            if dense_stride is not None:
                index[a, b] = i * dense_stride + j
            elif field == "M":
                start = model.M_rowadr[row]
                where = np.flatnonzero(model.M_colind[start : start + model.M_rownnz[row]] == col)
                if where.size != 1:
                    raise ValueError(f"dofs {row} and {col} are not on one kinematic chain")
                index[a, b] = start + where[0]
            elif field == "qM":
                adr, k = model.dof_Madr[row], row
                while k != col:
                    k = model.dof_parentid[k]
                    adr += 1
                    if k < 0:
                        raise ValueError(f"dofs {row} and {col} are not on one kinematic chain")
                index[a, b] = adr
            else:
                raise ValueError(f"field must be 'M' or 'qM', not {field!r}")
    return index


@dataclasses.dataclass(frozen=True)
class ObservableIndex:
    """Ids of what the observables read in one compiled model."""

    eef_site: int
    eef_body: int
    arm_qpos: np.ndarray
    gripper_qpos: np.ndarray

    @classmethod
    def from_robosuite(cls, env: Any) -> ObservableIndex:
        """Read the ids from a robosuite (LIBERO) env's first robot."""
        robot = env.robots[0]
        model = env.sim.model._model
        return cls(
            eef_site=int(robot.eef_site_id),
            eef_body=int(model.body(robot.robot_model.eef_name).id),
            arm_qpos=np.asarray(robot._ref_joint_pos_indexes, dtype=np.int32),
            gripper_qpos=np.asarray(robot._ref_gripper_joint_pos_indexes, dtype=np.int32),
        )


# Atom kinds.
IN_REGION = 0
ON_REGION = 1
ON_OBJECT = 2
JOINTS = 3
# Joint comparisons against a threshold.
LESS = 0
GREATER = 1
GREATER_EQUAL = 2
# Most joints an articulated object's predicate reads.
MAX_JOINTS = 4

# LIBERO's articulated objects (articulated_objects.py), by category: predicate -> (comparison,
# which articulation range, which end of it). Open and TurnOn hold when any joint passes, Close
# and TurnOff when all do; thresholds are read from the object's own properties.
_CABINET_LIKE = {"open": (LESS, "default_open_ranges", max), "close": (GREATER, "default_close_ranges", min)}
_DRAWER_LIKE = {"open": (GREATER, "default_open_ranges", min), "close": (LESS, "default_close_ranges", max)}
JOINT_RULES: dict[str, dict[str, tuple[int, str, Any]]] = {
    "microwave": _CABINET_LIKE,
    "wooden_cabinet": _CABINET_LIKE,
    "white_cabinet": _CABINET_LIKE,
    "short_cabinet": _DRAWER_LIKE,
    "short_fridge": _DRAWER_LIKE,
    "flat_stove": {
        "turnon": (GREATER_EQUAL, "default_turnon_ranges", min),
        "turnoff": (LESS, "default_turnoff_ranges", max),
    },
}
_ANY_JOINT = ("open", "turnon")


class UnsupportedGoal(ValueError):
    """A task's goal has an atom whose batched form is not written; the message names it."""


@dataclasses.dataclass(frozen=True)
class GoalTable:
    """One task's goal atoms as arrays (ids in the compiled model), one row per atom."""

    atoms: tuple[str, ...]
    kind: np.ndarray  # [n] int32
    body: np.ndarray  # [n] int32: the object placed (In, On)
    other_body: np.ndarray  # [n] int32: what it is placed on (On an object)
    site: np.ndarray  # [n] int32: the region (In, On a region)
    size: np.ndarray  # [n, 3] float32: the region's size
    needs_contact: np.ndarray  # [n] int32
    geom_side: np.ndarray  # [n, ngeom] int32: bit 1 the first geom set, bit 2 the second
    joint_qpos: np.ndarray  # [n, MAX_JOINTS] int32
    joint_count: np.ndarray  # [n] int32
    any_joint: np.ndarray  # [n] int32
    compare: np.ndarray  # [n] int32
    threshold: np.ndarray  # [n] float32


def _rule(category: str | None, predicate: str, atom: str) -> tuple[int, str, Any]:
    rule = JOINT_RULES.get(category or "", {}).get(predicate)
    if rule is None:
        raise UnsupportedGoal(f"{atom}: no batched {predicate!r} for objects of category {category!r}")
    return rule


def compile_goal(env: Any) -> GoalTable:
    """Compile the goal of a built LIBERO env (``OffScreenRenderEnv(...).env``) into arrays.

    Raises:
        UnsupportedGoal: an atom whose predicate or arguments have no batched form here.
    """
    model = env.sim.model._model
    goal = env.parsed_problem["goal_state"]
    n = len(goal)
    rows: dict[str, Any] = {
        "kind": np.zeros(n, np.int32),
        "body": np.zeros(n, np.int32),
        "other_body": np.zeros(n, np.int32),
        "site": np.zeros(n, np.int32),
        "size": np.zeros((n, 3), np.float32),
        "needs_contact": np.zeros(n, np.int32),
        "geom_side": np.zeros((n, model.ngeom), np.int32),
        "joint_qpos": np.zeros((n, MAX_JOINTS), np.int32),
        "joint_count": np.zeros(n, np.int32),
        "any_joint": np.zeros(n, np.int32),
        "compare": np.zeros(n, np.int32),
        "threshold": np.zeros(n, np.float32),
    }
    sites = env.object_sites_dict

    def contact_between(i: int, first: Any, second: Any) -> None:
        rows["needs_contact"][i] = 1
        for bit, obj in ((1, first), (2, second)):
            for name in obj.contact_geoms:
                rows["geom_side"][i, model.geom(name).id] |= bit

    atoms = []
    for i, (predicate, *args) in enumerate(goal):
        atom = f"({predicate} {' '.join(args)})"
        atoms.append(atom)
        if predicate in ("in", "on") and len(args) == 2:
            placed, target = args
            rows["body"][i] = env.obj_body_id[placed]
            if target in sites:
                region = sites[target]
                rows["site"][i] = model.site(target).id
                rows["size"][i] = np.asarray(region.size, dtype=np.float32)
                if predicate == "in":
                    rows["kind"][i] = IN_REGION
                    continue
                if not hasattr(region, "under"):
                    raise UnsupportedGoal(f"{atom}: region {target!r} has no 'under' test")
                rows["kind"][i] = ON_REGION
                parent = env.get_object(region.parent_name)
                if parent is not None:
                    contact_between(i, parent, env.get_object(placed))
                continue
            if predicate == "on" and target in env.obj_body_id:
                rows["kind"][i] = ON_OBJECT
                rows["other_body"][i] = env.obj_body_id[target]
                contact_between(i, env.get_object(target), env.get_object(placed))
                continue
            raise UnsupportedGoal(f"{atom}: {predicate!r} with {target!r} (not a region) has no batched form")
        if predicate in ("open", "close", "turnon", "turnoff") and len(args) == 1:
            (name,) = args
            if name in sites:
                joints, owner = sites[name].joints or [], env.get_object(sites[name].parent_name)
            else:
                owner = env.get_object(name)
                joints = owner.joints if owner is not None else []
            compare, ranges, end = _rule(getattr(owner, "category_name", None), predicate, atom)
            if len(joints) > MAX_JOINTS:
                raise UnsupportedGoal(f"{atom}: {len(joints)} joints, at most {MAX_JOINTS}")
            rows["kind"][i] = JOINTS
            rows["joint_count"][i] = len(joints)
            for k, joint in enumerate(joints):
                rows["joint_qpos"][i, k] = model.jnt_qposadr[model.joint(joint).id]
            rows["any_joint"][i] = int(predicate in _ANY_JOINT)
            rows["compare"][i] = compare
            rows["threshold"][i] = end(owner.object_properties["articulation"][ranges])
            continue
        raise UnsupportedGoal(f"{atom}: predicate {predicate!r} has no batched form")
    return GoalTable(atoms=tuple(atoms), **rows)


def supported_tasks(suite: str) -> list[int]:
    """The task indexes of a LIBERO suite whose goals :func:`compile_goal` accepts.

    Decided from the bddl files alone (no scene is built): regions, object categories and the
    predicates above.
    """
    from vecsim.engine.tasks._libero import libero_benchmark

    bench = libero_benchmark(suite)  # first: it points LIBERO at vecsim's config
    from libero.libero.envs.bddl_utils import robosuite_parse_problem

    problems = (robosuite_parse_problem(bench.get_task_bddl_file_path(i)) for i in range(bench.n_tasks))
    return [i for i, problem in enumerate(problems) if _goal_supported(problem)]


def _goal_supported(problem: dict[str, Any]) -> bool:
    category = {
        name: cat for group in ("objects", "fixtures") for cat, names in problem[group].items() for name in names
    }
    regions = problem["regions"]
    for predicate, *args in problem["goal_state"]:
        if predicate in ("in", "on") and len(args) == 2:
            target = args[1]
            if not (target in regions or (predicate == "on" and target in category)):
                return False
        elif predicate in ("open", "close", "turnon", "turnoff") and len(args) == 1:
            name = args[0]
            owner = regions[name]["target"] if name in regions else name
            if predicate not in JOINT_RULES.get(category.get(owner, ""), {}):
                return False
        else:
            return False
    return True
