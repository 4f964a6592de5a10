"""The batched render path gives exactly the pixels of rendering one env at a time.

References are robosuite's and gymnasium's own renderers (one GL context and one render context
per env, one readback per camera) with the same preset applied through :mod:`vecsim.engine.render`.
Software EGL (Mesa) here, so the scenes are the tiny suite and Pusher, the cameras small; one
LIBERO scene stands for LIBERO.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import subprocess
import sys
from collections.abc import Callable, Iterator

import gymnasium
import mujoco
import numpy as np
import pytest
from support import ROOT

from vecsim.engine import batch_render, render
from vecsim.engine.batch_render import BatchRenderer, same_render_assets, shared_renderer
from vecsim.config import Assignment, CameraConfig, LiberoProtocol, TaskBlock
from vecsim.engine import assignment_spaces
from vecsim.engine.protocol import Order
from vecsim.engine.worker import Worker, WorkerSpec
from vecsim.engine.tasks import RobotTaskEnv, derive_seed, make_env

PRESETS = ("full", "fast", "lean", "lowpoly")
CAMERAS = ("agentview", "robot0_eye_in_hand")
HEIGHT, WIDTH = 24, 32
CAMERA = CameraConfig(names=CAMERAS, height=HEIGHT, width=WIDTH)
ACTIONS = np.random.default_rng(3).uniform(-1.0, 1.0, (3, 7)).astype(np.float32)


@contextlib.contextmanager
def robosuite_renderer(env: RobotTaskEnv, preset: str) -> Iterator[Callable[[str], np.ndarray]]:
    """robosuite's own offscreen renderer on ``env``'s sim under ``preset``: camera -> upright image."""
    from robosuite.utils.binding_utils import MjRenderContextOffscreen

    sim = env.inner.sim
    # Making it runs mj_forward (robosuite does): positions move on from where the last physics
    # substep left them, so whatever is compared with it must be rendered after this.
    context = MjRenderContextOffscreen(sim, device_id=-1)
    # As robosuite's reset sets them: visual meshes shown, collision meshes hidden.
    context.vopt.geomgroup[0] = 0
    context.vopt.geomgroup[1] = 1
    render.apply_to_robosuite(sim, preset)

    def own(name: str) -> np.ndarray:
        # robosuite renders into whichever GL context is current; make it its own.
        context.gl_ctx.make_current()
        return sim.render(camera_name=name, width=env.camera.width, height=env.camera.height)[::-1]

    try:
        yield own
    finally:
        context.gl_ctx.make_current()
        context.con.free()
        context.gl_ctx.free()
        sim._render_context_offscreen = None


@pytest.fixture(scope="module")
def lifts() -> Iterator[list[RobotTaskEnv]]:
    """Three tiny/lift envs in three different states, each a few steps into its episode."""
    envs = [make_env("tiny/lift", CAMERA, "lean") for _ in range(3)]
    try:
        for index, env in enumerate(envs):
            env.reset(options={"state_id": index})
            for action in ACTIONS[: index + 1]:
                env.step(action)
        yield envs
    finally:
        for env in envs:
            env.close()


@contextlib.contextmanager
def attached(renderer: BatchRenderer, envs: list) -> Iterator[list[batch_render.CameraView]]:
    """Attach ``envs``' models to ``renderer`` for the block; yield all their views, env-major."""
    for env in envs:
        renderer.attach(env.camera_views[0].model, len(env.camera_views))
    try:
        yield [view for env in envs for view in env.camera_views]
    finally:
        for env in envs:
            renderer.detach(env.camera_views[0].model, len(env.camera_views))
        renderer.close()


@pytest.mark.parametrize("preset", PRESETS)
@pytest.mark.slow
def test_a_batch_of_robosuite_envs_equals_robosuites_own_renderer_bit_for_bit(
    lifts: list[RobotTaskEnv], preset: str
) -> None:
    with contextlib.ExitStack() as stack:
        owns = [stack.enter_context(robosuite_renderer(env, preset)) for env in lifts]
        expected = [own(name) for own in owns for name in CAMERAS]
        renderer = BatchRenderer(HEIGHT, WIDTH, preset)
        with attached(renderer, lifts) as views:
            batched = renderer.render(views)
            assert renderer.readbacks == 1
    for index, (ours, theirs) in enumerate(zip(batched, expected)):
        assert np.array_equal(ours, theirs), f"view {index} differs under {preset}"


def test_a_view_lays_its_image_out_as_its_orientation_says(lifts: list[RobotTaskEnv]) -> None:
    renderer = BatchRenderer(HEIGHT, WIDTH, "lean")
    with attached(renderer, lifts[:1]) as views:
        oriented = [dataclasses.replace(views[0], orientation=way) for way in ("upright", "rotate180", "raw")]
        upright, rotated, raw = renderer.render(oriented)
    # GL's frame (bottom row first) is ``raw``; upright is raw[::-1]; LIBERO's evaluations' is raw[::-1, ::-1].
    assert np.array_equal(raw, upright[::-1])
    assert np.array_equal(rotated, raw[::-1, ::-1])


def test_without_multisampling_a_batch_still_equals_robosuites_own_renderer(lifts: list[RobotTaskEnv]) -> None:
    models = [env.inner.sim.model._model for env in lifts]
    samples = [model.vis.quality.offsamples for model in models]
    try:
        for model in models:
            model.vis.quality.offsamples = 0
        with contextlib.ExitStack() as stack:
            owns = [stack.enter_context(robosuite_renderer(env, "full")) for env in lifts]
            expected = np.stack([own(name) for own in owns for name in CAMERAS])
            renderer = BatchRenderer(HEIGHT, WIDTH, "full")
            with attached(renderer, lifts) as views:
                batched = renderer.render(views)
                assert renderer.context_of(models[0])[0].offSamples == 0
    finally:
        for model, count in zip(models, samples):
            model.vis.quality.offsamples = count
    assert np.array_equal(batched, expected)


@pytest.mark.parametrize("preset", PRESETS)
def test_a_batch_equals_rendering_each_view_alone(lifts: list[RobotTaskEnv], preset: str) -> None:
    renderer = BatchRenderer(HEIGHT, WIDTH, preset)
    with attached(renderer, lifts) as views:
        batched = renderer.render(views)
        alone = np.concatenate([renderer.render([view]) for view in views])
    assert np.array_equal(batched, alone)


def _pictures(envs: list, presets: tuple[str, ...] = PRESETS) -> dict[str, np.ndarray]:
    pictures = {}
    for preset in presets:
        renderer = BatchRenderer(HEIGHT, WIDTH, preset)
        with attached(renderer, envs) as views:
            pictures[preset] = renderer.render(views)
    return pictures


def test_reflections_show_under_full_only(lifts: list[RobotTaskEnv]) -> None:
    # robosuite's table reflects; its light casts no shadow, so only reflections tell presets apart.
    pictures = _pictures(lifts[:1])
    assert not np.array_equal(pictures["full"], pictures["fast"])


def test_shadows_show_under_full_and_fast_but_not_lean() -> None:
    env = make_env("gym/Pusher-v5", CameraConfig(names=("render",), height=HEIGHT, width=WIDTH), "lean")
    try:
        env.reset(options={"state_id": 0})
        pictures = _pictures([env])
    finally:
        env.close()
    assert not np.array_equal(pictures["fast"], pictures["lean"])
    assert not np.array_equal(pictures["full"], pictures["lean"])


def test_a_batch_bigger_than_the_buffer_takes_several_passes_with_the_same_pixels(
    lifts: list[RobotTaskEnv], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(batch_render, "MAX_BUFFER_SIDE", 2 * WIDTH)
    renderer = BatchRenderer(HEIGHT, WIDTH, "lean")
    with attached(renderer, lifts) as views:
        batched = renderer.render(views)
        assert renderer.readbacks == 2
        alone = np.concatenate([renderer.render([view]) for view in views])
    assert np.array_equal(batched, alone)


@pytest.mark.parametrize("preset", PRESETS)
def test_gym_envs_rendered_in_a_batch_equal_gymnasiums_own_render(preset: str) -> None:
    camera = CameraConfig(names=("render",), height=HEIGHT, width=WIDTH)
    ours = [make_env("gym/Pusher-v5", camera, preset) for _ in range(2)]
    theirs, viewers = [], []
    try:
        for state_id in range(2):
            reference = gymnasium.make("Pusher-v5", render_mode="rgb_array", width=WIDTH, height=HEIGHT)
            viewers.append(render.apply_to_gymnasium(reference, preset))
            reference.reset(seed=derive_seed("gym/Pusher-v5", state_id))
            theirs.append(reference)
        for state_id, env in enumerate(ours):
            env.defer_images = True
            env.reset(options={"state_id": state_id})
        for env, reference in zip(ours, theirs):
            action = np.full(env.action_space.shape, 0.5, dtype=np.float32)
            env.step(action)
            reference.step(action)
        renderer = ours[0].renderer
        batched = renderer.render([env.camera_views[0] for env in ours])
        for image, reference, viewer in zip(batched, theirs, viewers):
            # gymnasium renders into whichever GL context is current; make it its own.
            viewer.make_context_current()
            assert np.array_equal(image, reference.render())
    finally:
        for env in [*ours, *theirs]:
            env.close()


def test_a_step_renders_each_camera_once_showing_the_state_after_the_step(lifts: list[RobotTaskEnv]) -> None:
    env = lifts[0]
    renderer = env.renderer
    before = renderer.views_rendered
    obs, *_ = env.step(ACTIONS[0])
    assert renderer.views_rendered - before == len(CAMERAS)
    again = env.render_images()
    for name in CAMERAS:
        assert np.array_equal(obs["images"][name], again[name])


def test_a_worker_renders_only_the_envs_it_reset_or_stepped_in_one_readback() -> None:
    assignment = Assignment(
        generation=1,
        pod="sim-0",
        stage_id=0,
        tasks=(TaskBlock(task_id="tiny/lift", env_start=0, num_envs=3),),
        camera=CAMERA,
        envs_per_worker=3,
    )
    observation_space, action_space = assignment_spaces(assignment)
    spec = WorkerSpec(("tiny/lift",) * 3, (0, 1, 2), 3, CAMERA, "lean", 10, observation_space, action_space)
    worker = Worker(spec)
    try:
        worker.build()
        renderer = shared_renderer(HEIGHT, WIDTH, "lean")
        out = worker._out
        idle = out["obs"]["images"]["agentview"][1].copy()
        views, readbacks = renderer.views_rendered, renderer.readbacks
        chunk = np.array([[action_space.sample()]])  # a chunk of one action for env 0
        worker.run(Order(np.array([0]), actions=chunk), Order(np.array([2]), state_ids=np.array([4])))
        assert renderer.views_rendered - views == 2 * len(CAMERAS)
        assert renderer.readbacks - readbacks == 1
        assert np.array_equal(out["obs"]["images"]["agentview"][1], idle)
        own = worker._envs[2].render_images()
        assert np.array_equal(out["obs"]["images"]["agentview"][2], own["agentview"])
    finally:
        worker.close()


def test_envs_of_one_task_share_a_render_context_and_other_tasks_get_their_own(
    lifts: list[RobotTaskEnv],
) -> None:
    stack = make_env("tiny/stack", CAMERA, "lean")
    try:
        models = [env.inner.sim.model._model for env in (*lifts[:2], stack)]
        assert same_render_assets(models[0], models[1]) and not same_render_assets(models[0], models[2])
        stack.render_images()
        lifts[0].render_images()
        renderer = stack.renderer
        assert renderer.context_of(models[0])[0] is renderer.context_of(models[1])[0]
        assert renderer.context_of(models[0])[0] is not renderer.context_of(models[2])[0]
    finally:
        stack.close()


def test_closing_the_last_env_of_a_scene_frees_its_render_context() -> None:
    camera = CameraConfig(names=("agentview",), height=HEIGHT, width=WIDTH)
    env = make_env("tiny/door", camera, "fast")
    model = env.inner.sim.model._model
    env.render_images()
    renderer = env.renderer
    assert renderer.context_of(model)[0] is not None
    env.close()
    with pytest.raises(KeyError):
        renderer.context_of(model)


def test_an_empty_batch_renders_nothing(lifts: list[RobotTaskEnv]) -> None:
    renderer = lifts[0].renderer
    readbacks = renderer.readbacks
    assert renderer.render([]).shape == (0, HEIGHT, WIDTH, 3)
    assert renderer.readbacks == readbacks


def test_an_output_array_of_the_wrong_shape_is_refused(lifts: list[RobotTaskEnv]) -> None:
    with pytest.raises(ValueError, match="out: expected uint8"):
        lifts[0].renderer.render(lifts[0].camera_views, out=np.zeros((1, HEIGHT, WIDTH, 3), np.uint8))


def test_a_view_of_a_model_never_attached_is_refused(lifts: list[RobotTaskEnv]) -> None:
    renderer = BatchRenderer(HEIGHT, WIDTH, "lean")
    with pytest.raises(KeyError, match="not attached"):
        renderer.render(lifts[0].camera_views)


def test_an_unknown_preset_is_refused_naming_it() -> None:
    with pytest.raises(ValueError, match="'shiny'"):
        BatchRenderer(HEIGHT, WIDTH, "shiny")


def test_the_gl_context_names_its_renderer() -> None:
    info = batch_render.gl_info()
    assert info["backend"] in ("egl", "osmesa", "glfw") and info["renderer"]


def test_an_unknown_render_priority_is_refused_naming_the_variable(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(batch_render.RENDER_PRIORITY_ENV, "urgent")
    with pytest.raises(ValueError, match="VECSIM_RENDER_PRIORITY='urgent'"):
        batch_render.render_priority()
    monkeypatch.setenv(batch_render.RENDER_PRIORITY_ENV, " Low ")
    assert batch_render.render_priority() == "low"
    monkeypatch.delenv(batch_render.RENDER_PRIORITY_ENV)
    assert batch_render.render_priority() == "medium"


# A fresh process: the GL context is made once a process, at the priority asked for then.
PRIORITY_PROBE = """
import logging, sys
logging.basicConfig(level=logging.WARNING, stream=sys.stdout, format="%(message)s")
from mujoco import egl
from mujoco.egl import egl_ext as EGL
from vecsim.engine import batch_render
info = batch_render.gl_info()
offered = b"EGL_IMG_context_priority" in (EGL.eglQueryString(egl.EGL_DISPLAY, EGL.EGL_EXTENSIONS) or b"").split()
print("RESULT", info.get("priority"), offered)
"""


@pytest.mark.skipif(os.environ.get("MUJOCO_GL", "egl").lower() != "egl", reason="render priorities are EGL's")
def test_a_low_render_priority_is_granted_or_reported_as_medium_with_a_warning() -> None:
    env = {
        **os.environ,
        "MUJOCO_GL": "egl",
        batch_render.RENDER_PRIORITY_ENV: "low",
        "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
    }
    done = subprocess.run([sys.executable, "-c", PRIORITY_PROBE], env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    granted, offered = done.stdout.split("RESULT ", 1)[1].split()
    if offered == "True":  # NVIDIA's EGL: the level asked for (a driver may grant another, and says so)
        assert granted == "low" or "granted" in done.stdout, done.stdout
    else:  # Mesa's llvmpipe offers no priorities: the default, and a warning naming the level asked for
        assert granted == "medium" and "no EGL_IMG_context_priority" in done.stdout and "not low" in done.stdout


@pytest.mark.libero
def test_a_libero_scene_in_a_batch_equals_robosuites_own_renderer() -> None:
    camera = CameraConfig(names=CAMERAS, height=16, width=16)
    # Right after a reset with no settle steps the views' copy of the sim is the sim itself.
    protocol = LiberoProtocol(image_orientation="upright", settle_steps=0)
    env = make_env("libero_10/0", camera, "full", libero=protocol)
    try:
        assert env.renderer.preset == "full"
        env.reset(options={"state_id": 3})
        with robosuite_renderer(env, "full") as own:
            batched = env.renderer.render(env.camera_views)
            for image, name in zip(batched, CAMERAS):
                assert np.array_equal(image, own(name)), name
    finally:
        env.close()


def test_scene_flags_follow_the_preset(lifts: list[RobotTaskEnv]) -> None:
    for preset in PRESETS:
        renderer = BatchRenderer(HEIGHT, WIDTH, preset)
        with attached(renderer, lifts[:1]) as views:
            renderer.render(views)
            context, scene = renderer.context_of(views[0].model)
            chosen = render.settings(preset)
            assert scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] == chosen.shadows
            assert scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] == chosen.reflections
            assert scene.flags[mujoco.mjtRndFlag.mjRND_SKYBOX] == chosen.skybox
            expected = {"full": views[0].model.vis.quality.shadowsize, "fast": 1024, "lean": 0, "lowpoly": 0}[preset]
            assert context.shadowSize == expected
