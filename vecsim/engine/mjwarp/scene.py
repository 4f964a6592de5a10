"""LIBERO scenes for the ``mjwarp`` engine, exported from the CPU engine and cached on disk.

The ``mjwarp`` engine runs in an environment of its own (mujoco 4, no robosuite, no LIBERO), so a
task's scene is built once with the CPU stack (robosuite 1.4, LIBERO, mujoco 3.3) and handed over
as files, one folder per task and LIBERO protocol (:func:`scene_dir`):

- ``scene.xml`` and ``assets/``: the compiled model as MJCF (``mj_saveLastXML``) with every mesh
  and texture it loads copied beside it. ``mj_saveLastXML`` alone does not give back the model
  LIBERO steps: the compiler derives the objects' inertias from their meshes again, and gets
  masses up to twice too high. So every body's ``<inertial>`` is written from the runtime model,
  and :func:`model_differences` checks the reloaded model field by field against it;
- ``states.npz``: for each of LIBERO's init states ``k``, the state a CPU pod's reset to ``k``
  leaves after its settle steps (``qpos``, ``qvel``, ``act``, ``ctrl``, ``qacc_warmstart``,
  ``time``), that reset's fixture placement (``body_pos``, ``body_quat``: fixtures live in the
  model), the arm controller's nullspace target (``initial_joint``) and goal, the gripper's
  command, the observation and success the CPU pod answered (``obs_state``, ``obs_proprio``,
  ``success``), and the kinematics its cameras drew them from (``view.*``, :data:`VIEW_FIELDS`,
  at LIBERO's last observable sample): an ``mjwarp`` reset to ``k`` starts exactly where a CPU
  reset ends and shows what it showed;
- ``tables.npz``: what the batched controller, observables and success predicates read of the
  model (``panda.*``: :class:`~vecsim.engine.mjwarp.controller.PandaIndex`, ``obs.*``:
  :class:`~vecsim.engine.mjwarp.observables.ObservableIndex`, ``goal.*``:
  :class:`~vecsim.engine.mjwarp.predicates.GoalTable`), ids in the compiled model, which the
  MJCF keeps in order;
- ``manifest.json``: the task, its episode limit, the protocol, versions, the goal's atoms (or
  why its predicates have no batched form yet), and the robot by name (eef site, arm joints and
  actuators, gripper actuators, torque limits, substeps per action).

Export (the CPU stack)::

    python -m vecsim.engine.mjwarp.scene libero_10/0 libero_10/1 [--root DIR] [--libero '{"settle_steps": 15}']

:func:`load_scene` reads a folder with numpy and json alone.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import logging
import os
import shutil
import sys
import tempfile
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from vecsim.config import LiberoProtocol

log = logging.getLogger(__name__)

# Bumped whenever what a scene folder holds changes, so a stale cache is never read.
SCENE_FORMAT = 4  # 4: what the cameras see at each reset (``view.*``); the digest drops the orientation
ROOT_ENV = "VECSIM_MJWARP_SCENES"
# The kinematics MuJoCo Warp's ray tracer reads (its render.py and bvh.py); at a reset they are
# recorded where LIBERO's observables last sampled, which is what a CPU pod's cameras draw.
VIEW_FIELDS = ("geom_xpos", "geom_xmat", "cam_xpos", "cam_xmat", "light_xpos", "light_xdir")
# What a scene's content depends on: the image orientation is applied when frames are unpacked.
_PROTOCOL_KEY = ("settle_steps", "fixture_seed", "fixture_rule")
# Model fields allowed to differ after the round trip through MJCF, and by how much: MJCF holds
# six significant digits, so values read back carry relative errors near 1e-6; fields derived
# from them (inverse weights, the bounding volumes) carry the same, relatively.
RTOL = 2e-5
ATOL = 1e-6
# Not physics: where each asset's file name sits in the model's string table (the export renames
# the files on purpose), and the bounding-volume tree, rebuilt from the same geoms.
UNCHECKED_FIELDS = frozenset(
    {
        "mesh_pathadr",
        "tex_pathadr",
        "hfield_pathadr",
        "skin_pathadr",
        "bvh_nodeid",
        "bvh_child",
        "bvh_aabb",
        "bvh_depth",
    }
)
# Read only for cameras and lights that track their subtree's centre of mass (mjCAMLIGHT_TRACKCOM):
# compiled from the placement the model was built with, which the export's moved fixtures change.
_TRACKCOM_FIELDS = {"cam_poscom0": "cam_mode", "light_poscom0": "light_mode"}
_TRACKCOM = 2


def default_root() -> Path:
    """Where scenes are cached: ``$VECSIM_MJWARP_SCENES``, else ``~/.cache/vecsim/mjwarp-scenes``."""
    return Path(os.environ.get(ROOT_ENV) or Path.home() / ".cache" / "vecsim" / "mjwarp-scenes")


def scene_dir(task_id: str, protocol: LiberoProtocol, root: Path | None = None) -> Path:
    """The folder of ``task_id``'s scene under ``protocol`` (its settle steps and fixtures)."""
    fields = {name: getattr(protocol, name) for name in _PROTOCOL_KEY}
    key = json.dumps({"format": SCENE_FORMAT, **fields}, sort_keys=True)
    digest = hashlib.sha256(key.encode()).hexdigest()[:12]
    return (root or default_root()) / f"{task_id.replace('/', '-')}-{digest}"


@dataclass(frozen=True)
class Scene:
    """One exported scene: ``xml`` (the model file), ``manifest``, and ``states`` (name ->
    array with one row per init state)."""

    path: Path
    manifest: dict[str, Any]
    states: dict[str, np.ndarray]

    @property
    def xml(self) -> Path:
        return self.path / "scene.xml"

    @property
    def num_states(self) -> int:
        return int(self.manifest["num_states"])


def load_scene(path: Path) -> Scene:
    """Read the scene exported into ``path``.

    Raises:
        FileNotFoundError: no complete scene there (the message says how to export one).
        ValueError: a scene of another format.
    """
    manifest_path = path / "manifest.json"
    if not manifest_path.is_file():
        raise FileNotFoundError(
            f"no exported scene at {path}: export it with the CPU stack, "
            f"python -m vecsim.engine.mjwarp.scene TASK_ID --root {path.parent}"
        )
    manifest = json.loads(manifest_path.read_text())
    if manifest.get("format") != SCENE_FORMAT:
        raise ValueError(f"{path}: scene format {manifest.get('format')}, this engine reads {SCENE_FORMAT}")
    with np.load(path / "states.npz") as npz:
        states = {name: npz[name] for name in npz.files}
    return Scene(path=path, manifest=manifest, states=states)


def refusal(manifest: dict[str, Any]) -> str | None:
    """Why the ``mjwarp`` engine cannot serve the scene of ``manifest``, or None when it can."""
    goal = manifest["goal"]
    if goal["atoms"] is None:
        return f"the mjwarp engine has no batched success predicate for it: {goal['unsupported']}"
    if manifest["fixtures_vary"]:
        return (
            "its fixtures move from one init state to the next, and the mjwarp engine holds one model per task; "
            "serve it on the cpu engine, or with libero.fixture_rule 'first_reset'"
        )
    return None


def model_differences(reference: Any, exported: Any) -> dict[str, str]:
    """Every numeric field of two ``MjModel`` that differs beyond :data:`RTOL`/:data:`ATOL`
    (fields in :data:`UNCHECKED_FIELDS` aside): field -> what differs. Empty when they agree."""
    found: dict[str, str] = {}
    for name in dir(reference):
        want = getattr(reference, name, None)
        if name.startswith("_") or name in UNCHECKED_FIELDS or not isinstance(want, np.ndarray):
            continue
        have = getattr(exported, name)
        if name in _TRACKCOM_FIELDS and want.shape == have.shape:
            tracking = getattr(reference, _TRACKCOM_FIELDS[name]) == _TRACKCOM
            want, have = want[tracking], have[tracking]
        if want.shape != have.shape:
            found[name] = f"shape {have.shape}, LIBERO's {want.shape}"
        elif want.dtype.kind == "f":
            if not np.allclose(have, want, rtol=RTOL, atol=ATOL, equal_nan=True):
                found[name] = f"up to {np.nanmax(np.abs(have - want)):.3g} off"
        elif not np.array_equal(have, want):
            found[name] = f"{int(np.sum(have != want))} entries differ"
    for name in (
        "timestep",
        "impratio",
        "cone",
        "solver",
        "iterations",
        "tolerance",
        "integrator",
        "noslip_iterations",
    ):
        if getattr(reference.opt, name) != getattr(exported.opt, name):
            found[f"opt.{name}"] = f"{getattr(exported.opt, name)}, LIBERO's {getattr(reference.opt, name)}"
    return found


def _number(values: Any) -> str:
    return " ".join(repr(float(v)) for v in np.ravel(values))


def write_model(model: Any, out: Path) -> None:
    """Write ``model`` as ``out/scene.xml`` plus ``out/assets``, with the runtime inertias."""
    import mujoco

    raw = out / "raw.xml"
    # mj_saveLastXML writes the XML this process compiled last: the caller builds the env just
    # before, and the field-by-field check after the export catches any other model.
    mujoco.mj_saveLastXML(str(raw), model)
    tree = ET.parse(raw)
    raw.unlink()
    root = tree.getroot()
    compiler = root.find("compiler")
    if compiler is not None:
        for attribute in ("meshdir", "texturedir", "assetdir"):
            compiler.attrib.pop(attribute, None)
    assets = out / "assets"
    assets.mkdir(exist_ok=True)
    for element in root.iter():
        source = element.get("file")
        if source is None:
            continue
        digest = hashlib.sha256(source.encode()).hexdigest()[:8]
        name = f"{digest}_{Path(source).name}"
        if not (assets / name).exists():
            shutil.copyfile(source, assets / name)
        element.set("file", f"assets/{name}")
    bodies = list(root.find("worldbody").iter("body"))
    if len(bodies) != model.nbody - 1:
        raise RuntimeError(f"MJCF holds {len(bodies)} bodies, the model {model.nbody - 1}")
    for body_id, body in enumerate(bodies, start=1):
        for old in body.findall("inertial"):
            body.remove(old)
        inertial = ET.Element(
            "inertial",
            pos=_number(model.body_ipos[body_id]),
            quat=_number(model.body_iquat[body_id]),
            mass=_number(model.body_mass[body_id : body_id + 1]),
            diaginertia=_number(model.body_inertia[body_id]),
        )
        body.insert(0, inertial)
    # MJCF keeps a sphere site's radius alone; the model keeps all three sizes, which the
    # compiler would fill with its defaults.
    for site in root.iter("site"):
        name = site.get("name")
        if name is not None:
            site.set("size", _number(model.site_size[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, name)]))
    tree.write(out / "scene.xml")


def _watch_view(inner: Any) -> dict[str, np.ndarray]:
    """Copy :data:`VIEW_FIELDS` of ``inner``'s data into the returned dict whenever LIBERO's
    observables sample (an observable of their rate, as a CPU pod's cameras take their copy)."""
    from robosuite.utils.observables import Observable, sensor

    data = inner.sim.data._data
    seen: dict[str, np.ndarray] = {}

    @sensor(modality="vecsim")
    def view(obs_cache: dict[str, Any]) -> float:
        seen.update({name: np.array(getattr(data, name), copy=True) for name in VIEW_FIELDS})
        return 0.0

    inner.add_observable(Observable(name="vecsim_export_view", sensor=view, sampling_rate=inner.control_freq))
    return seen


def _settled_states(env: Any, num_states: int) -> dict[str, np.ndarray]:
    """Reset ``env`` (a vecsim LIBERO env, no cameras) to each init state; what each leaves, and
    (``view.*``) the kinematics its cameras would draw, taken at the observables' last sample."""
    inner = env.inner
    model, data = inner.sim.model._model, inner.sim.data._data
    robot = inner.robots[0]
    seen = _watch_view(inner)
    rows: dict[str, list[np.ndarray]] = {}
    for state_id in range(num_states):
        seen.clear()
        obs, info = env.reset(options={"state_id": state_id})
        if set(seen) != set(VIEW_FIELDS):
            raise RuntimeError(f"state {state_id}: LIBERO's observables did not sample during the reset")
        controller = robot.controller
        row = {
            "time": np.array(data.time),
            "qpos": data.qpos,
            "qvel": data.qvel,
            "act": data.act,
            "ctrl": data.ctrl,
            "qacc_warmstart": data.qacc_warmstart,
            "body_pos": model.body_pos,
            "body_quat": model.body_quat,
            "initial_joint": np.asarray(controller.initial_joint),
            "goal_pos": np.asarray(controller.goal_pos),
            "goal_ori": np.asarray(controller.goal_ori),
            "gripper_action": np.asarray(robot.gripper.current_action),
            "obs_state": obs["state"],
            "obs_proprio": obs["proprio"],
            "success": np.array(info["success"]),
            **{f"view.{name}": value for name, value in seen.items()},
        }
        for name, value in row.items():
            rows.setdefault(name, []).append(np.array(value, copy=True))
    return {name: np.stack(values) for name, values in rows.items()}


def _robot_manifest(inner: Any) -> dict[str, Any]:
    """What the engine needs of the robot, by name (ids may differ in another mujoco)."""
    import mujoco

    model = inner.sim.model._model
    robot = inner.robots[0]
    controller = robot.controller

    def name(kind: Any, index: int) -> str:
        return mujoco.mj_id2name(model, kind, int(index))

    return {
        "eef_site": controller.eef_name,
        "arm_joints": list(robot.robot_joints),
        "arm_actuators": [name(mujoco.mjtObj.mjOBJ_ACTUATOR, i) for i in robot._ref_joint_actuator_indexes],
        "gripper_joints": list(robot.gripper.joints),
        "gripper_actuators": [name(mujoco.mjtObj.mjOBJ_ACTUATOR, i) for i in robot._ref_joint_gripper_actuator_indexes],
        "torque_low": np.asarray(controller.actuator_min).tolist(),
        "torque_high": np.asarray(controller.actuator_max).tolist(),
        "control_freq": float(inner.control_freq),
        "substeps": round(inner.control_timestep / model.opt.timestep),
        "cameras": [name(mujoco.mjtObj.mjOBJ_CAMERA, i) for i in range(model.ncam)],
    }


def _tables(inner: Any) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """The batched modules' index tables of ``inner`` (prefixed ``panda.``, ``obs.``, ``goal.``)
    and the manifest's ``goal``: its atoms, or why it has no batched form."""
    from vecsim.engine.mjwarp.tables import ObservableIndex, PandaIndex, UnsupportedGoal, compile_goal

    tables: dict[str, np.ndarray] = {}
    for prefix, value in (("panda", PandaIndex.from_robosuite(inner)), ("obs", ObservableIndex.from_robosuite(inner))):
        tables.update({f"{prefix}.{k}": np.asarray(v) for k, v in dataclasses.asdict(value).items()})
    try:
        table = compile_goal(inner)
    except UnsupportedGoal as exc:
        return tables, {"atoms": None, "unsupported": str(exc)}
    fields = dataclasses.asdict(table)
    atoms = list(fields.pop("atoms"))
    tables.update({f"goal.{k}": np.asarray(v) for k, v in fields.items()})
    return tables, {"atoms": atoms, "unsupported": None}


def load_tables(scene: Scene) -> dict[str, dict[str, np.ndarray]]:
    """``tables.npz`` of ``scene`` as ``{"panda": {...}, "obs": {...}, "goal": {...}}``."""
    grouped: dict[str, dict[str, np.ndarray]] = {}
    with np.load(scene.path / "tables.npz") as npz:
        for key in npz.files:
            prefix, _, name = key.partition(".")
            grouped.setdefault(prefix, {})[name] = npz[key]
    return grouped


def export_scene(
    task_id: str, protocol: LiberoProtocol | None = None, root: Path | None = None, force: bool = False
) -> Path:
    """Export ``task_id``'s scene (the CPU stack: robosuite, LIBERO), unless it is cached.

    Returns:
        The scene's folder (:func:`scene_dir`).

    Raises:
        UnknownTaskError, TaskSetupError: as the CPU engine's task registry raises them.
        ValueError: not a LIBERO task, or the exported model differs from LIBERO's (the fields
            named).
    """
    import mujoco

    from vecsim.config import CameraConfig
    from vecsim.engine.tasks import LIBERO_SUITES, get_task, make_env

    protocol = protocol or LiberoProtocol()
    task = get_task(task_id)
    if task.suite not in LIBERO_SUITES:
        raise ValueError(f"tasks: {task_id!r} is not a LIBERO task; the mjwarp engine serves LIBERO tasks only")
    target = scene_dir(task.task_id, protocol, root)
    if (target / "manifest.json").is_file() and not force:
        return target
    target.parent.mkdir(parents=True, exist_ok=True)
    env = make_env(task.task_id, CameraConfig(names=()), libero=protocol)
    try:
        inner = env.inner
        with tempfile.TemporaryDirectory(dir=target.parent) as scratch:
            out = Path(scratch)
            states = _settled_states(env, task.num_states)
            # The model as it stands after the last reset; fixtures go per state, from states.npz.
            model = inner.sim.model._model
            write_model(model, out)
            exported = mujoco.MjModel.from_xml_path(str(out / "scene.xml"))
            exported.body_pos[:], exported.body_quat[:] = model.body_pos, model.body_quat
            differences = model_differences(model, exported)
            if differences:
                raise ValueError(f"{task.task_id}: the exported model differs from LIBERO's: {differences}")
            np.savez_compressed(out / "states.npz", **states)
            tables, goal = _tables(inner)
            np.savez_compressed(out / "tables.npz", **tables)
            import robosuite

            manifest = {
                "format": SCENE_FORMAT,
                "task_id": task.task_id,
                "instruction": task.instruction,
                "num_states": task.num_states,
                "max_episode_steps": task.max_episode_steps,
                "protocol": protocol.model_dump(),
                "exported_with": {"mujoco": mujoco.__version__, "robosuite": robosuite.__version__},
                "fixtures_vary": bool(
                    np.ptp(states["body_pos"], axis=0).max() > 0 or np.ptp(states["body_quat"], axis=0).max() > 0
                ),
                "sizes": {"nq": model.nq, "nv": model.nv, "nu": model.nu, "na": model.na, "nbody": model.nbody},
                "robot": _robot_manifest(inner),
                "goal": goal,
            }
            (out / "manifest.json").write_text(json.dumps(manifest, indent=1))
            if target.exists():
                shutil.rmtree(target)
            out.rename(target)
            # TemporaryDirectory's cleanup expects its folder: leave an empty one behind.
            out.mkdir()
    finally:
        env.close()
    log.info("exported %s to %s", task.task_id, target)
    return target


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m vecsim.engine.mjwarp.scene", description=__doc__.split("\n\n")[0])
    parser.add_argument("tasks", nargs="+", help="LIBERO task ids (libero_10/0 ...)")
    parser.add_argument(
        "--root", type=Path, default=None, help=f"cache folder (default ${ROOT_ENV} or ~/.cache/vecsim/mjwarp-scenes)"
    )
    parser.add_argument(
        "--libero",
        type=LiberoProtocol.model_validate_json,
        default=LiberoProtocol(),
        help="the job's libero block as JSON (default: LIBERO's published protocol), e.g. '{\"settle_steps\": 15}'",
    )
    parser.add_argument("--force", action="store_true", help="export again even when cached")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    for task_id in args.tasks:
        path = export_scene(task_id, args.libero, root=args.root, force=args.force)
        refused = refusal(load_scene(path).manifest)
        print(f"{task_id}\t{path}\t{'refused: ' + refused if refused else 'served'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
