"""The ``lowpoly`` preset: lighter meshes for the render context only, deterministic, seam-aware.

Bit-exactness against robosuite's and gymnasium's own renderers and batch-against-alone under
``lowpoly`` are in ``tests/engine/test_batch_render.py`` (its presets include it). Here: what the
simplification keeps, that physics never sees it, and that the preset goes wherever presets go.
"""

from __future__ import annotations

from collections.abc import Iterator

import mujoco
import numpy as np
import pydantic
import pytest

from vecsim.engine import mesh_lod, render
from vecsim.engine.batch_render import BatchRenderer
from vecsim.config import Assignment, CameraConfig, JobSpec, TaskBlock
from vecsim.engine import TaskGroupedVectorEnv
from vecsim.engine.tasks import RobotTaskEnv, make_env

CAMERA = CameraConfig(names=("agentview", "robot0_eye_in_hand"), height=24, width=32)
MESH_FIELDS = (
    "mesh_face",
    "mesh_facenormal",
    "mesh_facetexcoord",
    "mesh_facenum",
    "mesh_vert",
    "mesh_normal",
    "mesh_texcoord",
)


@pytest.fixture(scope="module")
def lift() -> Iterator[RobotTaskEnv]:
    """A tiny/lift env (the Panda's links are meshes of 5-15 thousand triangles) a step into its episode."""
    env = make_env("tiny/lift", CAMERA, "lowpoly")
    try:
        env.reset(options={"state_id": 1})
        env.step(np.full(env.action_space.shape, 0.3, dtype=np.float32))
        yield env
    finally:
        env.close()


def _two_chart_sheet(cells: int = 24) -> mujoco.MjModel:
    """A 1 m square of ``cells`` x ``cells`` quads facing +z, textured from two charts.

    Triangles with x < 0.5 read the texture at u in [0, 0.4], the others at u in [0.6, 1]: the
    line x = 0.5 is a texture seam, its vertices doubled, one copy for each chart.
    """
    vertices, texcoords, faces = [], [], []
    for side, (low, high) in enumerate(((0.0, 0.4), (0.6, 1.0))):
        columns = cells // 2 + 1
        base = len(vertices)
        for row in range(cells + 1):
            for column in range(columns):
                x = (side * (cells // 2) + column) / cells
                y = row / cells
                # A gentle bump: MuJoCo refuses a flat mesh (its convex hull has no volume).
                vertices.append((x, y, 0.05 * np.sin(np.pi * x) * np.sin(np.pi * y)))
                texcoords.append((low + (high - low) * column / (columns - 1), y))
        for row in range(cells):
            for column in range(columns - 1):
                a = base + row * columns + column
                b, c, d = a + 1, a + columns, a + columns + 1
                faces += [(a, b, d), (a, d, c)]

    def numbers(rows: list[tuple[float, ...]]) -> str:
        return " ".join(f"{value:g}" for row in rows for value in row)

    xml = f"""
    <mujoco>
      <asset>
        <mesh name="sheet" vertex="{numbers(vertices)}" texcoord="{numbers(texcoords)}" face="{numbers(faces)}"/>
      </asset>
      <worldbody><geom type="mesh" mesh="sheet"/></worldbody>
    </mujoco>"""
    return mujoco.MjModel.from_xml_string(xml)


def _corners(model: mujoco.MjModel, simplified: mesh_lod.SimplifiedMeshes) -> tuple[np.ndarray, np.ndarray]:
    """Positions and texture coordinates of the corners of mesh 0's simplified triangles."""
    mesh = simplified.mesh_ids.index(0)
    start, tex = int(model.mesh_vertadr[0]), int(model.mesh_texcoordadr[0])
    return model.mesh_vert[start + simplified.face[mesh]], model.mesh_texcoord[tex + simplified.facetexcoord[mesh]]


def test_a_textured_triangle_never_draws_from_the_other_side_of_a_seam() -> None:
    model = _two_chart_sheet()
    simplified = mesh_lod.simplify_meshes(model, cell=0.13)
    assert 0 < simplified.faces_after < simplified.faces_before
    _, uv = _corners(model, simplified)
    left = uv[:, :, 0] <= 0.4 + 1e-6
    right = uv[:, :, 0] >= 0.6 - 1e-6
    assert np.all(left.all(axis=1) | right.all(axis=1))


def test_simplified_triangles_face_the_way_they_did_and_none_is_degenerate_or_doubled() -> None:
    model = _two_chart_sheet()
    simplified = mesh_lod.simplify_meshes(model, cell=0.13)
    positions, _ = _corners(model, simplified)
    normals = np.cross(positions[:, 1] - positions[:, 0], positions[:, 2] - positions[:, 0])
    # MuJoCo turned the mesh to its principal axes: "up" is the original triangles' mean normal.
    original = model.mesh_vert[model.mesh_face[: simplified.faces_before]]
    up = np.cross(original[:, 1] - original[:, 0], original[:, 2] - original[:, 0]).sum(axis=0)
    assert np.all(normals @ up > 0)
    face = simplified.face[0]
    rotated = [tuple(np.roll(row, -int(np.argmin(row)))) for row in face]
    assert len(set(rotated)) == len(rotated)


def test_kept_corners_are_original_vertices_and_the_sheet_keeps_its_outline() -> None:
    model = _two_chart_sheet()
    simplified = mesh_lod.simplify_meshes(model, cell=0.13)
    positions, _ = _corners(model, simplified)
    drawn = positions.reshape(-1, 3)
    original = model.mesh_vert[: int(model.mesh_vertnum[0])]
    assert set(map(tuple, drawn)) <= set(map(tuple, original))
    # The square's four corners (the vertices furthest from its middle) stay where they are.
    reach = np.linalg.norm(original - original.mean(axis=0), axis=1)
    corners = original[reach >= reach.max() - 1e-6]
    assert len(corners) == 4
    assert set(map(tuple, corners)) <= set(map(tuple, drawn))


def test_simplification_is_deterministic_across_builds_of_a_scene(lift: RobotTaskEnv) -> None:
    other = make_env("tiny/lift", CAMERA, "lowpoly")
    try:
        first = mesh_lod.simplify_meshes(lift.camera_views[0].model, render.LOWPOLY_CELL)
        second = mesh_lod.simplify_meshes(other.camera_views[0].model, render.LOWPOLY_CELL)
    finally:
        other.close()
    assert first.mesh_ids == second.mesh_ids
    for name in ("face", "facenormal", "facetexcoord"):
        assert all(np.array_equal(a, b) for a, b in zip(getattr(first, name), getattr(second, name)))


def test_lowpoly_draws_fewer_triangles_of_the_robots_meshes(lift: RobotTaskEnv) -> None:
    simplified = mesh_lod.simplify_meshes(lift.camera_views[0].model, render.LOWPOLY_CELL)
    model = lift.camera_views[0].model
    assert simplified.mesh_ids
    assert all(len(face) <= model.mesh_facenum[mesh] for mesh, face in zip(simplified.mesh_ids, simplified.face))
    assert simplified.faces_after < simplified.faces_before


def test_the_gripper_the_wrist_camera_rides_with_keeps_every_triangle(lift: RobotTaskEnv) -> None:
    model = lift.camera_views[0].model
    hand = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_MESH, "gripper0_hand_vis")
    base = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_MESH, "robot0_link1_vis")
    assert model.mesh_facenum[hand] > mesh_lod.MIN_FACES and model.mesh_facenum[base] > mesh_lod.MIN_FACES
    simplified = mesh_lod.simplify_meshes(model, render.LOWPOLY_CELL)
    assert hand in mesh_lod.riding_meshes(model)
    assert hand not in simplified.mesh_ids
    assert base in simplified.mesh_ids


def test_making_a_lowpoly_context_leaves_the_model_and_the_physics_as_they_were(lift: RobotTaskEnv) -> None:
    model, data = lift.camera_views[0].model, lift.camera_views[0].data
    before = {name: getattr(model, name).copy() for name in MESH_FIELDS}
    state = (data.qpos.copy(), data.qvel.copy(), data.time)
    renderer = BatchRenderer(CAMERA.height, CAMERA.width, "lowpoly")
    renderer.attach(model, 2)
    try:
        renderer.render(lift.camera_views)
        assert renderer.context_of(model)[0] is not None
    finally:
        renderer.close()
    for name, value in before.items():
        assert np.array_equal(getattr(model, name), value), name
    assert np.array_equal(data.qpos, state[0]) and np.array_equal(data.qvel, state[1]) and data.time == state[2]


def test_two_lowpoly_renders_of_one_state_are_byte_identical(lift: RobotTaskEnv) -> None:
    images = []
    for _ in range(2):
        renderer = BatchRenderer(CAMERA.height, CAMERA.width, "lowpoly")
        renderer.attach(lift.camera_views[0].model, 2)
        try:
            images.append(renderer.render(lift.camera_views).tobytes())
        finally:
            renderer.close()
    assert images[0] == images[1]


def test_lowpoly_images_stay_close_to_lean_ones(lift: RobotTaskEnv) -> None:
    images = {}
    for preset in ("lean", "lowpoly"):
        renderer = BatchRenderer(CAMERA.height, CAMERA.width, preset)
        renderer.attach(lift.camera_views[0].model, 2)
        try:
            images[preset] = renderer.render(lift.camera_views).astype(np.float64)
        finally:
            renderer.close()
    assert not np.array_equal(images["lean"], images["lowpoly"])
    assert np.abs(images["lean"] - images["lowpoly"]).mean() < 3.0


def test_a_cell_that_is_not_a_positive_length_is_refused_naming_it(lift: RobotTaskEnv) -> None:
    for cell in (0.0, -0.01, float("nan")):
        with pytest.raises(ValueError, match="cell"):
            mesh_lod.simplify_meshes(lift.camera_views[0].model, cell)


def test_a_model_without_meshes_simplifies_to_nothing() -> None:
    model = mujoco.MjModel.from_xml_string("<mujoco><worldbody><geom size='1'/></worldbody></mujoco>")
    simplified = mesh_lod.simplify_meshes(model, render.LOWPOLY_CELL)
    assert simplified.mesh_ids == () and simplified.faces_before == simplified.faces_after == 0


def test_jobs_and_assignments_accept_lowpoly() -> None:
    assert JobSpec(suite="tiny", render="lowpoly").render == "lowpoly"
    assert Assignment(generation=0, pod="sim-0", stage_id=0, render="lowpoly").render == "lowpoly"
    with pytest.raises(pydantic.ValidationError, match="lowpoly"):
        JobSpec(suite="tiny", render="ultra")


def test_a_pods_envs_under_lowpoly_show_what_a_local_env_shows() -> None:
    assignment = Assignment(
        generation=1,
        pod="sim-0",
        stage_id=0,
        tasks=(TaskBlock(task_id="tiny/lift", env_start=0, num_envs=1),),
        camera=CAMERA,
        render="lowpoly",
        envs_per_worker=1,
    )
    local = make_env("tiny/lift", CAMERA, "lowpoly")
    pod = TaskGroupedVectorEnv(assignment)
    try:
        theirs, _ = pod.reset_envs([0], [2])
        mine, _ = local.reset(options={"state_id": 2})
    finally:
        pod.close()
        local.close()
    for name in CAMERA.names:
        assert np.array_equal(theirs["images"][name][0], mine["images"][name])
