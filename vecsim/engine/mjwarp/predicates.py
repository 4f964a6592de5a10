"""LIBERO's success predicates, batched over worlds in Warp.

A LIBERO task succeeds when every atom of its bddl ``:goal`` holds (a conjunction). Each atom
is one of LIBERO's predicates over object and region states (``libero/libero/envs/predicates``,
``object_states``), evaluated here per world from the arrays MuJoCo Warp holds:

- ``In(obj, region)``: the object's body origin inside the region site's box (LIBERO's
  ``in_box``: half-sizes ``|R size|``, 1 cm of slack below);
- ``On(obj, region)``: the origin above the region (LIBERO's ``under``) and, when the region
  belongs to an object, that object touching ``obj``;
- ``On(obj, other)``: ``obj`` no lower than ``other``, touching it, within 3 cm of it in x-y;
- ``Open``, ``Close``, ``TurnOn``, ``TurnOff``: joint thresholds of LIBERO's articulated
  objects (any joint for open / on, every joint for close / off).

``compile_goal(env)`` reads a built LIBERO env into a :class:`GoalTable`; a goal with any other
atom raises :class:`UnsupportedGoal` (:func:`supported_tasks` lists the tasks that compile).
Example::

    goal = GoalEvaluator(compile_goal(libero_env.env), nworld, device)
    goal.evaluate(d.qpos, d.xpos, d.site_xpos, d.site_xmat, d.nacon, d.contact.geom, d.contact.worldid)
    goal.success  # [nworld] int32, goal.holds: [nworld, atoms]
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import warp as wp

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


@wp.kernel
def goal_contacts(
    nacon: wp.array(dtype=wp.int32),
    contact_geom: wp.array(dtype=wp.vec2i),
    contact_worldid: wp.array(dtype=wp.int32),
    geom_side: wp.array2d(dtype=wp.int32),
    touching: wp.array2d(dtype=wp.int32),
):
    """Mark each (world, atom) whose two geom sets have a contact (robosuite's ``check_contact``)."""
    c, t = wp.tid()
    if c >= nacon[0]:
        return
    geoms = contact_geom[c]
    s1 = geom_side[t, geoms[0]]
    s2 = geom_side[t, geoms[1]]
    if ((s1 & 1) != 0 and (s2 & 2) != 0) or ((s1 & 2) != 0 and (s2 & 1) != 0):
        touching[contact_worldid[c], t] = 1


@wp.func
def joint_passes(value: float, compare: int, threshold: float) -> bool:
    if compare == LESS:
        return value < threshold
    if compare == GREATER:
        return value > threshold
    return value >= threshold


@wp.kernel
def goal_atoms(
    qpos: wp.array2d(dtype=wp.float32),
    xpos: wp.array2d(dtype=wp.vec3),
    site_xpos: wp.array2d(dtype=wp.vec3),
    site_xmat: wp.array2d(dtype=wp.mat33),
    touching: wp.array2d(dtype=wp.int32),
    kind: wp.array(dtype=wp.int32),
    body: wp.array(dtype=wp.int32),
    other_body: wp.array(dtype=wp.int32),
    site: wp.array(dtype=wp.int32),
    size: wp.array(dtype=wp.vec3),
    needs_contact: wp.array(dtype=wp.int32),
    joint_qpos: wp.array2d(dtype=wp.int32),
    joint_count: wp.array(dtype=wp.int32),
    any_joint: wp.array(dtype=wp.int32),
    compare: wp.array(dtype=wp.int32),
    threshold: wp.array(dtype=wp.float32),
    holds: wp.array2d(dtype=wp.int32),
):
    """Whether each goal atom holds in each world."""
    w, t = wp.tid()
    k = kind[t]
    ok = bool(False)
    if k == JOINTS:
        count = joint_count[t]
        want_any = any_joint[t] != 0
        ok = not want_any
        for j in range(count):
            passes = joint_passes(qpos[w, joint_qpos[t, j]], compare[t], threshold[t])
            if want_any and passes:
                ok = True
            if not want_any and not passes:
                ok = False
    elif k == ON_OBJECT:
        below = xpos[w, other_body[t]]
        above = xpos[w, body[t]]
        dx = below[0] - above[0]
        dy = below[1] - above[1]
        ok = below[2] <= above[2] and touching[w, t] != 0 and wp.sqrt(dx * dx + dy * dy) < 0.03
    else:
        centre = site_xpos[w, site[t]]
        rot = site_xmat[w, site[t]]
        placed = xpos[w, body[t]]
        s = size[t]
        if k == IN_REGION:
            half = rot * s
            ok = True
            for i in range(3):
                h = wp.abs(half[i])
                low = centre[i] - h
                if i == 2:
                    low = low - 0.01
                if not (placed[i] > low and placed[i] < centre[i] + h):
                    ok = False
        else:
            # LIBERO's ``under`` multiplies by the site's matrix itself, not its transpose.
            d = rot * (placed - centre)
            ok = s[2] - 0.005 < d[2] and d[2] < s[2] + 0.1 and wp.abs(d[0]) < s[0] and wp.abs(d[1]) < s[1]
            if needs_contact[t] != 0 and touching[w, t] == 0:
                ok = False
    holds[w, t] = wp.where(ok, 1, 0)


@wp.kernel
def goal_success(holds: wp.array2d(dtype=wp.int32), natoms: int, success: wp.array(dtype=wp.int32)):
    """A world succeeds when every atom of the goal holds."""
    w = wp.tid()
    result = int(1)
    for t in range(natoms):
        if holds[w, t] == 0:
            result = 0
    success[w] = result


class GoalEvaluator:
    """One task's goal over ``nworld`` worlds: :meth:`evaluate` fills ``holds`` and ``success``."""

    def __init__(self, table: GoalTable, nworld: int, device: Any = None):
        self.table, self.nworld = table, nworld
        self.device = wp.get_device(device)
        self.natoms = len(table.atoms)

        def put(values: np.ndarray, dtype: Any) -> wp.array:
            return wp.array(values, dtype=dtype, device=self.device)

        self._arrays = [
            put(table.kind, wp.int32),
            put(table.body, wp.int32),
            put(table.other_body, wp.int32),
            put(table.site, wp.int32),
            put(table.size, wp.vec3),
            put(table.needs_contact, wp.int32),
            put(table.joint_qpos, wp.int32),
            put(table.joint_count, wp.int32),
            put(table.any_joint, wp.int32),
            put(table.compare, wp.int32),
            put(table.threshold, wp.float32),
        ]
        self._geom_side = put(table.geom_side, wp.int32)
        self.touching = wp.zeros((nworld, self.natoms), dtype=wp.int32, device=self.device)
        self.holds = wp.zeros((nworld, self.natoms), dtype=wp.int32, device=self.device)
        self.success = wp.zeros(nworld, dtype=wp.int32, device=self.device)

    def evaluate(
        self,
        qpos: wp.array,
        xpos: wp.array,
        site_xpos: wp.array,
        site_xmat: wp.array,
        nacon: wp.array,
        contact_geom: wp.array,
        contact_worldid: wp.array,
    ) -> None:
        """Evaluate every atom in every world from its current kinematics and contacts."""
        self.touching.zero_()
        if contact_geom.shape[0]:
            wp.launch(
                goal_contacts,
                dim=(contact_geom.shape[0], self.natoms),
                device=self.device,
                inputs=[nacon, contact_geom, contact_worldid, self._geom_side],
                outputs=[self.touching],
            )
        wp.launch(
            goal_atoms,
            dim=(self.nworld, self.natoms),
            device=self.device,
            inputs=[qpos, xpos, site_xpos, site_xmat, self.touching, *self._arrays],
            outputs=[self.holds],
        )
        wp.launch(
            goal_success, dim=self.nworld, device=self.device, inputs=[self.holds, self.natoms], outputs=[self.success]
        )
