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

``compile_goal(env)`` (:mod:`vecsim.engine.mjwarp.tables`, no warp) reads a built LIBERO env into a
``GoalTable``; a goal with any other atom raises ``UnsupportedGoal`` (``supported_tasks`` lists
the tasks that compile).
Example::

    goal = GoalEvaluator(compile_goal(libero_env.env), nworld, device)
    goal.evaluate(d.qpos, d.xpos, d.site_xpos, d.site_xmat, d.nacon, d.contact.geom, d.contact.worldid)
    goal.success  # [nworld] int32, goal.holds: [nworld, atoms]
"""

from __future__ import annotations

from typing import Any

import numpy as np
import warp as wp

from vecsim.engine.mjwarp.tables import GREATER, IN_REGION, JOINTS, LESS, ON_OBJECT, GoalTable


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
