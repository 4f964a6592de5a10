"""Success rates of a scripted policy over LIBERO init states, on the ``cpu`` and ``mjwarp``
engines, through real pods and ``HTTPVectorEnv``.

The policy (``lib/scripted.py``) is closed loop on the end effector and open loop on the
scene: ``table`` (the CPU stack: robosuite, LIBERO) measures, for each init state of each task,
where the goal's objects and regions are after a CPU pod's reset (settle steps included), and
the knobs to turn on and the doors or drawers to push shut (``lib/fixtures.py``), and writes
``bench/lib/scripted_table.json``, which the bench carries (rows of other tasks kept)::

    python bench/bench_scripted.py table --tasks libero_10/0 libero_10/1 libero_10/4 libero_10/6 libero_10/7
    python bench/bench_scripted.py table --libero rlinf --tasks libero_10/5 libero_10/8
    python bench/bench_scripted.py table --libero rlinf --tasks libero_10/2 libero_10/3 libero_10/9

``--libero`` (both commands) names the LIBERO protocol: ``published`` (LIBERO's evaluation, the
default) or ``rlinf`` (RLinf's: 15 settle steps, ``first_reset`` fixtures, under which the
``mjwarp`` engine serves the tasks whose fixtures move between init states, 2, 3, 5, 8 and 9
among them). Rows are keyed by task and protocol (:func:`row_key`): a run reads only rows
measured under its own protocol, and its pods run under it.

``run`` starts one real pod (``vecsim pod``, uvicorn, loopback) per task and engine, resets its
envs to the init states (all 50 by default, ``--envs`` at a time, an env taking the next state
when its episode ends) and runs the policy to each episode's end (LIBERO's success, or the
suite's step limit). An env that raises (a world no longer finite, say) ends only its own
episode: the state is recorded as an error (``per_state[k]["error"]``, the exception's text) and
the env takes the next state. Per task and engine: successes, errors and their state ids, the
rate with its Wilson 95% interval over the episodes that ended without an error, the mean
episode length of the successes, and with both engines the agreement per init state (states
that errored on either engine counted apart). Each episode's record names the waypoint and
phase the policy was at when it ended (``<step>:<phase>``) and where its closed fingers were
first found empty (``per_state[k]``: ``waypoint``, ``phase``, ``empty_grip``); the summary
counts the failures by both. Each engine's pods run under their own ``PYTHONPATH`` (the two
stacks pin different mujoco versions); this process needs only the client. The record
is written after every task and engine, so a run cut short keeps what it did::

    python bench/bench_scripted.py run --engines cpu mjwarp --tasks libero_10/0 \\
        --cpu-pythonpath /tmp/site --mjwarp-pythonpath /tmp/site-mjw:/tmp/site \\
        --out out/bench/bench_scripted.json

``--smoke`` runs two init states of one task on the ``cpu`` engine (a test's check that the
path works, no figure).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import os
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from lib.jobs import RLINF_PROTOCOL
from lib.records import command_line, machine_info, write_record
from lib.fixtures import INSERTS, SHUTS, inserted_pair, knob_turn, shut_path
from lib.scripted import Episodes, Gains, Script, agreement, closing_yaw, summary

from vecsim.client.errors import ClientError
from vecsim.config import Assignment, CameraConfig, LiberoProtocol, TaskBlock

log = logging.getLogger("bench_scripted")

TABLE = Path(__file__).resolve().parent / "lib" / "scripted_table.json"
CODE = Path(__file__).resolve().parents[1]
# The LIBERO protocols a table and a run can take (``--libero``): LIBERO's published evaluation,
# and RLinf's (15 settle steps, every init state on a fresh env's first fixture placement), the
# one under which the ``mjwarp`` engine serves every LIBERO-10 task (docs/mjwarp.md).
PROTOCOLS = {
    "published": LiberoProtocol(),
    "rlinf": RLINF_PROTOCOL,
}


# Tasks whose script moves otherwise than :class:`Gains`'s defaults (tuned on libero_10/0):
# libero_10/5's book hangs 11 cm under the fingers, so it is carried higher, clear of the
# caddy's walls (at the default height it catches on them and turns in the grasp).
# libero_10/9's hand crosses the open microwave door's top (1.11 m) on its way to push it: it
# moves 20 cm over what it carries or pushes, not 12; and twice as fast towards its waypoints
# (full speed until 2.5 cm from one, not 5): its three steps (the mug in, pushed deeper, the
# door's ten-point arc) then take 363-420 of the suite's 520 steps; at the default speed, an
# earlier version of the script left init state 0's door 0.1 rad open at the 520th.
TASK_GAINS = {"libero_10/5": Gains(hover_m=0.2), "libero_10/9": Gains(hover_m=0.2, position_gain=2.0)}


def task_gains(task: str) -> Gains:
    """The script's gains for ``task``: its own (:data:`TASK_GAINS`) or the defaults."""
    return TASK_GAINS.get(task, Gains())


def row_key(task: str, protocol: LiberoProtocol) -> str:
    """The table's key of ``task``'s rows measured under ``protocol``: the task id under the
    default (published) protocol, else the task id and every setting that differs from it
    (``libero_10/5@fixture_rule=first_reset,settle_steps=15``), so rows measured under one
    protocol are never read for another."""
    default = LiberoProtocol().model_dump()
    changed = sorted((k, v) for k, v in protocol.model_dump().items() if v != default[k])
    return task if not changed else f"{task}@" + ",".join(f"{k}={v}" for k, v in changed)


# -- the table (CPU stack) ---------------------------------------------------------------------


def body_corners(model: Any, data: Any, body: int, colliding: bool = False) -> np.ndarray:
    """The world corners ``[8 * geoms, 3]`` of the bounding boxes of every geom of ``body``'s tree
    (with ``colliding``, of its geoms that collide only: visual meshes left out)."""
    corners = []
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
    geoms = model.body_rootid[model.geom_bodyid] == body
    if colliding:
        geoms &= (model.geom_contype != 0) | (model.geom_conaffinity != 0)
    for geom in np.flatnonzero(geoms):
        centre, half = model.geom_aabb[geom, :3], model.geom_aabb[geom, 3:]
        local = centre + signs * half
        corners.append(data.geom_xpos[geom] + local @ data.geom_xmat[geom].reshape(3, 3).T)
    return np.concatenate(corners)


@dataclass(frozen=True)
class Grasp:
    """How the script holds an object that its centre and narrowest side do not suit. Points are
    in the object's body frame (x, y), read off the collision geoms of LIBERO's model."""

    at: tuple[float, float]  # where the fingers close
    centre: tuple[float, float] | None = None  # given: the fingers close along ``at - centre``
    depth_m: float = 0.02  # the fingertips' centre this far under the top of its collision geoms
    clearance_m: float = 0.012  # its bottom this far above the goal's top when let go


# By LIBERO object category (the object's name without its ``_<n>`` suffix). A mug is too wide
# for the Panda's 8 cm: it is held by the rim, the fingers astride the wall across from the
# handle and closing along the radius (``centre``: the mean of the wall boxes' centres; ``at``:
# the wall box across from the handle). A moka pot is held round its 6.8 cm body, across its
# narrowest side, 5 cm under its lid's knob (its visual mesh reaches 3 cm above its collision
# geoms, where the default grasp would close on air); it is let go 3.5 cm over its region's site,
# which lies 2.3 cm under the stove's burner.
GRASPS = {
    "porcelain_mug": Grasp(at=(0.0568, -0.0015), centre=(0.0157, 0.0)),
    "white_yellow_mug": Grasp(at=(-0.0604, -0.0045), centre=(-0.018, 0.0)),
    "moka_pot": Grasp(at=(0.0, 0.07), depth_m=0.046, clearance_m=0.035),
    # A bowl (10.5 cm) by its rim on its world -x side (its frame turned a quarter), the fingers closing along x: the hand, 21 cm
    # along the fingers, then stays clear of the cabinet above an open drawer it goes into.
    "akita_black_bowl": Grasp(at=(0.0, 0.0475), centre=(0.0, 0.0)),
}

# Fixtures whose regions reach far above the floor things stand on inside them (a cabinet's
# drawer): an object is let go just over that floor (found under the region's centre), not over
# the region's top, and its body this far off the region's centre (metres, in the fixture's
# frame). A bowl goes 2.2 cm towards a drawer's open side: its far rim then passes the handles of
# the drawers above, which overhang the open drawer's back, by 4 mm at most.
INSIDE = {"white_cabinet": (0.0, -0.022)}
# Tasks whose objects share one goal region, and how far apart (metres, along the region's x
# axis) their places are set, in the goal's order: libero_10/8's two moka pots on one burner.
SHARED_GOAL_SPACING_M = {"libero_10/8": 0.084}


def scene_row(inner: Any, spacing_m: float = 0.0) -> dict[str, Any]:
    """Where the goal's objects and goals are in ``inner`` (a LIBERO env, now): for each of the
    goal's ``in``/``on`` predicates, in order, the object's centre, top, bottom and grasp yaw (its
    narrowest horizontal direction), and the goal's centre and top (a region site, or an
    object's bounding box). A goal's other terms must hold already (the script leaves them be),
    but for knobs to turn on and doors or drawers to close. With ``spacing_m``, objects that share a goal get places that far
    apart along the goal's x axis, centred on it. A region site at least twice as long as wide
    (a slot) adds ``place_yaw``, turning the object's narrowest side across it, unless it is of
    :data:`GRASPS`: those add ``grip`` (where the fingertips close) and ``release`` (where they
    open: its body over the goal object's body, or over the region site, as LIBERO's ``On``
    checks; over the floor under it in an :data:`INSIDE` fixture). An object going into a
    fixture of :data:`INSERTS` adds ``grip``, ``yaw``, ``release`` and ``approach`` instead, and
    a ``pushes`` entry that takes it deeper (:func:`inserted_pair`). A ``turnon`` term adds a
    ``turns`` entry (:func:`knob_turn`), a ``close`` term of a :data:`SHUTS` fixture a ``closes``
    entry (:func:`shut_path`)."""
    import mujoco

    model, data = inner.sim.model._model, inner.sim.data._data
    terms, turns, closes = [], [], []
    for term in inner.parsed_problem["goal_state"]:
        if len(term) == 3 and term[0].lower() in ("in", "on"):
            terms.append(term)
        elif inner._eval_predicate(term):
            continue  # holds already (libero_10/8's stove is on): the script leaves it be
        elif len(term) == 2 and term[0].lower() == "turnon":
            turns.append(knob_turn(inner, term[1]))
        elif len(term) == 2 and term[0].lower() == "close" and category(inner, term[1]) in SHUTS:
            closes.append(shut_path(inner, term[1], SHUTS[category(inner, term[1])]))
        else:
            raise ValueError(f"task goal {term}: the script cannot make it hold")
    sharing = [sum(1 for t in terms if t[2] == term[2]) for term in terms]
    pairs, pushes = [], []
    for index, (_, obj, goal) in enumerate(terms):
        body = inner.obj_body_id[obj]
        corners = body_corners(model, data, body)
        spread = corners[:, :2] - corners[:, :2].mean(axis=0)
        narrowest = np.linalg.eigh(spread.T @ spread)[1][:, 0]
        site = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, goal)
        slot = None
        if site >= 0:
            place = data.site_xpos[site].copy()
            place_top = float(place[2] + model.site_size[site, 2])
            goal_xy, x_axis = place[:2], data.site_xmat[site].reshape(3, 3)[:2, 0]
            release_top, shift = place_top, INSIDE.get(category(inner, goal))
            if shift is not None:
                release_top = floor_under(model, data, site, body)
                frame = data.xmat[inner.obj_body_id[inner.object_states_dict[goal].parent_name]].reshape(3, 3)
                goal_xy = goal_xy + frame[:2, :2] @ np.array(shift)
            slot = slot_axis(model, data, site)
        else:
            around = body_corners(model, data, inner.obj_body_id[goal])
            place_top = release_top = float(around[:, 2].max())
            place = np.array([*around[:, :2].mean(axis=0), place_top])
            goal_body = inner.obj_body_id[goal]
            goal_xy, x_axis = data.xpos[goal_body][:2], data.xmat[goal_body].reshape(3, 3)[:2, 0]
        if spacing_m and sharing[index] > 1:
            rank = sum(1 for t in terms[:index] if t[2] == goal)
            shift = (rank - (sharing[index] - 1) / 2) * spacing_m * x_axis
            goal_xy, place = goal_xy + shift, place + [*shift, 0.0]
        pair = {
            "object": obj,
            "goal": goal,
            "pick": [round(float(v), 5) for v in data.xpos[body]],
            "top": round(float(corners[:, 2].max()), 5),
            "bottom": round(float(corners[:, 2].min()), 5),
            "yaw": round(closing_yaw(narrowest), 4),
            "place": [round(float(v), 5) for v in place],
            "place_top": round(place_top, 5),
        }
        grasp = GRASPS.get(obj.rsplit("_", 1)[0])
        insert = INSERTS.get((obj.rsplit("_", 1)[0], category(inner, goal)))
        if slot is not None and grasp is None and insert is None:  # one held by a Grasp goes in as it was held
            pair["place_yaw"] = round(closing_yaw(slot, pair["yaw"]), 4)
        if insert is not None:  # the door's push comes next: the wrist starts near its mean yaw
            prefer = float(np.mean(closes[0]["yaws"])) if closes else 0.0
            place, push = inserted_pair(inner, obj, goal, insert, floor_under(model, data, site, body), prefer)
            pair.update(place)
            pushes.append(push)
        elif grasp is not None:
            pair.update(held_pair(model, data, body, grasp, goal_xy, release_top))
        pairs.append(pair)
    row: dict[str, Any] = {"pairs": pairs}
    if turns:
        row["turns"] = turns
    if pushes:
        row["pushes"] = pushes
    if closes:
        row["closes"] = closes
    return row


def category(inner: Any, name: str) -> str:
    """The LIBERO category of ``name``: an object's or fixture's name without its ``_<n>``
    suffix, or a region site's fixture's (``white_cabinet_1_bottom_region``: ``white_cabinet``)."""
    if name in inner.object_sites_dict:
        name = inner.object_states_dict[name].parent_name
    return name.rsplit("_", 1)[0]


def floor_under(model: Any, data: Any, site: int, held: int) -> float:
    """The height of the first colliding surface under region ``site``'s centre, ``held`` (the
    object to put there) left out."""
    import mujoco

    found = np.zeros(1, dtype=np.int32)
    collide = np.array([1, 0, 0, 0, 0, 0], dtype=np.uint8)  # robosuite's collision geoms: group 0
    centre = data.site_xpos[site]
    distance = mujoco.mj_ray(model, data, centre, np.array([0.0, 0.0, -1.0]), collide, 1, held, found)
    if found[0] < 0:
        raise ValueError(f"region {model.site(site).name}: no floor under its centre")
    return float(centre[2] - distance)


def slot_axis(model: Any, data: Any, site: int, ratio: float = 2.0) -> np.ndarray | None:
    """The horizontal direction along which a region site is narrow, if it is ``ratio`` times
    narrower one way than the other (a caddy's back compartment); None for a squarer one."""
    half = model.site_size[site, :2]
    axes = data.site_xmat[site].reshape(3, 3)[:2, :2]
    if half.max() < ratio * half.min():
        return None
    return axes[:, int(np.argmin(half))]


def held_pair(model: Any, data: Any, body: int, grasp: Grasp, goal_xy: np.ndarray, goal_top: float) -> dict[str, Any]:
    """An object's ``grip`` and ``release`` (and ``yaw``, with a ``centre``) under ``grasp``,
    where it stands now."""
    frame = data.xmat[body].reshape(3, 3)[:2, :2]
    origin = data.xpos[body]
    solid = body_corners(model, data, body, colliding=True)
    grip_xy = origin[:2] + frame @ np.array(grasp.at)
    grip_z = float(solid[:, 2].max()) - grasp.depth_m
    # Carried without turning: the body goes where its grip point's offset puts it.
    release_xy = goal_xy + grip_xy - origin[:2]
    release_z = goal_top + grasp.clearance_m + grip_z - float(solid[:, 2].min())
    held = {
        "grip": [round(float(v), 5) for v in (*grip_xy, grip_z)],
        "release": [round(float(v), 5) for v in (*release_xy, release_z)],
    }
    if grasp.centre is not None:
        held["yaw"] = round(closing_yaw(frame @ (np.array(grasp.at) - np.array(grasp.centre))), 4)
    return held


def table(args: argparse.Namespace) -> None:
    """Measure the table's rows for ``--tasks`` (all of each task's init states) on the CPU stack,
    under the ``--libero`` protocol (keyed by :func:`row_key`); other rows are kept as they are."""
    from vecsim.engine.tasks import make_env

    protocol = PROTOCOLS[args.libero]
    rows: dict[str, list[dict[str, Any]]] = json.loads(args.out.read_text()) if args.out.exists() else {}
    for task in args.tasks:
        key = row_key(task, protocol)
        env = make_env(task, CameraConfig(names=(), height=128, width=128), libero=protocol)
        try:
            rows[key] = []
            for k in range(env.task.num_states):
                env.reset(options={"state_id": k})
                rows[key].append(scene_row(env.inner, SHARED_GOAL_SPACING_M.get(task, 0.0)))
        finally:
            env.close()
        log.info("%s: %d init states", key, len(rows[key]))
    # One init state a line: the file is read by people too.
    lines = ",\n".join(
        f"{json.dumps(task)}: [\n" + ",\n".join(json.dumps(row) for row in task_rows) + "\n]"
        for task, task_rows in sorted(rows.items())
    )
    args.out.write_text("{\n" + lines + "\n}\n")


# -- the runs (any stack with the client) --------------------------------------------------------


@contextmanager
def pod(
    engine: str,
    task: str,
    envs: int,
    pythonpath: str | None,
    port: int,
    ready_s: float,
    protocol: LiberoProtocol = PROTOCOLS["published"],
) -> Iterator[str]:
    """One real pod (``vecsim pod``) of ``envs`` envs of ``task`` on ``engine`` under the LIBERO
    ``protocol``, no cameras; its URL."""
    import httpx

    spec = Assignment(
        generation=0,
        pod="sim-0",
        stage_id=0,
        engine=engine,
        camera=CameraConfig(names=()),
        libero=protocol,
        tasks=(TaskBlock(task_id=task, env_start=0, num_envs=envs),),
    )
    env = {**os.environ, "VECSIM_MAX_ENVS": str(envs), "VECSIM_BUILD_TIMEOUT_S": str(int(ready_s))}
    env["PYTHONPATH"] = ":".join(p for p in (str(CODE), pythonpath or env.get("PYTHONPATH")) if p)
    url = f"http://127.0.0.1:{port}"
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "assignment.json"
        path.write_text(spec.model_dump_json())
        command = [sys.executable, "-m", "service.cli", "pod", "--assignment", str(path), "--port", str(port)]
        process = subprocess.Popen(command, env=env, cwd=CODE)
        try:
            started = time.monotonic()
            with httpx.Client(timeout=30) as client:
                while True:
                    try:
                        if client.get(f"{url}/readyz").status_code == 200:
                            break
                    except httpx.TransportError:
                        pass  # not listening yet
                    if process.poll() is not None:
                        raise RuntimeError(f"{engine} pod for {task} exited with {process.returncode} before ready")
                    if time.monotonic() - started > ready_s:
                        raise RuntimeError(f"{engine} pod for {task} not ready after {ready_s:.0f} s")
                    time.sleep(1.0)
            log.info("%s pod for %s ready in %.0f s", engine, task, time.monotonic() - started)
            yield url
        finally:
            process.terminate()
            try:
                process.wait(timeout=60)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait(timeout=30)


class Policy(Protocol):
    """What :func:`run_episodes` drives: a policy per env, told which init state each env starts.
    A policy that has ``progress(env_index) -> dict`` too has it recorded with each episode's end."""

    def restart(self, env_index: int, state_id: int) -> None: ...

    def act(self, obs: Any) -> np.ndarray: ...


class Scripted:
    """The scripted policy over ``rows`` (the table's rows of one task) for ``num_envs`` envs."""

    def __init__(self, rows: Sequence[dict[str, Any]], num_envs: int, gains: Gains) -> None:
        self.rows = rows
        self.script = Script([rows[0]] * num_envs, gains)

    def restart(self, env_index: int, state_id: int) -> None:
        self.script.restart(env_index, self.rows[state_id])

    def act(self, obs: Any) -> np.ndarray:
        return self.script.act(obs["state"])

    def progress(self, env_index: int) -> dict[str, Any]:
        """The env's waypoint and phase (:meth:`Script.progress`)."""
        return self.script.progress(env_index)


def env_error(exc: BaseException) -> bool:
    """Whether ``exc`` is an env's own exception (its episode's), not a failure of the call or pod."""
    return not isinstance(exc, ClientError) and getattr(exc, "failed_envs", None) is not None


def error_text(exc: BaseException) -> str:
    """The exception's type and message, and its notes (the other envs' messages)."""
    return "; ".join([f"{type(exc).__name__}: {exc}", *getattr(exc, "__notes__", ())])


def run_episodes(env: Any, state_ids: Sequence[int], policy: Policy) -> dict[int, dict[str, Any]]:
    """Run ``policy`` from each of ``state_ids`` to its episode's end on ``env`` (an
    ``HTTPVectorEnv``, autoreset disabled), as many at a time as it has envs, an env taking the
    next state when its episode ends. An env that raises ends only its own episode (an error,
    with the exception's text) and takes the next state. Returns :class:`Episodes`'s ``outcome``,
    each episode's with the policy's ``progress`` at its end if the policy has one."""
    book = Episodes(state_ids, env.num_envs)
    progress = getattr(policy, "progress", None)
    obs = start(env, book, policy, range(env.num_envs))
    while book.running.any():
        active = np.flatnonzero(book.running)
        actions = policy.act(obs)[active, None]  # a chunk of one action per running env
        failed: list[int] = []
        try:
            obs, _, terminated, truncated, _ = env.chunk_step(actions, env_ids=active)
        except Exception as exc:
            if not env_error(exc):
                raise
            obs, _, terminated, truncated, _ = exc.result
            failed = list(exc.failed_envs)
            book.fail(failed, error_text(exc), notes(progress, failed))
            log.warning("envs %s raised; their episodes are errors: %s", failed, error_text(exc))
        stepped = [int(i) for i in active if i not in failed]
        over = [i for i in stepped if terminated[i, 0] or truncated[i, 0]]
        ended = book.step(stepped, terminated[stepped, 0], truncated[stepped, 0], notes(progress, over))
        if ended or failed:
            obs = start(env, book, policy, ended + failed, obs)
    return book.outcome


def notes(progress: Any, envs: Iterable[int]) -> dict[int, dict[str, Any]] | None:
    """``progress(env)`` of each of ``envs`` (a policy's, before it restarts them); None without one."""
    return None if progress is None else {int(i): progress(int(i)) for i in envs}


def start(env: Any, book: Episodes, policy: Policy, envs: Iterable[int], obs: Any = None) -> Any:
    """Reset ``envs`` to the next states not yet run (an env none is left for idles); a state whose
    reset raises is an error and its env takes the next. Returns the observations."""
    envs = list(envs)
    while envs:
        given = book.assign(envs)
        if not given:
            break
        mask = np.zeros(env.num_envs, dtype=bool)
        state_ids = np.zeros(env.num_envs, dtype=np.int64)
        mask[list(given)], state_ids[list(given)] = True, list(given.values())
        try:
            obs, _ = env.reset(options={"state_ids": state_ids, "reset_mask": mask})
            envs = []
        except Exception as exc:
            if not env_error(exc):
                raise
            obs, envs = exc.result[0], list(exc.failed_envs)
            book.fail(envs, error_text(exc))
            log.warning("envs %s raised in their reset; their episodes are errors: %s", envs, error_text(exc))
        for i, k in given.items():
            if i not in envs:
                policy.restart(i, k)
    return obs


def episodes(url: str, rows: Sequence[dict[str, Any]], state_ids: Sequence[int], gains: Gains) -> dict[int, dict]:
    """The scripted policy from each of ``state_ids`` through ``HTTPVectorEnv`` on the pod at
    ``url``: :func:`run_episodes`'s outcome."""
    from vecsim.client.vector_env import HTTPVectorEnv

    env = HTTPVectorEnv(pod_urls=[url], autoreset_mode="disabled", timeout_s=600)
    try:
        outcome = run_episodes(env, state_ids, Scripted(rows, env.num_envs, gains))
    finally:
        env.close()
    done = summary(outcome)
    log.info(
        "%d of %d succeeded, %d errors %s", done["successes"], done["states"], done["errors"], done["error_state_ids"]
    )
    return outcome


def run(args: argparse.Namespace) -> None:
    """Every task of ``--tasks`` on every engine of ``--engines`` under the ``--libero``
    protocol (the table's rows measured under it), a record after each."""
    import httpx

    rows = json.loads(args.table.read_text())
    protocol = PROTOCOLS[args.libero]
    deadline = time.monotonic() + args.budget_s
    record: dict[str, Any] = {
        "name": "bench_scripted",
        "command": command_line(),
        "machine": {**machine_info(), "name": args.machine},
        "libero": {"name": args.libero, **protocol.model_dump()},
        "policy": asdict(Gains()),
        "table": {"file": args.table.name, "sha256": hashlib.sha256(args.table.read_bytes()).hexdigest()},
        "tasks": {},
        "complete": False,
    }
    for task in args.tasks:
        if row_key(task, protocol) not in rows:
            raise SystemExit(
                f"--tasks: {task} has no row under --libero {args.libero} ({row_key(task, protocol)}) in "
                f"{args.table}; run `table --tasks {task} --libero {args.libero}` first"
            )
    for index, task in enumerate(args.tasks):
        task_rows = rows[row_key(task, protocol)]
        gains = task_gains(task)
        entry = record["tasks"].setdefault(task, {})
        if gains != Gains():
            entry["policy"] = asdict(gains)  # the task's own, in place of the record's
        state_ids = list(range(min(args.states, len(task_rows))))
        for offset, engine in enumerate(args.engines):
            if time.monotonic() > deadline:
                record["cut_short"] = f"budget of {args.budget_s} s spent before {task} on {engine}"
                break
            pythonpath = {"cpu": args.cpu_pythonpath, "mjwarp": args.mjwarp_pythonpath}[engine]
            began = time.monotonic()
            try:
                envs = min(args.envs, len(state_ids))
                port = args.port + 2 * index + offset
                with pod(engine, task, envs, pythonpath, port, args.ready_timeout_s, protocol) as url:
                    outcome = episodes(url, task_rows, state_ids, gains)
            except (RuntimeError, OSError, ValueError, httpx.HTTPError, ClientError) as exc:
                entry[engine] = {"error": str(exc)}
                log.error("%s on %s failed: %s", task, engine, exc)
            else:
                entry[engine] = {
                    **summary(outcome),
                    "seconds": round(time.monotonic() - began, 1),
                    "per_state": {str(k): v for k, v in outcome.items()},
                }
                done = entry[engine]
                log.info("%s on %s: %d/%d, %d errors", task, engine, done["successes"], done["states"], done["errors"])
            if all("per_state" in entry.get(e, {}) for e in ("cpu", "mjwarp")):
                first, second = (
                    {int(k): v.get("success") for k, v in entry[e]["per_state"].items()} for e in ("cpu", "mjwarp")
                )
                entry["agreement"] = agreement(first, second)
            write_record(record, args.out)
        if "cut_short" in record:
            break
    else:
        record["complete"] = True
    write_record(record, args.out)
    brief = {
        task: {e: {k: v for k, v in r.items() if k != "per_state"} if isinstance(r, dict) else r for e, r in t.items()}
        for task, t in record["tasks"].items()
    }
    print("RESULT", json.dumps({"name": record["name"], "complete": record["complete"], "tasks": brief}), flush=True)


LIBERO_HELP = "the LIBERO protocol: published (LIBERO's evaluation) or rlinf (15 settle steps, first_reset fixtures)"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    measure = sub.add_parser("table", help="where each init state's objects are (the CPU stack)")
    measure.add_argument("--tasks", nargs="+", default=["libero_10/0"])
    measure.add_argument("--out", type=Path, default=TABLE)
    measure.add_argument("--libero", choices=sorted(PROTOCOLS), default="published", help=LIBERO_HELP)
    go = sub.add_parser("run", help="the policy's success over the init states, per task and engine")
    go.add_argument("--tasks", nargs="+", default=["libero_10/0"])
    go.add_argument("--engines", nargs="+", choices=["cpu", "mjwarp"], default=["cpu"])
    go.add_argument("--states", type=int, default=50, help="init states 0..N-1 of each task")
    go.add_argument("--envs", type=int, default=50, help="envs of each pod (states run this many at a time)")
    go.add_argument("--table", type=Path, default=TABLE)
    go.add_argument("--libero", choices=sorted(PROTOCOLS), default="published", help=LIBERO_HELP)
    go.add_argument("--cpu-pythonpath", default=None, help="the CPU stack's PYTHONPATH (default: this process's)")
    go.add_argument("--mjwarp-pythonpath", default=None, help="the mjwarp stack's PYTHONPATH (default: this process's)")
    go.add_argument("--port", type=int, default=8300)
    go.add_argument("--ready-timeout-s", type=float, default=600.0)
    go.add_argument("--budget-s", type=float, default=3600.0, help="no new task or engine is started after this")
    go.add_argument("--machine", default=os.uname().nodename, help="names the machine in the record")
    go.add_argument("--out", type=Path, default=Path("out/bench/bench_scripted.json"))
    go.add_argument("--smoke", action="store_true", help="two init states of the first task, cpu only")
    args = parser.parse_args()
    if args.command == "run" and args.smoke:
        args.tasks, args.engines, args.states, args.envs = args.tasks[:1], ["cpu"], 2, 2
    # `timeout` ends a run with SIGTERM: exit through the pods' `finally`, never orphaning one.
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    logging.getLogger("httpx").setLevel(logging.WARNING)
    {"table": table, "run": run}[args.command](args)


if __name__ == "__main__":
    main()
