"""A scripted policy for LIBERO's tasks that put objects in or on goals, turn knobs and close
doors or drawers, and the figures of its success rates: which init state each env runs and how
each episode ended (an env's error included), Wilson intervals over the episodes that ended
without one, and the agreement of two engines per init state.

The policy is closed loop on the end effector (LIBERO's 8-float ``state``: eef position,
axis-angle, gripper) and open loop on the scene: where each object, goal, knob and handle is,
for each init state, comes from a table measured once on the CPU engine (:func:`scene_row`). A
script is a sequence of steps (:func:`steps`), each a few waypoints with named phases: a place
(above the object, down, close, up, above the goal, down, open, up; or, into a goal under a
top, down in front of it and in level), a turn (onto a knob, close, turn the wrist, open, up), a
push (fingers closed, along a path: an object put in pushed deeper) and a close (fingers closed,
push along a path past shut, back off).
Actions are robosuite's OSC_POSE deltas (position up to 5 cm and rotation up to 0.5 rad per
unit, clipped to [-1, 1]) and the gripper (-1 open, 1 closed)::

    policy = Script([table[k] for k in state_ids])
    while not done:
        actions = policy.act(obs["state"])
"""

from __future__ import annotations

import math
from collections import Counter, deque
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from statistics import NormalDist
from typing import Any, NamedTuple

import numpy as np

# robosuite's OSC_POSE output limits: an action of 1 asks for this much per step.
POS_LIMIT_M = 0.05
ROT_LIMIT_RAD = 0.5
OPEN, CLOSED = -1.0, 1.0


@dataclass(frozen=True)
class Gains:
    """How the script moves; the defaults are what was tuned on the CPU engine (libero_10/0)."""

    hover_m: float = 0.12  # height above the goal's region top (and above objects) for transport
    grasp_below_top_m: float = 0.03  # grip this far under the object's top,
    floor_clearance_m: float = 0.015  # but the fingertips' centre this far above its bottom at least
    release_above_m: float = 0.07  # release the object this far above the goal's region centre
    reach_tol_m: float = 0.008  # a waypoint is reached within this distance (and yaw tolerance)
    yaw_tol_rad: float = 0.08
    position_gain: float = 1.0  # action per POS_LIMIT_M of error
    rotation_gain: float = 1.0  # action per ROT_LIMIT_RAD of error
    grip_steps: int = 15  # steps spent closing or opening the gripper
    move_timeout: int = 50  # steps after which a waypoint not reached is given up on
    empty_grip_m: float = 0.005  # closed fingers nearer than this hold nothing (recorded, not acted on)
    back_off_m: float = 0.04  # after pushing a door or drawer shut, back off this far before rising
    push_timeout: int = 120  # steps after which a push's waypoint not reached is given up on (a drawer is slow)


def wilson(successes: int, trials: int, confidence: float = 0.95) -> tuple[float, float]:
    """The Wilson score interval of a success rate; (0, 1) for no trials."""
    if trials <= 0:
        return 0.0, 1.0
    z = NormalDist().inv_cdf((1 + confidence) / 2)
    p = successes / trials
    denominator = 1.0 + z * z / trials
    centre = (p + z * z / (2 * trials)) / denominator
    half = z * math.sqrt(p * (1 - p) / trials + z * z / (4 * trials * trials)) / denominator
    return max(0.0, centre - half), min(1.0, centre + half)


class Episodes:
    """Which init state each of ``num_envs`` envs runs, and how each state's episode ended.

    Envs take the states in order as they come free (at the start, when an episode ends, when an
    env raised); an env with no state left idles. ``outcome[k]`` is ``{"success", "steps"}`` for
    an episode that ended (LIBERO ends one on success alone, or at the step limit), and
    ``{"error", "steps"}`` for one whose env raised (the exception's text, the steps it took),
    each with the ``notes`` given for its env when it ended (the policy's progress, say).
    """

    def __init__(self, state_ids: Sequence[int], num_envs: int) -> None:
        self.pending = deque(int(k) for k in state_ids)
        self.state = np.full(num_envs, -1, dtype=np.int64)  # each env's state id; -1: idle
        self.steps = np.zeros(num_envs, dtype=np.int64)
        self.outcome: dict[int, dict[str, Any]] = {}

    @property
    def running(self) -> np.ndarray:
        """The envs running an episode."""
        return self.state >= 0

    def assign(self, envs: Iterable[int]) -> dict[int, int]:
        """Give each of ``envs`` the next state not yet run, while any is left (the others
        idle); return ``{env: state id}`` of those given one."""
        given = {}
        for i in envs:
            self.state[i], self.steps[i] = -1, 0
            if self.pending:
                self.state[i] = given[int(i)] = self.pending.popleft()
        return given

    def step(
        self,
        envs: Sequence[int],
        terminated: np.ndarray,
        truncated: np.ndarray,
        notes: Mapping[int, Mapping[str, Any]] | None = None,
    ) -> list[int]:
        """Count a step of ``envs`` (running ones) with their flags; end the episodes of those that
        terminated (a success) or truncated, with ``notes[env]`` if given; return those envs, free now."""
        ended = []
        for i, term, trunc in zip(envs, terminated, truncated):
            self.steps[i] += 1
            if term or trunc:
                ending = {"success": bool(term), "steps": int(self.steps[i])}
                self.outcome[int(self.state[i])] = {**ending, **(notes or {}).get(int(i), {})}
                self.state[i] = -1
                ended.append(int(i))
        return ended

    def fail(self, envs: Iterable[int], error: str, notes: Mapping[int, Mapping[str, Any]] | None = None) -> None:
        """The episodes of ``envs`` ended with ``error`` (their env raised), with ``notes[env]`` if
        given; the envs are free."""
        for i in envs:
            if self.state[i] >= 0:
                ending = {"error": error, "steps": int(self.steps[i])}
                self.outcome[int(self.state[i])] = {**ending, **(notes or {}).get(int(i), {})}
                self.state[i] = -1


def summary(outcome: Mapping[int, Mapping[str, Any]]) -> dict[str, Any]:
    """Successes, errors (their state ids), the rate with its Wilson 95% interval over the
    episodes that ended without an error, the mean steps to success of one task on one engine,
    and the failures (episodes ended without success or error) counted by the ``phase`` they
    ended in and by the phase their grip was first found empty in (``empty_grip``; ``"never"``
    if it was not), those whose outcome names them."""
    errored = sorted(k for k, o in outcome.items() if "error" in o)
    ended = [o for o in outcome.values() if "error" not in o]
    wins = [o["steps"] for o in ended if o["success"]]
    lost = Counter(o["phase"] for o in ended if not o["success"] and "phase" in o)
    dropped = Counter(o["empty_grip"] or "never" for o in ended if not o["success"] and "empty_grip" in o)
    low, high = wilson(len(wins), len(ended))
    return {
        "states": len(outcome),
        "successes": len(wins),
        "errors": len(errored),
        "error_state_ids": errored,
        "rate": len(wins) / len(ended) if ended else None,
        "wilson95": [round(low, 4), round(high, 4)],
        "mean_steps_to_success": float(np.mean(wins)) if wins else None,
        "failures_by_phase": dict(sorted(lost.items())),
        "failures_by_empty_grip": dict(sorted(dropped.items())),
    }


def agreement(first: Mapping[int, bool | None], second: Mapping[int, bool | None]) -> dict[str, Any]:
    """Per init state (the ids both mappings hold), whether two engines' successes agree; a state
    whose episode errored on either (None) is counted apart, in ``errored``."""
    common = sorted(set(first) & set(second))
    errored = [k for k in common if first[k] is None or second[k] is None]
    compared = [k for k in common if k not in errored]
    differ = [k for k in compared if bool(first[k]) != bool(second[k])]
    return {
        "states": len(common),
        "both_succeed": sum(1 for k in compared if first[k] and second[k]),
        "both_fail": sum(1 for k in compared if not first[k] and not second[k]),
        "differ": len(differ),
        "differing_state_ids": differ,
        "errored": len(errored),
        "errored_state_ids": errored,
    }


def axis_angle_to_matrix(vector: np.ndarray) -> np.ndarray:
    """Rotation matrices ``[n, 3, 3]`` of axis-angle vectors ``[n, 3]`` (Rodrigues)."""
    vector = np.asarray(vector, dtype=np.float64)
    angle = np.linalg.norm(vector, axis=-1, keepdims=True)
    axis = np.divide(vector, angle, out=np.zeros_like(vector), where=angle > 1e-12)
    x, y, z = axis[..., 0], axis[..., 1], axis[..., 2]
    zero = np.zeros_like(x)
    k = np.stack([zero, -z, y, z, zero, -x, -y, x, zero], axis=-1).reshape(*axis.shape[:-1], 3, 3)
    s, c = np.sin(angle)[..., None], np.cos(angle)[..., None]
    return np.eye(3) + s * k + (1 - c) * (k @ k)


def matrix_to_axis_angle(matrix: np.ndarray) -> np.ndarray:
    """Axis-angle vectors ``[n, 3]`` of rotation matrices ``[n, 3, 3]`` (angles in [0, pi])."""
    cos = np.clip((np.trace(matrix, axis1=-2, axis2=-1) - 1) / 2, -1.0, 1.0)
    angle = np.arccos(cos)
    skew = np.stack(
        [
            matrix[..., 2, 1] - matrix[..., 1, 2],
            matrix[..., 0, 2] - matrix[..., 2, 0],
            matrix[..., 1, 0] - matrix[..., 0, 1],
        ],
        axis=-1,
    )
    sin = np.sin(angle)
    out = np.zeros(matrix.shape[:-2] + (3,))
    regular = sin > 1e-6
    out[regular] = skew[regular] / (2 * sin[regular, None]) * angle[regular, None]
    # Near pi the skew part vanishes: the axis is the column of (R + I) / 2 of largest norm.
    flipped = ~regular & (angle > 1.0)
    if flipped.any():
        half = (matrix[flipped] + np.eye(3)) / 2
        column = np.argmax(np.linalg.norm(half, axis=-2), axis=-1)
        axis = half[np.arange(len(column)), :, column]
        out[flipped] = axis / np.linalg.norm(axis, axis=-1, keepdims=True) * angle[flipped, None]
    return out


def top_down(yaw: np.ndarray) -> np.ndarray:
    """The gripper pointing down, turned by ``yaw`` about the world's z: ``Rz(yaw) Rx(pi)``.
    Its fingers close along ``(sin yaw, -cos yaw, 0)``."""
    c, s = np.cos(yaw), np.sin(yaw)
    zero, one = np.zeros_like(c), np.ones_like(c)
    rz = np.stack([c, -s, zero, s, c, zero, zero, zero, one], axis=-1).reshape(*np.shape(yaw), 3, 3)
    return rz @ np.diag([1.0, -1.0, -1.0])


def gripper_frame(yaw: np.ndarray, tilt: np.ndarray) -> np.ndarray:
    """:func:`top_down` at ``yaw``, then turned by ``tilt`` about the fingers' closing axis: the
    fingertips lean towards the hand's x, ``(cos yaw, sin yaw, 0)``, for a positive one."""
    c, s = np.cos(tilt), np.sin(tilt)
    zero, one = np.zeros_like(c), np.ones_like(c)
    about_y = np.stack([c, zero, s, zero, one, zero, -s, zero, c], axis=-1).reshape(*np.shape(tilt), 3, 3)
    return top_down(yaw) @ about_y


def closing_yaw(direction_xy: Sequence[float], current_yaw: float = 0.0) -> float:
    """The yaw at which the fingers close along ``direction_xy``, the one of the two (yaw and
    yaw + pi close alike) nearest ``current_yaw``."""
    yaw = math.atan2(direction_xy[0], -direction_xy[1])
    return float(current_yaw + (yaw - current_yaw + math.pi / 2) % math.pi - math.pi / 2)


# One waypoint of a step: position, yaw, tilt, grip, hold, carries, phase.
Waypoint = tuple[Sequence[float], float, float, float, int, bool, str]


class Waypoints(NamedTuple):
    """A script for one init state, one row per waypoint: where the gripper goes (``positions``
    ``[W, 3]``; ``yaws`` and ``tilts`` ``[W]``, :func:`gripper_frame`'s), its fingers there (``grips``, :data:`OPEN` or :data:`CLOSED`),
    steps to stay in place (``holds``, 0: move until reached), whether the closed fingers
    should hold something there (``carries``: an object or a knob) and the waypoint's
    ``phases`` (``"<step>:<phase>"``, the step's index in the script from 0)."""

    positions: np.ndarray
    yaws: np.ndarray
    tilts: np.ndarray
    grips: np.ndarray
    holds: np.ndarray
    carries: np.ndarray
    phases: tuple[str, ...]


def steps(row: Mapping[str, Any]) -> list[tuple[str, Mapping[str, Any]]]:
    """The steps of ``row``'s script in order, each ``(kind, its row entry)``: every knob of
    ``row["turns"]`` turned first, then every object of ``row["pairs"]`` put in or on its goal,
    then every push of ``row["pushes"]`` (an object put in, pushed deeper), then every door or
    drawer of ``row["closes"]`` pushed shut (a closed door would bar its region, an object put in
    a drawer goes in open)."""
    return (
        [("turn", turn) for turn in row.get("turns", ())]
        + [("place", pair) for pair in row["pairs"]]
        + [("push", push) for push in row.get("pushes", ())]
        + [("close", close) for close in row.get("closes", ())]
    )


def waypoints(row: Mapping[str, Any], gains: Gains = Gains()) -> Waypoints:
    """The script for one init state: :func:`steps`'s waypoints one after the other.

    A place (``row["pairs"]``) lists the object's ``pick`` (its centre), ``top`` and ``bottom``
    (its heights), ``yaw`` (the grasp's) and ``place`` (the goal region's centre) and
    ``place_top`` (the region's top, the height to carry it over). Optional: ``grip`` and
    ``release``, where the fingertips close and open when that is not over the object's centre
    and goal (a mug held by its rim); ``place_yaw``, the yaw to carry and let go at when it is
    not the grasp's (a book turned to fit a slot); ``approach`` (x, y), the way into a goal under
    a top the hand cannot pass under (a microwave's): the object goes down this far short of its
    release, in level to it, and the open hand backs out the same way before it rises. A turn
    (``row["turns"]``) lists where the fingertips close on a knob (``grip``), its ``top``, the
    grasp's ``yaw`` and the ``turn`` to give it (radians of yaw). A close (``row["closes"]``) lists the ``path`` the grip site
    pushes along, from in front of the door or drawer to past where it is shut, and its ``yaws``;
    a push (``row["pushes"]``) is alike, its path taking an object put in deeper. A step after
    another takes whichever of its yaws and yaws + pi (the fingers close alike) is nearer the
    last waypoint's yaw on average over the step: the wrist turns the least.
    """
    script: list[Waypoint] = []
    for index, (kind, entry) in enumerate(steps(row)):
        made = {
            "turn": turn_waypoints,
            "place": place_waypoints,
            "push": close_waypoints,
            "close": close_waypoints,
        }[kind](entry, gains)
        if kind != "place" and script:  # fingers that close alike at yaw and yaw + pi: turn the least, on average
            mean = float(np.mean([waypoint[1] for waypoint in made]))
            shift = closing_yaw((math.sin(mean), -math.cos(mean)), script[-1][1]) - mean
            flip = -1.0 if round(shift / math.pi) % 2 else 1.0  # the hand's x turned about: the tilt too
            made = [(position, yaw + shift, flip * tilt, *rest) for position, yaw, tilt, *rest in made]
        script.extend((*waypoint[:6], f"{index}:{waypoint[6]}") for waypoint in made)
    positions, yaws, tilts, grips, holds, carries, phases = zip(*script)
    return Waypoints(
        np.array(positions, dtype=np.float64),
        np.array(yaws, dtype=np.float64),
        np.array(tilts, dtype=np.float64),
        np.array(grips, dtype=np.float64),
        np.array(holds, dtype=np.int64),
        np.array(carries, dtype=bool),
        phases,
    )


def place_waypoints(pair: Mapping[str, Any], gains: Gains) -> list[Waypoint]:
    """Put an object in or on its goal: above it, down, close, up, above the goal, down, open, up;
    with an ``approach``, above the goal short of it by that, down, in level, open, back out, up."""
    x, y, _ = pair["pick"]
    px, py, pz = pair["place"]
    yaw = pair["yaw"]
    turned = pair.get("place_yaw", yaw)
    carry = max(pair["place_top"], pair["top"]) + gains.hover_m
    grasp = max(pair["top"] - gains.grasp_below_top_m, pair["bottom"] + gains.floor_clearance_m)
    release = pz + gains.release_above_m
    if "grip" in pair:  # an object held elsewhere than over its centre (a mug by its rim)
        x, y, grasp = pair["grip"]
    if "release" in pair:
        px, py, release = pair["release"]
    reach = [
        ((x, y, carry), yaw, 0.0, OPEN, 0, False, "reach"),
        ((x, y, grasp), yaw, 0.0, OPEN, 0, False, "reach"),
        ((x, y, grasp), yaw, 0.0, CLOSED, gains.grip_steps, False, "grasp"),
        ((x, y, carry), yaw, 0.0, CLOSED, 0, True, "lift"),
    ]
    if "approach" not in pair:
        return reach + [
            ((px, py, carry), turned, 0.0, CLOSED, 0, True, "carry"),
            ((px, py, release), turned, 0.0, CLOSED, 0, True, "lower"),
            ((px, py, release), turned, 0.0, OPEN, gains.grip_steps, False, "release"),
            ((px, py, carry), turned, 0.0, OPEN, 0, False, "retreat"),
        ]
    if len(pair["approach"]) != 2:
        raise ValueError(f"approach {pair['approach']} of {pair.get('object')}: not [x, y]")
    outside_x, outside_y = px - pair["approach"][0], py - pair["approach"][1]
    return reach + [
        ((outside_x, outside_y, carry), turned, 0.0, CLOSED, 0, True, "carry"),
        ((outside_x, outside_y, release), turned, 0.0, CLOSED, 0, True, "lower"),
        ((px, py, release), turned, 0.0, CLOSED, 0, True, "insert"),
        ((px, py, release), turned, 0.0, OPEN, gains.grip_steps, False, "release"),
        ((outside_x, outside_y, release), turned, 0.0, OPEN, 0, False, "retreat"),
        ((outside_x, outside_y, carry), turned, 0.0, OPEN, 0, False, "retreat"),
    ]


def turn_waypoints(turn: Mapping[str, Any], gains: Gains) -> list[Waypoint]:
    """Turn a knob about the vertical through its grip: above it, down, close, turn the wrist by
    ``turn``, open, up."""
    x, y, z = turn["grip"]
    above = turn["top"] + gains.hover_m
    yaw, turned = turn["yaw"], turn["yaw"] + turn["turn"]
    return [
        ((x, y, above), yaw, 0.0, OPEN, 0, False, "reach"),
        ((x, y, z), yaw, 0.0, OPEN, 0, False, "reach"),
        ((x, y, z), yaw, 0.0, CLOSED, gains.grip_steps, False, "grasp"),
        ((x, y, z), turned, 0.0, CLOSED, 0, True, "turn"),
        ((x, y, z), turned, 0.0, OPEN, gains.grip_steps, False, "release"),
        ((x, y, above), turned, 0.0, OPEN, 0, False, "retreat"),
    ]


def close_waypoints(close: Mapping[str, Any], gains: Gains) -> list[Waypoint]:
    """Push a door or drawer shut (a close) or an object deeper (a push), the fingers closed:
    above the ``path``'s start, down to it, along it (at each point its yaw of ``yaws``), back
    off from its end by ``gains.back_off_m`` the way it came, up. With ``lean`` (radians), the
    fingertips lean that far towards the path's first stretch the whole way: the arm stays back,
    clear of what the pushed part goes under (a cabinet's top over its drawers, a microwave's)."""
    path = np.asarray(close["path"], dtype=np.float64)
    yaws = [float(yaw) for yaw in close["yaws"]]
    if path.ndim != 2 or path.shape[1] != 3 or len(path) < 2 or len(yaws) != len(path):
        raise ValueError(
            f"close path {close['path']} with yaws {close['yaws']}: not two or more points [x, y, z], a yaw each"
        )
    way = path[-1] - path[-2]
    back = path[-1] - gains.back_off_m * way / max(float(np.linalg.norm(way)), 1e-9)
    above = max(float(path[:, 2].max()), float(back[2])) + gains.hover_m
    first = path[1] - path[0]

    def tilt(yaw: float) -> float:  # about the fingers' axis; the hand's x is (cos yaw, sin yaw)
        return float(close.get("lean", 0.0)) * (
            1.0 if math.cos(yaw) * first[0] + math.sin(yaw) * first[1] >= 0 else -1.0
        )

    return [
        ((path[0, 0], path[0, 1], above), yaws[0], tilt(yaws[0]), CLOSED, 0, False, "reach"),
        (tuple(path[0]), yaws[0], tilt(yaws[0]), CLOSED, 0, False, "reach"),
        *((tuple(point), yaw, tilt(yaw), CLOSED, 0, False, "push") for point, yaw in zip(path[1:], yaws[1:])),
        (tuple(back), yaws[-1], tilt(yaws[-1]), CLOSED, 0, False, "retreat"),
        ((back[0], back[1], above), yaws[-1], tilt(yaws[-1]), CLOSED, 0, False, "retreat"),
    ]


def pushing(phases: Sequence[str]) -> np.ndarray:
    """Which of a script's waypoints (their ``phases``) push a door, drawer or object."""
    return np.array([name.endswith(":push") for name in phases], dtype=bool)


class Script:
    """The scripts of a batch of envs, one init state's table row each (:func:`waypoints`; rows
    of one task, whose scripts are alike in length); :meth:`act` takes their 8-float states and
    returns their next actions ``[n, 7]``, advancing each env's waypoint."""

    def __init__(self, rows: Sequence[Mapping[str, Any]], gains: Gains = Gains()) -> None:
        scripts = [waypoints(row, gains) for row in rows]
        if len({len(s.phases) for s in scripts}) > 1:
            raise ValueError(f"rows of {sorted({len(s.phases) for s in scripts})} waypoints: not one task's")
        self.gains = gains
        self.positions = np.stack([s.positions for s in scripts])
        self.yaws = np.stack([s.yaws for s in scripts])
        self.tilts = np.stack([s.tilts for s in scripts])
        self.grips = np.stack([s.grips for s in scripts])
        self.holds = np.stack([s.holds for s in scripts])
        self.carries = np.stack([s.carries for s in scripts])
        self.pushes = np.stack([pushing(s.phases) for s in scripts])  # given ``push_timeout`` steps
        self.phases = [s.phases for s in scripts]
        self.index = np.zeros(len(rows), dtype=np.int64)  # each env's current waypoint
        self.spent = np.zeros(len(rows), dtype=np.int64)  # steps spent on it
        self.empty = np.full(len(rows), -1, dtype=np.int64)  # the waypoint its grip was first found empty at

    def restart(self, i: int, row: Mapping[str, Any]) -> None:
        """Env ``i`` starts over on the script of ``row`` (an init state of the same task)."""
        script = waypoints(row, self.gains)
        if len(script.phases) != self.positions.shape[1]:
            raise ValueError(f"env {i}: a row of {len(script.phases)} waypoints, not {self.positions.shape[1]}")
        self.positions[i], self.yaws[i], self.grips[i] = script.positions, script.yaws, script.grips
        self.tilts[i] = script.tilts
        self.holds[i], self.carries[i], self.phases[i] = script.holds, script.carries, script.phases
        self.pushes[i] = pushing(script.phases)
        self.index[i] = self.spent[i] = 0
        self.empty[i] = -1

    def phase(self, i: int, waypoint: int) -> str:
        """The phase of env ``i``'s ``waypoint``: ``"<step>:<phase>"``, or ``"done"`` past its last."""
        return self.phases[i][waypoint] if waypoint < len(self.phases[i]) else "done"

    def progress(self, i: int) -> dict[str, Any]:
        """Where env ``i`` is in its script: its waypoint's index and :meth:`phase`, and the
        phase in which its closed fingers were first found holding nothing where they should
        hold something (``empty_grip``: the object or knob slipped out, or was never caught),
        None if they never were."""
        waypoint, empty = int(self.index[i]), int(self.empty[i])
        return {
            "waypoint": waypoint,
            "phase": self.phase(i, waypoint),
            "empty_grip": self.phase(i, empty) if empty >= 0 else None,
        }

    @property
    def finished(self) -> np.ndarray:
        """The envs that went through every waypoint."""
        return self.index >= self.positions.shape[1]

    def act(self, states: np.ndarray) -> np.ndarray:
        """The next action of every env from its ``state`` row (``[n, 8]``)."""
        states = np.asarray(states, dtype=np.float64)
        n, last = len(states), self.positions.shape[1] - 1
        rows = np.arange(n)
        at = np.minimum(self.index, last)
        position = states[:, :3]
        rotation = axis_angle_to_matrix(states[:, 3:6])
        target = gripper_frame(self.yaws[rows, at], self.tilts[rows, at])
        position_error = self.positions[rows, at] - position
        rotation_error = matrix_to_axis_angle(target @ np.swapaxes(rotation, -1, -2))
        hold = self.holds[rows, at]
        reached = np.where(
            hold > 0,
            self.spent >= hold,
            (np.linalg.norm(position_error, axis=-1) < self.gains.reach_tol_m)
            & (np.linalg.norm(rotation_error, axis=-1) < self.gains.yaw_tol_rad),
        )
        timeout = np.where(self.pushes[rows, at], self.gains.push_timeout, self.gains.move_timeout)
        advance = ~self.finished & (reached | (self.spent >= timeout))
        self.index = np.where(advance, self.index + 1, self.index)
        self.spent = np.where(advance, 0, self.spent + 1)
        at = np.minimum(self.index, last)
        position_error = self.positions[rows, at] - position
        target = gripper_frame(self.yaws[rows, at], self.tilts[rows, at])
        rotation_error = matrix_to_axis_angle(target @ np.swapaxes(rotation, -1, -2))
        actions = np.zeros((n, 7))
        actions[:, :3] = self.gains.position_gain * position_error / POS_LIMIT_M
        actions[:, 3:6] = self.gains.rotation_gain * rotation_error / ROT_LIMIT_RAD
        actions[:, 6] = self.grips[rows, at]
        # Moving with something held (the grasp's hold done) and nothing between the fingers.
        holding = self.carries[rows, at] & ~self.finished
        empty = holding & (states[:, 6] - states[:, 7] < self.gains.empty_grip_m) & (self.empty < 0)
        self.empty = np.where(empty, self.index, self.empty)
        return np.clip(actions, -1.0, 1.0).astype(np.float32)
