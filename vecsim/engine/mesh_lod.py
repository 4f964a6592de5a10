"""Lighter meshes for drawing: a model's triangle lists simplified on a grid, for render contexts only.

LIBERO's scenes hold about 400 thousand visual triangles (scanned objects, kitchen backgrounds,
the Panda's links), and drawing them is what bounds a frame, on a GPU as in software. A render
context (``MjrContext``) copies every mesh's triangles to the GPU when it is made and never
looks at the model's mesh arrays again, so :func:`drawn_with` writes simplified triangles over
the start of each mesh's face range, lowers ``mesh_facenum``, lets the caller make the context,
and puts the model's arrays back: physics never sees a change.

The simplification is vertex clustering on a grid of ``cell`` metres (mesh vertices are in
metres, scale applied), made careful for textured meshes:

- Every grid cell keeps one of its own vertices: the one nearest the planes of the triangles
  around it and of planes standing on the mesh's open edges (their summed, area-weighted
  quadric, Garland and Heckbert's error; the distance to the cell's centroid breaks ties on
  flat ground), so creases, corners and outlines stay where they are.
  No vertex moves further than a cell's diagonal.
- A triangle whose corners fall in fewer than three cells is dropped; so is one that turned
  over (its normal against the original's) and a second copy of one already kept.
- Texture coordinates and normals are picked per corner group: corners of one cell whose own
  normals lean along the same axis and whose texture coordinates fall in one texture-space cell
  (sized from the mesh's own texels per metre). Corners on either side of a texture seam sit
  far apart in texture space, so they never share a group, and a triangle keeps drawing from
  its own part of the texture; a box's faces lean along different axes, so its edges stay hard.
  Each group takes the texture coordinates of its member nearest the cell's kept vertex
  (exactly that vertex's, where it is a member) and the area-weighted mean of its members'
  normals (a relief, such as a basket's weave, would otherwise shade in blotches).
- Meshes that ride with a camera (a wrist camera's gripper, seen from centimetres) and meshes
  of at most ``MIN_FACES`` triangles keep all of theirs.

Everything is numpy and deterministic: the same model gives the same triangles, so rendering
stays deterministic per state. A render context keeps what it was given; a renderer builds the
simplified lists once per scene (see ``docs/benchmarks.md`` for the time it takes).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import mujoco
import numpy as np

# Meshes this small are left alone: they cost little to draw and lose their shape first.
MIN_FACES = 200
# Meshes this close to a camera that moves with them keep every triangle (metres).
NEAR_CAMERA = 0.25
# Ties on flat ground: how much the distance to a cell's centroid weighs beside the quadric error.
_CENTROID_WEIGHT = 0.05
# A texture-space cell spans this many times what a grid cell spans on the mesh's texture.
_TEXCOORD_CELL_SCALE = 2.0


@dataclass(frozen=True)
class SimplifiedMeshes:
    """Simplified triangle lists of a model's meshes, for :func:`drawn_with`.

    ``mesh_ids`` are the meshes that changed; ``face``, ``facenormal`` and ``facetexcoord`` hold
    each one's new corners (indices local to the mesh, as in the model), one array a mesh;
    ``normal_index`` and ``normal`` the normals written over the mesh's own (local indices into
    its normals, and the unit vectors). ``faces_before`` and ``faces_after`` count the triangles
    of every mesh of the model.
    """

    cell: float
    mesh_ids: tuple[int, ...]
    face: tuple[np.ndarray, ...]
    facenormal: tuple[np.ndarray, ...]
    facetexcoord: tuple[np.ndarray, ...]
    normal_index: tuple[np.ndarray, ...]
    normal: tuple[np.ndarray, ...]
    faces_before: int
    faces_after: int


def riding_meshes(model: mujoco.MjModel, near: float = NEAR_CAMERA) -> set[int]:
    """Return the meshes that ride with a camera: geoms within ``near`` metres of a camera mounted
    on their body or one of its ancestors (not the world), in the model's reference pose.

    A wrist camera sees its gripper from a few centimetres, whatever the arm does, so a grid
    coarse enough for the rest of the scene would show there (measured: the Panda's hand was
    40% of the wrist view's error in LIBERO-10 task 2).
    """
    riding: set[int] = set()
    mounted = [c for c in range(model.ncam) if model.cam_bodyid[c] != 0]
    if not mounted:
        return riding
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    mujoco.mj_camlight(model, data)
    for geom in range(model.ngeom):
        if model.geom_type[geom] != mujoco.mjtGeom.mjGEOM_MESH:
            continue
        ancestors = set()
        body = int(model.geom_bodyid[geom])
        while body != 0:
            ancestors.add(body)
            body = int(model.body_parentid[body])
        for camera in mounted:
            reach = np.linalg.norm(data.geom_xpos[geom] - data.cam_xpos[camera]) - model.geom_rbound[geom]
            if int(model.cam_bodyid[camera]) in ancestors and reach < near:
                riding.add(int(model.geom_dataid[geom]))
    return riding


def simplify_meshes(model: mujoco.MjModel, cell: float, min_faces: int = MIN_FACES) -> SimplifiedMeshes:
    """Simplify every mesh of ``model`` with more than ``min_faces`` triangles on a ``cell``-metre grid,
    except those that ride with a camera (:func:`riding_meshes`).

    The model is not changed. Returns the new triangle lists (see :class:`SimplifiedMeshes`).

    Raises:
        ValueError: ``cell`` is not a positive, finite number.
    """
    if not (np.isfinite(cell) and cell > 0):
        raise ValueError(f"mesh simplification: cell must be a positive number of metres, got {cell!r}")
    mesh_ids: list[int] = []
    lists: list[tuple[np.ndarray, ...]] = []
    before = int(model.mesh_facenum.sum()) if model.nmesh else 0
    after = before
    riding = riding_meshes(model) if model.nmesh else set()
    for mesh in range(model.nmesh):
        count = int(model.mesh_facenum[mesh])
        if count <= min_faces or mesh in riding:
            continue
        first_face = int(model.mesh_faceadr[mesh])
        span = slice(first_face, first_face + count)
        vert_start, vert_count = int(model.mesh_vertadr[mesh]), int(model.mesh_vertnum[mesh])
        tex_start, tex_count = int(model.mesh_texcoordadr[mesh]), int(model.mesh_texcoordnum[mesh])
        texcoord = model.mesh_texcoord[tex_start : tex_start + tex_count] if tex_count else None
        normal_start, normal_count = int(model.mesh_normaladr[mesh]), int(model.mesh_normalnum[mesh])
        simplified = _simplify(
            model.mesh_vert[vert_start : vert_start + vert_count].astype(np.float64),
            model.mesh_face[span].astype(np.int64),
            model.mesh_facenormal[span].astype(np.int64),
            model.mesh_normal[normal_start : normal_start + normal_count].astype(np.float64),
            model.mesh_facetexcoord[span],
            None if texcoord is None else texcoord.astype(np.float64),
            float(cell),
        )
        mesh_ids.append(mesh)
        lists.append(simplified)
        after -= count - len(simplified[0])
    columns = tuple(zip(*lists)) if lists else ((),) * 5
    return SimplifiedMeshes(float(cell), tuple(mesh_ids), *columns, before, after)  # type: ignore[arg-type]


@contextmanager
def drawn_with(model: mujoco.MjModel, simplified: SimplifiedMeshes) -> Iterator[None]:
    """Hold ``simplified``'s triangles in ``model``'s mesh arrays for the ``with`` block, then restore them.

    Make the render context inside the block; nothing else should use the model meanwhile.
    Yields None.
    """
    saved = [
        (mesh, int(model.mesh_faceadr[mesh]), int(model.mesh_facenum[mesh]), int(model.mesh_normaladr[mesh]))
        for mesh in simplified.mesh_ids
    ]
    kept = [
        (
            model.mesh_face[a : a + n].copy(),
            model.mesh_facenormal[a : a + n].copy(),
            model.mesh_facetexcoord[a : a + n].copy(),
            model.mesh_normal[normal_start + normal_indices].copy(),
        )
        for (_, a, n, normal_start), normal_indices in zip(saved, simplified.normal_index)
    ]
    try:
        for (mesh, start, _, normal_start), face, facenormal, facetexcoord, normal_indices, normal in zip(
            saved,
            simplified.face,
            simplified.facenormal,
            simplified.facetexcoord,
            simplified.normal_index,
            simplified.normal,
        ):
            end = start + len(face)
            model.mesh_face[start:end] = face
            model.mesh_facenormal[start:end] = facenormal
            model.mesh_facetexcoord[start:end] = facetexcoord
            model.mesh_normal[normal_start + normal_indices] = normal
            model.mesh_facenum[mesh] = len(face)
        yield
    finally:
        for (mesh, start, count, normal_start), (face, facenormal, facetexcoord, normal), normal_indices in zip(
            saved, kept, simplified.normal_index
        ):
            model.mesh_face[start : start + count] = face
            model.mesh_facenormal[start : start + count] = facenormal
            model.mesh_facetexcoord[start : start + count] = facetexcoord
            model.mesh_normal[normal_start + normal_indices] = normal
            model.mesh_facenum[mesh] = count


def _group(keys: np.ndarray) -> tuple[np.ndarray, int]:
    """Return, for rows of integer ``keys``, a group number per row (equal rows, equal groups) and the count."""
    if not len(keys):
        return np.zeros(0, dtype=np.int64), 0
    keys = keys - keys.min(axis=0)
    spans = keys.max(axis=0) + 1
    # One int64 a row sorts many times faster than rows; rows stay rows where that could overflow.
    if float(np.prod(spans.astype(np.float64))) < 2.0**62:
        flat = np.zeros(len(keys), dtype=np.int64)
        for column, span in zip(keys.T, spans):
            flat = flat * int(span) + column
        _, inverse = np.unique(flat, return_inverse=True)
    else:
        _, inverse = np.unique(keys, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    return inverse, int(inverse.max()) + 1


def _first_by(group: np.ndarray, score: np.ndarray, groups: int) -> np.ndarray:
    """Return, for each group, the index of its member of least ``score`` (lowest index on ties)."""
    # lexsort is stable: among equal scores the lowest index comes first.
    order = np.lexsort((score, group))
    leader = np.ones(len(order), dtype=bool)
    leader[1:] = group[order][1:] != group[order][:-1]
    chosen = np.empty(groups, dtype=np.int64)
    chosen[group[order][leader]] = order[leader]
    return chosen


def _simplify(
    vert: np.ndarray,
    face: np.ndarray,
    facenormal: np.ndarray,
    normal: np.ndarray,
    facetexcoord: np.ndarray,
    texcoord: np.ndarray | None,
    cell: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    origin = vert.min(axis=0)
    vert_cell, cells = _group(np.floor((vert - origin) / cell).astype(np.int64))

    # Area-weighted plane quadrics of the triangles, summed into the cells of their corners.
    corners = vert[face]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    double_area = np.linalg.norm(cross, axis=1)
    unit = np.divide(cross, double_area[:, None], out=np.zeros_like(cross), where=double_area[:, None] > 0)
    plane = np.concatenate([unit, -(unit * corners[:, 0]).sum(axis=1, keepdims=True)], axis=1)
    rows, cols = np.triu_indices(4)
    quadric_terms = plane[:, rows] * plane[:, cols] * (double_area / 2)[:, None]
    corner_cell = vert_cell[face].reshape(-1)
    quadric = np.stack(
        [np.bincount(corner_cell, np.repeat(quadric_terms[:, k], 3), minlength=cells) for k in range(len(rows))],
        axis=1,
    )
    weight = np.bincount(corner_cell, np.repeat(double_area / 2, 3), minlength=cells)
    quadric += _boundary_quadrics(vert, face, unit, vert_cell, cells, rows, cols)

    # Each cell keeps the vertex of least error (squared distance to its planes) plus a little of
    # its distance to the cell's centroid.
    homogeneous = np.concatenate([vert, np.ones((len(vert), 1))], axis=1)
    factor = np.where(rows == cols, 1.0, 2.0)
    error = (quadric[vert_cell] * homogeneous[:, rows] * homogeneous[:, cols] * factor).sum(axis=1)
    error = error / np.maximum(weight[vert_cell], np.finfo(np.float64).tiny)
    counts = np.bincount(vert_cell, minlength=cells)
    centroid = np.stack([np.bincount(vert_cell, vert[:, k], minlength=cells) for k in range(3)], axis=1)
    centroid /= np.maximum(counts, 1)[:, None]
    spread = ((vert - centroid[vert_cell]) ** 2).sum(axis=1)
    kept_vert = _first_by(vert_cell, np.maximum(error, 0.0) + _CENTROID_WEIGHT * spread, cells)

    new_face = kept_vert[vert_cell[face]]
    face_cells = vert_cell[face]
    keep = (
        (face_cells[:, 0] != face_cells[:, 1])
        & (face_cells[:, 1] != face_cells[:, 2])
        & (face_cells[:, 0] != face_cells[:, 2])
    )
    moved = vert[new_face]
    new_cross = np.cross(moved[:, 1] - moved[:, 0], moved[:, 2] - moved[:, 0])
    keep &= (new_cross * cross).sum(axis=1) > 0
    kept = np.flatnonzero(keep)

    # One copy of each triangle: compare corners rotated to start at the least index (winding kept).
    candidate = new_face[kept]
    shift = np.argmin(candidate, axis=1)
    rotated = candidate[np.arange(len(candidate))[:, None], (shift[:, None] + np.arange(3)) % 3]
    if len(rotated):
        copy, copies = _group(rotated)
        kept = kept[np.sort(_first_by(copy, np.zeros(len(copy)), copies))]

    new_facenormal, new_texcoord, normal_indices, normals = _corners(
        vert, face, facenormal, normal, facetexcoord, texcoord, double_area, vert_cell, kept_vert, cell
    )
    return (
        new_face[kept].astype(np.int32),
        new_facenormal[kept].astype(np.int32),
        new_texcoord[kept].astype(np.int32),
        normal_indices,
        normals.astype(np.float32),
    )


def _boundary_quadrics(
    vert: np.ndarray,
    face: np.ndarray,
    unit: np.ndarray,
    vert_cell: np.ndarray,
    cells: int,
    rows: np.ndarray,
    cols: np.ndarray,
) -> np.ndarray:
    """Return per cell the quadrics of planes standing on the mesh's open edges (its outline).

    Plane quadrics alone let an open edge's vertices slide along the surface; a plane through
    each open edge, perpendicular to its triangle, holds them (as Garland and Heckbert do). An
    edge is open when one triangle alone uses it, vertices compared by position: meshes whose
    corners each carry their own vertex (LIBERO's) are whole again, texture seams included.
    """
    order = np.lexsort(vert.T[::-1])
    distinct = np.ones(len(vert), dtype=bool)
    distinct[1:] = np.any(vert[order][1:] != vert[order][:-1], axis=1)
    welded = np.empty(len(vert), dtype=np.int64)
    welded[order] = np.cumsum(distinct) - 1
    ends = welded[face]
    start, end = ends.reshape(-1), np.roll(ends, -1, axis=1).reshape(-1)
    edge, edges = _group(np.column_stack([np.minimum(start, end), np.maximum(start, end)]))
    open_edge = np.bincount(edge, minlength=edges)[edge] == 1
    first = face.reshape(-1)[open_edge]
    second = np.roll(face, -1, axis=1).reshape(-1)[open_edge]
    along = vert[second] - vert[first]
    normal = np.cross(along, np.repeat(unit, 3, axis=0)[open_edge])
    length = np.linalg.norm(normal, axis=1)
    normal = np.divide(normal, length[:, None], out=np.zeros_like(normal), where=length[:, None] > 0)
    plane = np.concatenate([normal, -(normal * vert[first]).sum(axis=1, keepdims=True)], axis=1)
    terms = plane[:, rows] * plane[:, cols] * (along**2).sum(axis=1)[:, None]
    cell_of = np.concatenate([vert_cell[first], vert_cell[second]])
    return np.stack([np.bincount(cell_of, np.tile(terms[:, k], 2), minlength=cells) for k in range(len(rows))], axis=1)


def _corners(
    vert: np.ndarray,
    face: np.ndarray,
    facenormal: np.ndarray,
    normal: np.ndarray,
    facetexcoord: np.ndarray,
    texcoord: np.ndarray | None,
    double_area: np.ndarray,
    vert_cell: np.ndarray,
    kept_vert: np.ndarray,
    cell: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Return every corner's new normal and texture coordinate indices, and the normals to write.

    Corners are grouped by cell, by the axis their own normal leans along most (a box's faces
    never share a group, so its edges stay hard) and by texture-space cell. A group draws with
    the texture coordinates of its member nearest the cell's kept vertex and with the
    area-weighted mean of its members' normals, written over that member's normal (where
    members' normals are shared between groups, as in a welded mesh, normals stay as they were).
    """
    corners = face.size
    corner_cell = vert_cell[face].reshape(-1)
    corner_normal = normal[facenormal.reshape(-1)]
    axis = np.argmax(np.abs(corner_normal), axis=1)
    leaning = 2 * axis + (corner_normal[np.arange(corners), axis] < 0)
    columns = [corner_cell, leaning]
    if texcoord is not None:
        uv = texcoord[facetexcoord]
        # Texels per metre of the mesh: the median over its triangles of sqrt(texture area / area).
        duv1, duv2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
        uv_area = np.abs(duv1[:, 0] * duv2[:, 1] - duv1[:, 1] * duv2[:, 0])
        usable = (double_area > 0) & (uv_area > 0)
        if usable.any():
            scale = float(np.median(np.sqrt(uv_area[usable] / (double_area[usable]))))
            uv_cell = _TEXCOORD_CELL_SCALE * cell * scale
            columns += list(np.floor(uv.reshape(-1, 2) / uv_cell).astype(np.int64).T)
    group, groups = _group(np.column_stack(columns))
    distance = ((vert[face.reshape(-1)] - vert[kept_vert[corner_cell]]) ** 2).sum(axis=1)
    leader = _first_by(group, distance, groups)
    new_texcoord = facetexcoord.reshape(-1)[leader[group]] if texcoord is not None else facetexcoord.reshape(-1)

    normal_indices = facenormal.reshape(-1)[leader]
    if len(np.unique(normal_indices)) != groups:
        return facenormal, new_texcoord.reshape(face.shape), np.zeros(0, np.int64), np.zeros((0, 3))
    weight = np.repeat(double_area, 3)
    mean = np.stack([np.bincount(group, corner_normal[:, k] * weight, minlength=groups) for k in range(3)], axis=1)
    length = np.linalg.norm(mean, axis=1, keepdims=True)
    mean = np.where(length > 0, mean / np.maximum(length, np.finfo(np.float64).tiny), normal[normal_indices])
    return normal_indices[group].reshape(face.shape), new_texcoord.reshape(face.shape), normal_indices, mean
