"""The ``mjwarp`` engine's scene export against the model LIBERO steps (vecsim.engine.mjwarp.scene).

The reference is LIBERO's own env, built by the CPU engine: the exported MJCF, reloaded, must be
that model field by field (``mj_saveLastXML`` alone is not: it re-derives object masses), must
step as it does, and each recorded reset must be where a CPU reset to the same state id ends.
"""

from __future__ import annotations

import json

import mujoco
import numpy as np
import pytest

from vecsim.config import CameraConfig, LiberoProtocol
from vecsim.engine.mjwarp.scene import export_scene, load_scene, load_tables, model_differences
from vecsim.engine.tasks import get_task, make_env

pytestmark = [pytest.mark.libero, pytest.mark.slow]

TASK = "libero_10/0"
STATE = 3


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
