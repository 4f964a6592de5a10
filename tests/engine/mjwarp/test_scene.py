"""The ``mjwarp`` engine's scene export against the model LIBERO steps (vecsim.engine.mjwarp.scene).

The reference is LIBERO's own env, built by the CPU engine: the exported MJCF, reloaded, must be
that model field by field (``mj_saveLastXML`` alone is not: it re-derives object masses), must
step as it does, and each recorded reset must be where a CPU reset to the same state id ends,
under LIBERO's published protocol and under RLinf's (15 settle steps, ``first_reset`` fixtures),
with the kinematics a CPU pod's cameras draw that reset from (LIBERO's last observable sample,
one physics substep before the settled end).
"""

from __future__ import annotations

import json
import sys
import tarfile

import mujoco
import numpy as np
import pytest
from PIL import Image
from support import ROOT

from vecsim.config import Assignment, CameraConfig, LiberoProtocol
from vecsim.engine.mjwarp.engine import check_scene
from vecsim.engine.mjwarp.scene import (
    ROOT_ENV,
    VIEW_FIELDS,
    export_scene,
    load_scene,
    load_tables,
    model_differences,
    scene_dir,
)
from vecsim.engine.tasks import get_task, make_env

pytestmark = [pytest.mark.libero, pytest.mark.slow]

TASK = "libero_10/0"
STATE = 3
# RLinf's env contract (docs/trainers.md): its 15 settle steps with the gripper opening, and its
# fixtures placed as a fresh env's first reset places them.
RLINF = LiberoProtocol(settle_steps=15, fixture_rule="first_reset")


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return load_scene(export_scene(TASK, LiberoProtocol(), root=tmp_path_factory.mktemp("scenes")))


@pytest.fixture(scope="module")
def libero():
    """LIBERO's env as a CPU pod runs it, reset to state ``STATE``."""
    env = make_env(TASK, CameraConfig(names=()))
    obs, info = env.reset(options={"state_id": STATE})
    yield env, obs, info
    env.close()


def exported_model(scene, state):
    model = mujoco.MjModel.from_xml_path(str(scene.xml))
    model.body_pos[:], model.body_quat[:] = scene.states["body_pos"][state], scene.states["body_quat"][state]
    return model


def test_the_exported_model_is_the_one_libero_steps_field_by_field(scene, libero):
    env, _, _ = libero
    assert model_differences(env.inner.sim.model._model, exported_model(scene, STATE)) == {}


def test_mj_save_last_xml_alone_gets_the_masses_wrong(libero, tmp_path):
    """The trap the export works around: the saved MJCF, reloaded, re-derives object masses.
    ``mj_saveLastXML`` writes the last XML this process compiled, so LIBERO's is compiled again
    first."""
    inner = libero[0].inner
    mujoco.MjModel.from_xml_string(inner.model.get_xml())
    mujoco.mj_saveLastXML(str(tmp_path / "raw.xml"), inner.sim.model._model)
    raw = mujoco.MjModel.from_xml_path(str(tmp_path / "raw.xml"))
    assert "body_mass" in model_differences(inner.sim.model._model, raw)


def test_a_recorded_reset_is_where_libero_s_reset_ends(scene, libero):
    env, obs, info = libero
    data = env.inner.sim.data._data
    states = scene.states
    for name in ("qpos", "qvel", "act", "ctrl", "qacc_warmstart"):
        np.testing.assert_array_equal(states[name][STATE], getattr(data, name), err_msg=name)
    np.testing.assert_array_equal(states["obs_state"][STATE], obs["state"])
    np.testing.assert_array_equal(states["obs_proprio"][STATE], obs["proprio"])
    assert bool(states["success"][STATE]) == bool(info["success"])
    controller = env.inner.robots[0].controller
    np.testing.assert_array_equal(states["initial_joint"][STATE], controller.initial_joint)


def test_the_exported_model_steps_as_libero_s_does(scene, libero):
    """One env action's 25 substeps under LIBERO's last torques, from the recorded reset, on both
    models in this mujoco: the trajectories agree to MJCF's printed precision."""
    env, _, _ = libero
    reference_model = env.inner.sim.model._model
    reference = mujoco.MjData(reference_model)
    model = exported_model(scene, STATE)
    exported = mujoco.MjData(model)
    for data in (reference, exported):
        for name in ("qpos", "qvel", "act", "ctrl", "qacc_warmstart"):
            getattr(data, name)[:] = scene.states[name][STATE]
        data.time = float(scene.states["time"][STATE])
    for _ in range(25):
        mujoco.mj_step(reference_model, reference)
        mujoco.mj_step(model, exported)
    assert np.abs(exported.qpos - reference.qpos).max() < 1e-6
    assert np.abs(exported.qvel - reference.qvel).max() < 1e-4


def test_the_manifest_names_what_the_engine_needs(scene):
    manifest = scene.manifest
    robot = manifest["robot"]
    assert manifest["task_id"] == TASK and manifest["num_states"] == 50 == len(scene.states["qpos"])
    assert manifest["instruction"] == get_task(TASK).instruction
    assert robot["substeps"] == 25 and {"agentview", "robot0_eye_in_hand"} <= set(robot["cameras"])
    model = mujoco.MjModel.from_xml_path(str(scene.xml))
    tables = load_tables(scene)
    assert mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_SITE, int(tables["panda"]["eef_site"])) == robot["eef_site"]
    assert manifest["goal"]["atoms"], manifest["goal"]
    json.dumps(manifest)


@pytest.fixture(scope="module")
def rlinf_scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("rlinf-scenes")
    return load_scene(export_scene(TASK, RLINF, root=root))


@pytest.fixture(scope="module")
def rlinf_libero():
    """A CPU pod's env under RLinf's protocol, with a camera (so it keeps the copy its cameras
    draw from), reset to ``STATE``."""
    env = make_env(TASK, CameraConfig(names=("agentview",), height=8, width=8), libero=RLINF)
    obs, info = env.reset(options={"state_id": STATE})
    yield env, obs, info
    env.close()


def test_a_recorded_reset_under_rlinf_s_protocol_is_where_its_reset_ends(rlinf_scene, rlinf_libero, scene):
    env, obs, info = rlinf_libero
    data = env.inner.sim.data._data
    states = rlinf_scene.states
    for name in ("qpos", "qvel", "act", "ctrl", "qacc_warmstart", "time"):
        np.testing.assert_array_equal(states[name][STATE], getattr(data, name), err_msg=name)
    np.testing.assert_array_equal(states["body_pos"][STATE], env.inner.sim.model._model.body_pos)
    np.testing.assert_array_equal(states["obs_state"][STATE], obs["state"])
    np.testing.assert_array_equal(states["obs_proprio"][STATE], obs["proprio"])
    assert bool(states["success"][STATE]) == bool(info["success"])
    np.testing.assert_array_equal(states["gripper_action"][STATE], env.inner.robots[0].gripper.current_action)
    assert rlinf_scene.manifest["protocol"] == RLINF.model_dump()
    # Five more settle steps than the published protocol's: the reset ends elsewhere.
    assert not np.array_equal(states["qpos"][STATE], scene.states["qpos"][STATE])


def test_the_reset_view_is_what_a_cpu_pod_s_cameras_draw(rlinf_scene, rlinf_libero):
    """The CPU pod draws a reset's images from its copy of the sim taken at LIBERO's last
    observable sample (substep 24 of the last settle step's 25); the export records the same
    kinematics, and they are not the settled end state's."""
    env, _, _ = rlinf_libero
    drawn, end = env._frame, env.inner.sim.data._data
    for name in VIEW_FIELDS:
        recorded = rlinf_scene.states[f"view.{name}"][STATE]
        np.testing.assert_array_equal(recorded, getattr(drawn, name), err_msg=name)
    moved = np.abs(rlinf_scene.states["view.geom_xpos"][STATE] - end.geom_xpos).max()
    assert moved > 0, "the recorded view is the end state's: the sample substep is not where the export looked"


def test_the_engine_takes_an_rlinf_job_s_scene(rlinf_scene, monkeypatch):
    monkeypatch.setenv(ROOT_ENV, str(rlinf_scene.path.parent))
    job = Assignment.model_validate(
        {
            "generation": 0,
            "job_id": "rlinf",
            "pod": "p",
            "stage_id": 0,
            "engine": "mjwarp",
            "tasks": [{"task_id": TASK, "env_start": 0, "num_envs": 4}],
            "camera": {"names": ["agentview", "robot0_eye_in_hand"], "height": 8, "width": 8},
            "libero": RLINF.model_dump(),
        }
    )
    assert check_scene(job, job.tasks[0]).path == rlinf_scene.path


def test_each_protocol_has_its_own_scene_and_the_image_orientation_none(tmp_path):
    published = scene_dir(TASK, LiberoProtocol(), tmp_path)
    assert scene_dir(TASK, RLINF, tmp_path) != published
    assert scene_dir(TASK, LiberoProtocol(fixture_seed=7), tmp_path) != published
    assert scene_dir(TASK, LiberoProtocol(image_orientation="upright"), tmp_path) == published


def test_camera_centres_of_mass_are_checked_only_where_a_camera_tracks_one(libero):
    """``cam_poscom0`` is compiled from the placement the model was built with (moved fixtures
    change it) and read only by cameras that track their subtree's centre of mass."""
    xml = libero[0].inner.model.get_xml()
    reference, other = (mujoco.MjModel.from_xml_string(xml) for _ in range(2))
    other.cam_poscom0[0] += 0.01
    assert model_differences(reference, other) == {}
    reference.cam_mode[0] = other.cam_mode[0] = mujoco.mjtCamLight.mjCAMLIGHT_TRACKCOM
    assert set(model_differences(reference, other)) == {"cam_poscom0"}


def test_packed_scenes_unpack_to_loadable_scenes_sharing_their_files(scene, rlinf_scene, tmp_path):
    """``scripts/pack_mjwarp_scenes.py --together``: both scenes in one archive, the files they
    share held once (hard links), textures reduced, each scene loadable where it is unpacked."""
    sys.path.insert(0, str(ROOT / "scripts"))
    try:
        from pack_mjwarp_scenes import Packer
    finally:
        sys.path.remove(str(ROOT / "scripts"))
    archive = Packer(max_texture=64).pack([scene.path, rlinf_scene.path], tmp_path / "both.tar.xz")
    with tarfile.open(archive) as tar:
        links = [m for m in tar.getmembers() if m.islnk()]
        assert links and all(m.name.startswith(rlinf_scene.path.name) for m in links)
        tar.extractall(tmp_path / "unpacked", filter="tar")
    for original in (scene, rlinf_scene):
        unpacked = load_scene(tmp_path / "unpacked" / original.path.name)
        np.testing.assert_array_equal(unpacked.states["qpos"], original.states["qpos"])
        textures = list((unpacked.path / "assets").glob("*.png"))
        assert textures and all(max(Image.open(path).size) <= 64 for path in textures)
        model = mujoco.MjModel.from_xml_path(str(unpacked.xml))
        np.testing.assert_array_equal(model.body_mass, mujoco.MjModel.from_xml_path(str(original.xml)).body_mass)
