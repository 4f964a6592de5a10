"""The task registry, the task envs and the render presets, on real robosuite, LIBERO and gymnasium.

Real scenes render through software EGL here, so the envs are few, the cameras tiny and the
episodes short; one LIBERO task (libero_10/0) stands for LIBERO.
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import mujoco
import gymnasium
import numpy as np
import pytest
import yaml

from vecsim.engine import render
from vecsim.config import CameraConfig
from vecsim.engine.tasks import (
    PROPRIO_KEYS,
    TaskEnv,
    TaskSetupError,
    UnknownTaskError,
    default_render,
    derive_seed,
    episode_limit,
    get_task,
    list_suites,
    make_env,
    normalize_task_id,
    states_path,
    suite_tasks,
    task_spaces,
)
from vecsim.engine.tasks._libero import LIBERO_SUITES, STATE_DIM, check_assets, quat_to_axis_angle

TINY_CAMERA = CameraConfig(height=8, width=8)
ACTIONS = np.random.default_rng(7).uniform(-1.0, 1.0, (5, 7)).astype(np.float32)


def _flat(obs: dict) -> bytes:
    """Every byte of an observation, images in camera order, so equality means bit-identical."""
    images = obs.get("images", {})
    return obs["proprio"].tobytes() + b"".join(images[name].tobytes() for name in sorted(images))


def _episode(env: TaskEnv, state_id: int, actions: np.ndarray = ACTIONS) -> list[bytes]:
    obs, _ = env.reset(options={"state_id": state_id})
    frames = [_flat(obs)]
    for action in actions:
        frames.append(_flat(env.step(action)[0]))
    return frames


def _robosuite_render(env: TaskEnv, preset: str, camera: str) -> np.ndarray:
    """What robosuite's own renderer shows of ``env`` now, bottom row first as robosuite gives it."""
    from robosuite.utils.binding_utils import MjRenderContextOffscreen

    sim = env.inner.sim
    context = MjRenderContextOffscreen(sim, device_id=-1)
    context.vopt.geomgroup[0] = 0
    render.apply_to_robosuite(sim, preset)
    try:
        context.gl_ctx.make_current()
        return sim.render(camera_name=camera, width=env.camera.width, height=env.camera.height)
    finally:
        context.gl_ctx.make_current()
        context.con.free()
        context.gl_ctx.free()
        sim._render_context_offscreen = None


@pytest.fixture(scope="module")
def lift() -> Iterator[TaskEnv]:
    env = make_env("tiny/lift", TINY_CAMERA, "lean")
    try:
        yield env
    finally:
        env.close()


@pytest.fixture(scope="module")
def libero_env() -> Iterator[TaskEnv]:
    env = make_env("libero_10/0", TINY_CAMERA, "lean")
    try:
        yield env
    finally:
        env.close()


# The registry.


def test_gym_colon_ids_are_normalised_to_slash() -> None:
    assert normalize_task_id("gym:HalfCheetah-v5") == "gym/HalfCheetah-v5"
    assert normalize_task_id("libero_10/3") == "libero_10/3"
    assert get_task("gym:HalfCheetah-v5").task_id == "gym/HalfCheetah-v5"


@pytest.mark.parametrize("task_id", ["nope/1", "libero_10/10", "robosuite/Wipe", "gym/NoSuchEnv-v0", "tiny"])
def test_unknown_task_error_names_the_id_and_lists_the_suites(task_id: str) -> None:
    with pytest.raises(UnknownTaskError) as caught:
        get_task(task_id)
    assert isinstance(caught.value, KeyError)
    assert repr(task_id) in str(caught.value)
    assert all(suite in str(caught.value) for suite in list_suites())


def test_unknown_suite_raises_unknown_task_error() -> None:
    with pytest.raises(UnknownTaskError, match="'libero_100'"):
        suite_tasks("libero_100")


def test_libero_suites_hold_its_130_tasks_in_its_order_with_its_instructions() -> None:
    from libero.libero import benchmark

    sizes = {}
    for suite in ("libero_10", "libero_spatial", "libero_object", "libero_goal", "libero_90"):
        tasks = suite_tasks(suite)
        theirs = benchmark.get_benchmark_dict()[suite]()
        assert [t.task_id for t in tasks] == [f"{suite}/{i}" for i in range(theirs.n_tasks)]
        assert [t.instruction for t in tasks] == [theirs.get_task(i).language for i in range(theirs.n_tasks)]
        assert {t.num_states for t in tasks} == {50}
        sizes[suite] = len(tasks)
    assert sum(sizes.values()) == 130
    assert get_task("libero_10/0").scene == "LIVING_ROOM_SCENE2"


def test_robosuite_and_tiny_suites_list_their_tasks() -> None:
    robosuite_ids = {t.task_id for t in suite_tasks("robosuite")}
    assert {"robosuite/Lift", "robosuite/Stack", "robosuite/Door", "robosuite/PickPlace"} <= robosuite_ids
    assert {"robosuite/PickPlaceCan", "robosuite/NutAssembly", "robosuite/NutAssemblySquare"} <= robosuite_ids
    assert [t.task_id for t in suite_tasks("tiny")] == ["tiny/lift", "tiny/stack", "tiny/door"]
    assert all(t.instruction for t in suite_tasks("robosuite") + suite_tasks("tiny"))


@pytest.mark.parametrize("suite", list_suites())
def test_every_task_of_a_suite_has_the_same_spaces(suite: str) -> None:
    spaces = {task.task_id: task_spaces(task.task_id, TINY_CAMERA) for task in suite_tasks(suite)}
    first = next(iter(spaces.values()))
    assert all(pair == first for pair in spaces.values())
    observation_space, action_space = first
    assert observation_space["proprio"].shape == (23,)
    assert observation_space["images"]["agentview"].shape == (8, 8, 3)
    assert action_space.shape == (7,) and action_space.dtype == np.float32


def test_libero_tasks_add_the_8_float_state_and_the_others_do_not() -> None:
    for suite in list_suites():
        observation_space, _ = task_spaces(suite_tasks(suite)[0].task_id, TINY_CAMERA)
        if suite in LIBERO_SUITES:
            assert observation_space["state"].shape == (STATE_DIM,)
        else:
            assert "state" not in observation_space.spaces


def test_a_pod_gives_each_libero_suite_its_own_episode_limit_unless_one_is_set() -> None:
    published = {"libero_spatial": 220, "libero_object": 280, "libero_goal": 300, "libero_10": 520, "libero_90": 400}
    for suite, limit in published.items():
        assert episode_limit(f"{suite}/0", None) == limit
        assert episode_limit(f"{suite}/0", 77) == 77
    assert episode_limit("tiny/lift", None) == 300
    assert episode_limit("robosuite/Lift", None) == 300


def test_libero_tasks_draw_with_full_and_the_others_with_lean_by_default() -> None:
    assert [default_render(task) for task in ("libero_goal/3", "libero_90/0")] == ["full", "full"]
    assert [default_render(task) for task in ("tiny/lift", "robosuite/Door", "gym/Pendulum-v1")] == ["lean"] * 3


def test_the_state_axis_angle_is_robosuites_with_the_quaternions_sign_kept() -> None:
    from robosuite.utils.transform_utils import quat2axisangle

    quats = np.random.default_rng(3).normal(size=(200, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    assert (quats[:, 3] < 0).any() and (quats[:, 3] > 0).any()
    for quat in quats:
        assert np.array_equal(quat_to_axis_angle(quat), quat2axisangle(quat.copy()))
    # -q is the same rotation; folding it onto w >= 0 would give another vector (the trap).
    quat = np.array([0.9, 0.1, 0.0, -0.42]) / np.linalg.norm([0.9, 0.1, 0.0, -0.42])
    assert np.linalg.norm(quat_to_axis_angle(quat)) > np.pi
    assert not np.allclose(quat_to_axis_angle(quat), quat_to_axis_angle(-quat))


def test_gym_task_takes_its_episode_length_from_gymnasium() -> None:
    task = get_task("gym/HalfCheetah-v5")
    assert (task.suite, task.max_episode_steps, task.num_states) == ("gym", 1000, 50)


def test_derived_seeds_do_not_depend_on_the_process() -> None:
    code = "from vecsim.engine.tasks import derive_seed; print(derive_seed('tiny/lift', 3))"
    outputs = {
        subprocess.run(
            [sys.executable, "-c", code],
            env={**os.environ, "PYTHONHASHSEED": salt},
            capture_output=True,
            text=True,
            timeout=60,
            check=True,
        ).stdout.strip()
        for salt in ("1", "2")
    }
    assert outputs == {str(derive_seed("tiny/lift", 3))}


# Robot task envs (robosuite).


def test_robot_observation_is_upright_images_and_23_proprio_floats(lift: TaskEnv) -> None:
    obs, info = lift.reset(options={"state_id": 0})
    assert lift.observation_space.contains(obs)
    assert set(obs["images"]) == {"agentview", "robot0_eye_in_hand"}
    assert info == {"success": False, "task_id": "tiny/lift", "state_id": 0}
    raw = lift.inner._get_observations()
    assert np.array_equal(obs["images"]["agentview"], _robosuite_render(lift, "lean", "agentview")[::-1])
    assert np.array_equal(obs["proprio"], np.concatenate([raw[k] for k in PROPRIO_KEYS]).astype(np.float32))


def test_reset_to_a_state_is_bit_identical_whatever_came_before(lift: TaskEnv) -> None:
    fresh = _episode(lift, 3)
    _episode(lift, 5, ACTIONS[::-1])
    assert _episode(lift, 3) == fresh


def test_different_state_ids_are_different_scenes(lift: TaskEnv) -> None:
    assert _episode(lift, 1, ACTIONS[:0]) != _episode(lift, 2, ACTIONS[:0])


def test_reset_sets_the_generated_state_cached_on_disk(lift: TaskEnv) -> None:
    lift.reset(options={"state_id": 4})
    cached = np.load(states_path(get_task("tiny/lift")))
    assert cached.shape == (50, lift.inner.sim.get_state().flatten().size)
    assert np.array_equal(lift.inner.sim.get_state().flatten(), cached[4])


def test_generated_states_are_written_once_and_then_read(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("VECSIM_CACHE_DIR", str(tmp_path))
    path = states_path(get_task("tiny/door"))
    first = make_env("tiny/door", CameraConfig(names=()))
    try:
        written = np.load(path)
        stamp = path.stat().st_mtime_ns
        obs_first, _ = first.reset(options={"state_id": 9})
    finally:
        first.close()
    second = make_env("tiny/door", CameraConfig(names=()))
    try:
        obs_second, _ = second.reset(options={"state_id": 9})
    finally:
        second.close()
    assert path.stat().st_mtime_ns == stamp
    assert written.shape[0] == 50 and written.dtype == np.float64
    assert not list(path.parent.glob(".*.tmp"))
    assert _flat(obs_first) == _flat(obs_second)


def test_reset_without_a_state_id_draws_one_from_the_seeded_generator(lift: TaskEnv) -> None:
    drawn = [lift.reset(seed=11)[1]["state_id"] for _ in range(2)]
    assert drawn[0] == drawn[1] and 0 <= drawn[0] < 50


@pytest.mark.parametrize("state_id", [-1, 50, 2.0, True])
def test_reset_rejects_a_state_id_out_of_range(lift: TaskEnv, state_id: object) -> None:
    with pytest.raises(ValueError, match="tiny/lift: state_id"):
        lift.reset(options={"state_id": state_id})


def test_truncation_comes_after_max_episode_steps_since_the_last_reset() -> None:
    env = make_env("tiny/stack", CameraConfig(names=()), max_episode_steps=2)
    try:
        env.reset(options={"state_id": 0})
        flags = [env.step(ACTIONS[i])[3] for i in range(3)]
        env.reset(options={"state_id": 0})
        after_reset = env.step(ACTIONS[0])[3]
    finally:
        env.close()
    assert flags == [False, True, True]
    assert after_reset is False


def test_every_tiny_task_resets_and_steps_within_its_spaces() -> None:
    for task in suite_tasks("tiny"):
        env = make_env(task.task_id, TINY_CAMERA)
        try:
            obs, info = env.reset(options={"state_id": 1})
            assert env.observation_space.contains(obs)
            step = env.step(ACTIONS[0])
            assert env.observation_space.contains(step[0])
            assert isinstance(step[1], float) and step[4] == {"success": False, "task_id": task.task_id}
            assert (env.max_episode_steps, info["task_id"]) == (50, task.task_id)
        finally:
            env.close()


@pytest.mark.slow
def test_every_robosuite_task_resets_exactly_to_its_states_within_its_spaces() -> None:
    for task in suite_tasks("robosuite"):
        env = make_env(task.task_id, CameraConfig(names=()))
        try:
            obs, _ = env.reset(options={"state_id": 49})
            assert env.observation_space.contains(obs)
            assert np.array_equal(env.inner.sim.get_state().flatten(), env.states[49])
            assert env.observation_space.contains(env.step(ACTIONS[0])[0])
        finally:
            env.close()


def test_a_camera_the_scene_lacks_is_an_error_naming_the_task_and_camera() -> None:
    with pytest.raises(ValueError, match=r"tiny/lift.*no_such_camera"):
        make_env("tiny/lift", CameraConfig(names=("no_such_camera",), height=8, width=8))


# gymnasium tasks.


def test_gym_task_gives_its_own_observation_as_proprio_and_a_render_image() -> None:
    env = make_env("gym/HalfCheetah-v5", CameraConfig(height=16, width=24))
    try:
        obs, info = env.reset(options={"state_id": 2})
        assert obs["proprio"].dtype == np.float32 and obs["proprio"].shape == (17,)
        assert obs["images"]["render"].shape == (16, 24, 3) and obs["images"]["render"].any()
        assert env.observation_space.contains(obs)
        assert info["task_id"] == "gym/HalfCheetah-v5"
        assert _episode(env, 2, ACTIONS[:, :6]) == _episode(env, 2, ACTIONS[:, :6])
        assert _episode(env, 2, ACTIONS[:0, :6]) != _episode(env, 3, ACTIONS[:0, :6])
    finally:
        env.close()


def test_gym_task_without_cameras_is_the_env_itself() -> None:
    env = make_env("gym/HalfCheetah-v5", CameraConfig(names=()))
    local = gymnasium.make("HalfCheetah-v5")
    try:
        assert env.observation_space == local.observation_space and env.action_space == local.action_space
        obs, info = env.reset(seed=7)
        expected, expected_info = local.reset(seed=7)
        assert np.array_equal(obs, expected) and obs.dtype == np.float64
        assert info == expected_info  # the env's own, nothing added
        fixed, info = env.reset(options={"state_id": 0})
        assert np.array_equal(fixed, env.reset(options={"state_id": 0})[0]) and set(info) == set(expected_info)
    finally:
        env.close()
        local.close()


def test_gym_task_with_a_discrete_action_space_is_served_without_cameras() -> None:
    assert task_spaces("gym/CartPole-v1", CameraConfig(names=()))[1] == gymnasium.spaces.Discrete(2)


def test_gym_task_with_cameras_needs_box_spaces() -> None:
    with pytest.raises(ValueError, match="gym/CartPole-v1: its observation space|gym/CartPole-v1: its action space"):
        task_spaces("gym/CartPole-v1", CameraConfig(names=("render",), height=8, width=8))


# Render presets.


def test_unknown_render_preset_is_a_value_error() -> None:
    with pytest.raises(ValueError, match="'fancy'"):
        render.settings("fancy")


def test_presets_set_the_shadow_map_and_scene_flags_on_a_robosuite_env(lift: TaskEnv) -> None:
    lift.render_images()
    context, scene = lift.renderer.context_of(lift.inner.sim.model._model)
    assert lift.renderer.preset == "lean"
    assert context.shadowSize == 0
    flags = scene.flags
    assert (flags[mujoco.mjtRndFlag.mjRND_SHADOW], flags[mujoco.mjtRndFlag.mjRND_REFLECTION]) == (0, 0)
    assert flags[mujoco.mjtRndFlag.mjRND_SKYBOX] == 0


def test_each_preset_renders_deterministically_and_presets_differ() -> None:
    camera = CameraConfig(names=("agentview",), height=32, width=32)
    images = {}
    for preset in ("full", "fast", "lean"):
        env = make_env("tiny/lift", camera, preset)
        try:
            first = env.reset(options={"state_id": 0})[0]["images"]["agentview"]
            again = env.reset(options={"state_id": 0})[0]["images"]["agentview"]
            assert np.array_equal(first, again)
            images[preset] = first
            expected_size = {"full": 4096, "fast": 1024, "lean": 0}[preset]
            assert env.renderer.context_of(env.inner.sim.model._model)[0].shadowSize == expected_size
        finally:
            env.close()
    assert not np.array_equal(images["full"], images["lean"])


# LIBERO.


@pytest.mark.libero
def test_libero_task_resets_to_the_init_state_libero_defines(libero_env: TaskEnv) -> None:
    from libero.libero import benchmark

    theirs = benchmark.get_benchmark_dict()["libero_10"]().get_task_init_states(0)
    # Settle steps move the objects on; without them a reset leaves LIBERO's init state.
    settling = libero_env.protocol
    libero_env.protocol = settling.model_copy(update={"settle_steps": 0})
    try:
        for state_id in (0, 7):
            obs, info = libero_env.reset(options={"state_id": state_id})
            assert np.array_equal(libero_env.inner.sim.get_state().flatten(), theirs[state_id])
            assert libero_env.observation_space.contains(obs)
            assert info["task_id"] == "libero_10/0"
    finally:
        libero_env.protocol = settling
    assert libero_env.task.instruction == "put both the alphabet soup and the tomato sauce in the basket"


@pytest.mark.libero
def test_libero_reset_is_bit_identical_whatever_came_before(libero_env: TaskEnv) -> None:
    fresh = _episode(libero_env, 7, ACTIONS[:3])
    _episode(libero_env, 5, ACTIONS[3:])
    assert _episode(libero_env, 7, ACTIONS[:3]) == fresh


def test_libero_config_is_written_without_asking_anything(tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if k != "LIBERO_CONFIG_PATH"}
    env["VECSIM_CACHE_DIR"] = str(tmp_path)
    code = "from vecsim.engine.tasks import get_task; print(get_task('libero_goal/0').instruction)"
    done = subprocess.run(
        [sys.executable, "-c", code],
        env=env,
        stdin=subprocess.DEVNULL,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == get_task("libero_goal/0").instruction
    config = yaml.safe_load((tmp_path / "libero" / "config.yaml").read_text())
    assert set(config) == {"benchmark_root", "bddl_files", "init_states", "datasets", "assets"}
    assert Path(config["bddl_files"]).is_dir() and Path(config["assets"]).is_dir()


def test_missing_libero_assets_are_an_error_pointing_at_the_setup_script(tmp_path: Path) -> None:
    (tmp_path / "assets").symlink_to(tmp_path / "gone")
    with pytest.raises(TaskSetupError, match="scripts/setup.sh"):
        check_assets(tmp_path)
