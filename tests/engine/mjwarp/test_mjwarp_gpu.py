"""The ``mjwarp`` engine's GPU-only path: CUDA graphs, worlds put back, failed worlds, the renderer.

On a GPU every action of a batch runs as one captured CUDA graph that steps *every* world; the
engine puts back the worlds that were not named (or ended, or failed) from a snapshot, and its
ray tracer draws every world while only the named envs' images are taken. None of that runs on
warp's CPU device (``test_mjwarp_pod.py``, which CI runs), so this module runs on the GPU
machine only and is skipped elsewhere: it needs MuJoCo Warp, a CUDA device and libero_10/0's
exported scene under ``$VECSIM_MJWARP_SCENES``. Run there, in the ``mjwarp`` extra's
environment, with ``python -m pytest --noconftest tests/engine/mjwarp/test_mjwarp_gpu.py``;
docs/mjwarp.md cites the record.

- A world that runs out of constraint rows (``njmax`` 104: init state 5 needs 111 rows at rest,
  state 0 99) is that env's ``SimStateError`` alone; the other env of the call goes on as it
  does beside a world that does not fail; the failed env stays failed until a reset brings it
  back.
- Worlds left out of a call keep their whole state (physics, controller, the cameras' poses) and
  their images bit for bit, though the graph stepped them.
- Empty calls change nothing.
- Recorded envs (``record_env_indices``) get a frame after each action they applied, the last one
  the chunk's observation, zeros after they stopped.
- Rays reordered into tiles (``frames.order_rays``) and meshes given other trees
  (``frames.build_mesh_trees``) draw the images the engine served, bit for bit.

The GPU does not give bit-identical outputs run to run (docs/mjwarp.md, Determinism), so a
world's trajectory is compared with another run's within :data:`ATOL`, and "changes nothing" is
checked on the engine's own state arrays, which a put-back restores exactly.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

mjw = pytest.importorskip("mujoco_warp")
wp = pytest.importorskip("warp")

from vecsim.config import Assignment, CameraConfig, LiberoProtocol, TaskBlock  # noqa: E402
from vecsim.engine.base import engine_kind  # noqa: E402
from vecsim.engine.mjwarp.scene import scene_dir  # noqa: E402

TASK = "libero_10/0"
if not wp.is_cuda_available():
    pytest.skip("the mjwarp engine's GPU path needs a CUDA device", allow_module_level=True)
if not scene_dir(TASK, LiberoProtocol()).is_dir():
    pytest.skip(f"no exported scene of {TASK} (python -m vecsim.engine.mjwarp.scene)", allow_module_level=True)

STATES = [0, 5, 45]
CHUNK = 4
CAMERAS = ("agentview", "robot0_eye_in_hand")
# 0.1 mm / 0.1 mrad: two GPU runs part by micrometres over a few actions (docs/mjwarp.md).
ATOL = 1e-4


def _actions(n: int) -> np.ndarray:
    rng = np.random.default_rng(40)
    steps = rng.uniform(-0.3, 0.3, size=(n, CHUNK, 7))
    actions = np.clip(np.cumsum(steps, axis=1), -1.0, 1.0).astype(np.float32)
    actions[:, :, 6] = -1.0
    return actions


def _engine(num_envs: int, **fields: Any) -> Any:
    return engine_kind("mjwarp").build(
        Assignment(
            generation=0,
            pod="sim-0",
            stage_id=0,
            engine="mjwarp",
            camera=CameraConfig(names=CAMERAS, height=128, width=128),
            tasks=(TaskBlock(task_id=TASK, env_start=0, num_envs=num_envs),),
            **fields,
        )
    )


def _state(engine: Any) -> dict[str, np.ndarray]:
    """Every per-world array of the engine's one batch, and the observations it holds."""
    (batch,) = engine._batches
    out = {key: array.numpy().copy() for key, array in engine._state_arrays(batch).items()}
    out.update({f"obs.{k}": v.copy() for k, v in engine._obs.items() if k != "images"})
    out.update({f"image.{k}": v.copy() for k, v in engine._obs["images"].items()})
    return out


@pytest.fixture(scope="module")
def engine() -> Iterator[Any]:
    built = _engine(len(STATES))
    try:
        yield built
    finally:
        built.close()


def test_worlds_left_out_of_a_call_keep_their_state_and_images_bit_for_bit(engine):
    ids = np.arange(len(STATES))
    engine.reset_envs(ids, np.array(STATES))
    before = _state(engine)
    result = engine.chunk_step_envs([0, 2], _actions(2))
    assert not result.errors and result.num_steps.tolist() == [CHUNK, CHUNK]
    after = _state(engine)
    for key, values in before.items():
        np.testing.assert_array_equal(after[key][1], values[1], err_msg=key)
        if key.startswith(("qpos", "obs.state")):
            assert not np.array_equal(after[key][[0, 2]], values[[0, 2]]), f"{key}: the named worlds did not move"


def test_empty_calls_change_nothing(engine):
    engine.reset_envs(np.arange(len(STATES)), np.array(STATES))
    before = _state(engine)
    result = engine.chunk_step_envs([], np.zeros((0, CHUNK, 7), np.float32))
    assert result.num_steps.shape == (0,) and result.reward.shape == (0, CHUNK)
    engine.reset_envs([], [])
    after = _state(engine)
    for key, values in before.items():
        np.testing.assert_array_equal(after[key], values, err_msg=key)


def test_a_world_out_of_constraint_rows_fails_alone(engine, monkeypatch):
    engine.reset_envs([0, 1], [0, 5])
    reference = engine.chunk_step_envs([0, 1], _actions(2))
    assert not reference.errors
    monkeypatch.setenv("VECSIM_MJWARP_NJMAX", "104")  # read by the next build
    tight = _engine(2)
    try:
        tight.reset_envs([0, 1], [0, 5])
        chunk = tight.chunk_step_envs([0, 1], _actions(2))
        assert [(e.row, e.type_name) for e in chunk.errors] == [(1, "SimStateError")], chunk.errors
        assert "njmax" in chunk.errors[0].message
        assert chunk.num_steps.tolist() == [CHUNK, 0]
        np.testing.assert_allclose(chunk.obs["state"][0], reference.obs["state"][0], atol=ATOL)
        np.testing.assert_allclose(chunk.obs["proprio"][0], reference.obs["proprio"][0], atol=ATOL)
        assert np.isfinite(chunk.obs["state"]).all()
        again = tight.chunk_step_envs([1], _actions(2)[1:])
        assert [e.row for e in again.errors] == [0] and "reset it" in again.errors[0].message
        tight.reset_envs([1], [0])
        stepped = tight.chunk_step_envs([1], _actions(2)[:1])
        assert not stepped.errors
        np.testing.assert_allclose(stepped.obs["state"][0], reference.obs["state"][0], atol=ATOL)
    finally:
        tight.close()


def test_recorded_envs_get_a_frame_after_each_applied_action(engine):
    ids = np.arange(len(STATES))
    engine.reset_envs(ids, np.array(STATES))
    actions = _actions(len(STATES))
    result = engine.chunk_step_envs(ids, actions, record_env_indices=[2, 0])
    assert set(result.frames) == set(CAMERAS)
    for name in CAMERAS:
        frames = result.frames[name]
        assert frames.shape == (2, CHUNK, 128, 128, 3)
        # The last frame is the observation after the chunk (the same poses drawn again); the
        # arm moves, so each action's frame is its own.
        np.testing.assert_array_equal(frames[0, -1], result.obs["images"][name][2])
        np.testing.assert_array_equal(frames[1, -1], result.obs["images"][name][0])
        assert all(not np.array_equal(frames[0, j], frames[0, j + 1]) for j in range(CHUNK - 1))

    # An env that stops inside the chunk (its episode's limit, 2 actions) gets no frames after it.
    short = _engine(2, max_episode_steps=2)
    try:
        short.reset_envs([0, 1], [0, 5])
        stopped = short.chunk_step_envs([0, 1], actions[:2], record_env_indices=[1])
    finally:
        short.close()
    assert stopped.num_steps.tolist() == [2, 2] and stopped.truncated[:, 1].all()
    for name in CAMERAS:
        assert stopped.frames[name][0, :2].any() and not stopped.frames[name][0, 2:].any()


@pytest.mark.parametrize(
    ("tile", "trees"), [(None, None), ((8, 4), None), ((8, 8), ("cubql", 2)), ((16, 16), ("sah", 1))]
)
def test_any_ray_order_and_mesh_trees_draw_the_engines_images_bit_for_bit(engine, tile, trees):
    """The ray tracer draws the same pixels whatever order its rays are in
    (``frames.order_rays``) and whichever trees its meshes have (``frames.build_mesh_trees``;
    ``None``: MuJoCo Warp's): a context of each draws the images the engine served."""
    from types import SimpleNamespace

    from vecsim.engine.mjwarp import frames
    from vecsim.engine.mjwarp.frames import render_context

    ids = np.arange(len(STATES))
    engine.reset_envs(ids, np.array(STATES))
    served = {name: engine._obs["images"][name].copy() for name in CAMERAS}
    (batch,) = engine._batches
    camera = engine.assignment.camera
    rc, order = render_context(batch.mjm, len(STATES), camera, tile=tile, mesh_trees=trees)
    probe = SimpleNamespace(
        view=batch.view,
        data=batch.data,
        model=batch.model,
        render=rc,
        ray_order=order,
        pixels=batch.pixels,
        host=batch.host,
    )
    drawn: dict[str, np.ndarray] = {}
    orientation = engine.assignment.libero.image_orientation
    frames.draw(
        probe, CAMERAS, camera.height, camera.width, orientation, lambda name, px: drawn.update({name: px.copy()})
    )
    for name in CAMERAS:
        np.testing.assert_array_equal(drawn[name], served[name], err_msg=f"{name}, tile {tile}, trees {trees}")


def test_a_refill_draws_the_images_a_reset_alone_draws(engine):
    """A refill draws its reset envs in the chunk's render, not in one of their own: their
    images are the ones a reset alone answers, bit for bit, and it renders once."""
    ids = np.arange(len(STATES))
    alone, _ = engine.reset_envs([1], [45])
    want = {name: alone["images"][name][0].copy() for name in CAMERAS}
    engine.reset_envs(ids, np.array(STATES))
    (reset, _info), chunk = engine.reset_and_step_envs([1], [45], [0, 2], _actions(2))
    assert not chunk.errors and chunk.num_steps.tolist() == [CHUNK, CHUNK]
    assert engine.last_timing.renders == len(STATES)  # one render of the batch's 3 worlds
    for name in CAMERAS:
        np.testing.assert_array_equal(reset["images"][name][0], want[name], err_msg=name)
        np.testing.assert_array_equal(engine._obs["images"][name][1], want[name], err_msg=name)
