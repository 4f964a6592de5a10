"""Where the scripted policy (``lib/scripted.py``) turns a knob on, pushes a door or drawer
shut, or puts an object into a fixture whose top the hand cannot pass under, read off a LIBERO
env's model and state (the table's ``turns``, ``closes``, and a place's ``approach`` and its
``pushes``: :data:`INSERTS`).

LIBERO's predicates read one joint each: ``TurnOn`` holds once the knob's joint is at or past
the low end of its fixture's ``default_turnon_ranges`` (the stove: 0.5 rad), ``Close`` once the
door's or drawer's joint is past the low end of its ``default_close_ranges`` (a cabinet's
drawer: 0 m; the microwave's door: -5 mrad). The script grips a knob on its joint's (vertical)
axis and turns the wrist by the joint angle that takes it to the middle of its on range; it
pushes a drawer along its slide's axis and a door along the arc of its hinge, from in front of
the face that closes to past the joint's closed limit::

    turn = knob_turn(inner, "flat_stove_1")
    close = shut_path(inner, "white_cabinet_1_bottom_region")
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from lib.scripted import closing_yaw

SLIDE, HINGE = 2, 3  # mujoco's mjtJoint values for the joints a fixture's parts move on


@dataclass(frozen=True)
class Shut:
    """How the script pushes one kind of fixture's door or drawer shut."""

    standoff_m: float  # the grip site this far behind the face it pushes: the pushing part's front
    past: float  # pushed this far past the joint's closed limit (metres for a slide, radians for a hinge)
    height_m: float | None = None  # the fingertips this far over the part's bottom; None: the face's middle
    along: float = 1.0  # a hinged door: pushed this far from its hinge, a fraction of its length
    arc_points: int = 10  # a hinged door: waypoints along the arc (as many for every init state: one script length)
    lean_rad: float = 0.0  # the fingertips lean this far towards the push, the arm kept back


# By LIBERO fixture category (the fixture's name without its ``_<n>`` suffix). A cabinet's drawer
# is pushed by its handle, whose front the closed fingertips (1.3 cm ahead of the grip site)
# meet; with the fingers closing across the push, the hand (2.4 cm over the fingertips, 3.9 cm
# ahead of the grip site) stays clear of the drawer's front above the handle. It is pushed 5 cm
# past its closed limit (which stops it): the push stays at full force to the end. The fingertips
# lean 20 degrees into the push: upright, the forearm meets the cabinet's top before it is shut.
# The microwave's door is pushed 7/10 of the way out from its hinge, 3 cm over its bottom, by
# the flat of the hand (3.9 cm ahead of the grip site; the fingers close along the door), which
# turns with it to 0.1 rad past shut.
SHUTS = {
    "white_cabinet": Shut(standoff_m=0.018, past=0.05, lean_rad=0.35),
    "microwave": Shut(standoff_m=0.045, past=0.1, height_m=0.03, along=0.7),
}
KNOB_DEPTH_M = 0.018  # the fingertips' centre this far under a knob's top (the stove's lever is 5 cm tall)


def subtree_corners(model: Any, data: Any, body: int) -> np.ndarray:
    """The world corners ``[8 * geoms, 3]`` of the bounding boxes of the colliding geoms of
    ``body`` and the bodies under it."""
    inside = np.zeros(model.nbody, dtype=bool)
    inside[body] = True
    for child in range(body + 1, model.nbody):  # a body's parent comes before it
        inside[child] = inside[model.body_parentid[child]]
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
    geoms = inside[model.geom_bodyid] & ((model.geom_contype != 0) | (model.geom_conaffinity != 0))
    corners = []
    for geom in np.flatnonzero(geoms):
        centre, half = model.geom_aabb[geom, :3], model.geom_aabb[geom, 3:]
        corners.append(data.geom_xpos[geom] + (centre + signs * half) @ data.geom_xmat[geom].reshape(3, 3).T)
    if not corners:
        raise ValueError(f"body {body}: no colliding geoms to push or grip")
    return np.concatenate(corners)


def articulation(inner: Any, name: str) -> tuple[int, dict[str, Any]]:
    """The one joint (its id) that LIBERO's predicates read for ``name`` (a fixture, or a region
    site of one: a cabinet's drawer), and its fixture's ``articulation`` properties."""
    import mujoco

    model = inner.sim.model._model
    if name in inner.object_sites_dict:
        joints = inner.object_sites_dict[name].joints
        owner = inner.get_object(inner.object_states_dict[name].parent_name)
    else:
        owner = inner.get_object(name)
        joints = owner.joints
    named = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, joint) for joint in joints]
    if len(named) != 1 or named[0] < 0:
        raise ValueError(f"{name}: joints {list(joints)}, not the one joint the script can work")
    return named[0], owner.object_properties["articulation"]


def knob_turn(inner: Any, name: str) -> dict[str, Any]:
    """A ``turns`` entry for the knob of fixture ``name``: the ``grip`` on its joint's axis
    (``KNOB_DEPTH_M`` under its top), its ``top``, the ``yaw`` at which the fingers close across
    the knob's parts at that height, and the ``turn`` of the wrist that takes the joint to the
    middle of LIBERO's on range."""
    model, data = inner.sim.model._model, inner.sim.data._data
    joint, properties = articulation(inner, name)
    if model.jnt_type[joint] != HINGE or abs(data.xaxis[joint][2]) < 0.99:
        raise ValueError(f"{name}: its joint is not a vertical hinge, not a knob the wrist can turn")
    corners = subtree_corners(model, data, model.jnt_bodyid[joint])
    top = float(corners[:, 2].max())
    grip_z = top - KNOB_DEPTH_M
    # The parts the fingertips meet at that height: each geom's 8 corners, kept if it reaches it.
    tall = corners.reshape(-1, 8, 3)
    tall = tall[tall[:, :, 2].max(axis=1) > grip_z].reshape(-1, 3)
    spread = tall[:, :2] - tall[:, :2].mean(axis=0)
    narrowest = np.linalg.eigh(spread.T @ spread)[1][:, 0]
    target = float(np.mean(properties["default_turnon_ranges"]))
    qpos = float(data.qpos[model.jnt_qposadr[joint]])
    anchor = data.xanchor[joint]
    return {
        "joint": model.joint(joint).name,
        "grip": [round(float(v), 5) for v in (anchor[0], anchor[1], grip_z)],
        "top": round(top, 5),
        "yaw": round(closing_yaw(narrowest), 4),
        "turn": round((target - qpos) * float(np.sign(data.xaxis[joint][2])), 4),
    }


def shut_path(inner: Any, name: str, shut: Shut) -> dict[str, Any]:
    """A ``closes`` entry for the door or drawer that LIBERO's ``Close`` reads for ``name``: the
    ``path`` of the grip site, from ``shut.standoff_m`` in front of the face that closes to
    ``shut.past`` beyond the joint's closed limit, and the ``yaws`` along it (the fingers
    closing across the push, turning with a door); ``lean``, if the fingertips lean into it."""
    model, data = inner.sim.model._model, inner.sim.data._data
    joint, properties = articulation(inner, name)
    if not model.jnt_limited[joint]:
        raise ValueError(f"{name}: its joint has no limits, so no closed end to push to")
    qpos = float(data.qpos[model.jnt_qposadr[joint]])
    closed = float(np.mean(properties["default_close_ranges"]))
    sign = 1.0 if closed > qpos else -1.0  # the joint's way to closed
    limit = float(model.jnt_range[joint][1 if sign > 0 else 0])
    axis = data.xaxis[joint] * sign
    corners = subtree_corners(model, data, model.jnt_bodyid[joint])
    if model.jnt_type[joint] == SLIDE:
        push = np.array([axis[0], axis[1], 0.0])
        push /= np.linalg.norm(push)
        depth = corners @ push
        face = corners[depth < depth.min() + 0.005]  # the corners of the face the push meets first
        start = face.mean(axis=0) - shut.standoff_m * push
        if shut.height_m is not None:
            start[2] = corners[:, 2].min() + shut.height_m
        end = start + (abs(limit - qpos) + shut.past) * push
        yaw = closing_yaw((-push[1], push[0]))
        path, yaws = [start, end], [yaw, yaw]
    elif model.jnt_type[joint] == HINGE:
        if abs(axis[2]) < 0.99:
            raise ValueError(f"{name}: its hinge is not vertical; the script pushes doors that swing level")
        anchor = data.xanchor[joint]
        radial = corners[:, :2] - anchor[:2]
        out = radial.mean(axis=0) / np.linalg.norm(radial.mean(axis=0))
        reach = (radial @ out).max() * shut.along
        # The door's face at that reach: the geoms spanning it (a handle further out stands proud
        # of it), along their longest horizontal direction, away from the hinge.
        spans = (radial @ out).reshape(-1, 8)
        there = np.repeat((spans.min(axis=1) <= reach) & (spans.max(axis=1) >= reach), 8)
        face = radial[there] if there.any() else radial
        longest = np.linalg.eigh(np.cov(face.T))[1][:, -1]
        out = longest * np.sign(longest @ out)
        tangent = np.array([-out[1], out[0]]) * np.sign(axis[2])  # where the door's points move as it closes
        behind = (face @ tangent).min()
        height = corners[:, 2].min() + shut.height_m if shut.height_m is not None else corners[:, 2].mean()
        first = anchor[:2] + reach * out + (behind - shut.standoff_m) * tangent
        sweep = (abs(limit - qpos) + shut.past) * np.sign(axis[2])
        yaw = closing_yaw(out)
        path, yaws = [], []
        for angle in np.linspace(0.0, sweep, max(2, shut.arc_points)):
            c, s = math.cos(angle), math.sin(angle)
            x, y = first - anchor[:2]
            path.append([anchor[0] + c * x - s * y, anchor[1] + s * x + c * y, height])
            yaws.append(yaw + angle)
    else:
        raise ValueError(f"{name}: its joint is neither a slide nor a hinge")
    entry = {
        "joint": model.joint(joint).name,
        "path": [[round(float(v), 5) for v in point] for point in path],
        "yaws": [round(float(y), 4) for y in yaws],
    }
    if shut.lean_rad:
        entry["lean"] = shut.lean_rad
    return entry


@dataclass(frozen=True)
class Insert:
    """How the script puts an object into a fixture whose top the hand cannot pass under (a
    microwave): held by a part that stays outside (a mug by its handle, the handle towards the
    hand), lowered in front of the opening, slid in level and let go, then pushed deeper by the
    closed fingertips leaning into the opening (their hand stays in front of the top) until all
    of it is past where the door shuts. Points and directions of the object are in its body
    frame (x, y), read off LIBERO's collision geoms; of the fixture, in the fixture's frame."""

    at: tuple[float, float]  # the object's part the fingers close on
    across: tuple[float, float]  # the direction they close along
    height_m: float  # the fingertips' centre this far over the object's bottom (and over the floor when pushing)
    into: tuple[float, float]  # the way into the fixture's opening
    side_m: float  # the object let go this far along the fixture's x from its region's centre
    out_m: float  # the grip site let go this far in front of the region's front face (the hand clear of the top)
    approach_m: float  # lowered this far in front of where it is let go (all of it clear of the top)
    approach_side_m: float  # and this far along the fixture's x from there (clear of an open door)
    clearance_m: float  # let go with its bottom this far over the floor
    push_in_m: float  # pushed until the grip site is this far past the region's front face (short of it: < 0)
    push_start_m: float  # the push starts this far in front of where the object was let go
    lean_rad: float  # the fingertips lean this far into the push


# By (object category, fixture category). libero_10/9's mug (10.5 cm across, 10.3 cm tall, its
# handle reaching 3.4 cm out) goes into the microwave (inside: 20.7 cm wide, 16.8 cm deep,
# 14.4 cm under its top; its top's front edge 1.45 cm in front of the heating region). Held by
# the rim, the hand (6.8 cm deep, its bottom 2.4 cm over the grip site, 10 cm tall) would stay
# in front of the top, and the mug's centre 3.4 cm in front of the floor's edge. So it is held
# by the handle's outer bar (turned towards the hand), fingers closing across the handle's
# 1.8 cm, 5.5 cm over its bottom: let go with the grip site 5.8 cm in front of the region, its
# body is on the floor, its handle outside. It is lowered 12 cm in front of that and 4 cm to
# the microwave's +x: the hand, 21 cm along x, then stays clear of the door's top on the -x side
# (init state 37's door, open 76 degrees, not 90, stood in its way), and slides in diagonally.
# The fingertips, closed and leaning 45 degrees, then push the handle until the grip site is
# 0.5 cm short of the region (further, the hand's +x end meets the microwave's front panel): the
# handle is then some 3 cm past the closed door's face, which the door's push (SHUTS) clears.
INSERTS = {
    ("white_yellow_mug", "microwave"): Insert(
        at=(0.0641, 0.0),
        across=(0.0, 1.0),
        height_m=0.055,
        into=(0.0, 1.0),
        side_m=-0.02,
        out_m=0.058,
        approach_m=0.12,
        approach_side_m=0.04,
        clearance_m=0.008,
        push_in_m=-0.005,
        push_start_m=0.04,
        lean_rad=0.785,
    )
}


def inserted_pair(
    inner: Any, obj: str, goal: str, insert: Insert, floor_z: float, prefer_yaw: float = 0.0
) -> tuple[dict[str, Any], dict[str, Any]]:
    """A place's ``grip``, ``yaw``, ``release`` and ``approach`` that put ``obj`` into region
    site ``goal`` of its fixture under ``insert`` (``floor_z``: the height of the floor under the
    region), and the ``pushes`` entry that takes it deeper. Of the two yaws that close the
    fingers alike, the one nearer ``prefer_yaw`` (the door's push that follows)."""
    import mujoco

    model, data = inner.sim.model._model, inner.sim.data._data
    body = inner.obj_body_id[obj]
    site = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, goal)
    if site < 0:
        raise ValueError(f"{goal}: not a region site to put {obj} into")
    fixture = inner.obj_body_id[inner.object_states_dict[goal].parent_name]
    frame = data.xmat[body].reshape(3, 3)[:2, :2]
    grip_xy = data.xpos[body][:2] + frame @ np.array(insert.at)
    bottom = float(subtree_corners(model, data, body)[:, 2].min())
    yaw = closing_yaw(frame @ np.array(insert.across), prefer_yaw)
    axes = data.xmat[fixture].reshape(3, 3)[:2, :2]
    into = axes @ np.array(insert.into)
    site_axes = data.site_xmat[site].reshape(3, 3)[:2, :2]
    depth = float(np.abs(into @ site_axes) @ model.site_size[site, :2])  # the region's half depth along ``into``
    front = data.site_xpos[site][:2] - depth * into + insert.side_m * axes[:, 0]
    release = front - insert.out_m * into
    height = floor_z + insert.height_m
    start = release - insert.push_start_m * into
    end = front + insert.push_in_m * into
    place = {
        "grip": [round(float(v), 5) for v in (*grip_xy, bottom + insert.height_m)],
        "yaw": round(yaw, 4),
        "release": [round(float(v), 5) for v in (*release, height + insert.clearance_m)],
        "approach": [round(float(v), 5) for v in insert.approach_m * into - insert.approach_side_m * axes[:, 0]],
    }
    push = {
        "path": [[round(float(v), 5) for v in (*point, height)] for point in (start, end)],
        "yaws": [round(yaw, 4)] * 2,
        "lean": insert.lean_rad,
    }
    return place, push
