"""Batched camera rendering: many envs' cameras into the tiles of one offscreen buffer, one readback.

MuJoCo's default path (robosuite's ``sim.render``, gymnasium's ``env.render()``) gives every env
its own GL context and render context and reads each camera back on its own. Here one process
has one GL context, and envs whose models carry the same render assets (every env of one task)
share one MuJoCo render context (``MjrContext``: meshes, textures, shadow map, and offscreen
buffers sized to a grid of tiles). A batch of camera views is drawn view by view
(``mjv_updateScene``, ``mjr_render``), each copied into its own tile, and the tiles are read
back with one ``glReadPixels`` per render context, then sliced and laid out as each view asks
(upright unless it says otherwise).

Each view is drawn at the buffer's origin, exactly where the default path draws it, and only
then copied to its tile (resolving the multisampled pixels on the way, as ``mjr_readPixels``
does). Drawing straight into a tile's viewport at an offset is not the same: the rasterizer
snaps vertices to sub-pixel positions after the viewport offset is added in floating point, so
an edge can land on the other side of a pixel centre (seen here: one pixel of 256 of LIBERO's
wrist camera, tile at x=48). Drawn at the origin, a batched view is bit for bit the default
path's image (``tests/engine/test_batch_render.py`` checks this against robosuite's and gymnasium's own
renderers for every preset). Tile 0 is that drawing area; views go to tiles 1 and up.

The GL backend follows ``MUJOCO_GL`` (``egl`` by default; ``osmesa`` and ``glfw`` too), so the
same code renders on a GPU node and through Mesa on a laptop. Nothing here is thread-safe: a
process renders from one thread.

With EGL, ``VECSIM_RENDER_PRIORITY`` (``low``, ``medium``, ``high``) in a pod's environment asks
for the GL context at that GPU scheduling priority through ``EGL_IMG_context_priority``, so
that a pod rendering on the GPU a trainer's policy runs on might yield it. The level is a hint:
``gl_info`` says which level the driver granted, and a driver without the extension renders at
its default (medium), with a warning. On an H200 (NVIDIA 580) every level was granted and none
changed the policy's speed beside the renders (docs/benchmarks.md, "Stage layouts and refill").
"""

from __future__ import annotations

import atexit
import contextlib
import ctypes
import hashlib
import logging
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import mujoco
import numpy as np

from vecsim.engine import mesh_lod
from vecsim.engine import render as render_presets
from vecsim.config import ImageOrientation, RenderPreset
from vecsim.engine.render import RenderSettings

log = logging.getLogger("vecsim.engine.batch_render")

# Scenes hold this many geoms; MuJoCo's and robosuite's 1000 drops geoms of big scenes silently.
MAX_SCENE_GEOMS = 10_000
# A render context's offscreen buffer is at most this many pixels wide or high.
MAX_BUFFER_SIDE = 8192
# Tile 0 of every buffer is where views are drawn before they are copied to their own tiles.
_DRAWING_TILES = 1
# Index of a tile as GL reads it (bottom row first) that lays it out in each orientation.
_ORIENTED: dict[str, tuple[slice, slice]] = {
    "upright": (slice(None, None, -1), slice(None)),
    "rotate180": (slice(None, None, -1), slice(None, None, -1)),
    "raw": (slice(None), slice(None)),
}

# Model fields that a render context copies to the GPU when it is made: envs whose models agree
# on all of them can share one context.
_RENDER_ASSET_PREFIXES = ("tex_", "mesh_", "hfield_", "skin_", "mat_", "flex_")
_RENDER_ASSET_FIELDS = ("geom_type", "geom_size", "geom_dataid", "geom_matid")
_VISUAL_STRUCTS = ("global_", "quality", "headlight", "map", "scale", "rgba")
_SMALL_ARRAY_BYTES = 1 << 16

#: The environment variable naming the GL context's scheduling priority (see the module's text).
RENDER_PRIORITY_ENV = "VECSIM_RENDER_PRIORITY"
# EGL_IMG_context_priority's attribute and its levels (Khronos EGL extension #10).
_EGL_CONTEXT_PRIORITY_LEVEL_IMG = 0x3100
_EGL_PRIORITY_LEVELS = {"high": 0x3101, "medium": 0x3102, "low": 0x3103}
#: The levels ``VECSIM_RENDER_PRIORITY`` takes.
RENDER_PRIORITIES = tuple(sorted(_EGL_PRIORITY_LEVELS))
_EGL_PRIORITY_NAMES = {value: name for name, value in _EGL_PRIORITY_LEVELS.items()}


@dataclass(eq=False)
class CameraView:
    """One camera of one env: what to draw (``model``, ``data``) and from where.

    ``camera`` is the MuJoCo camera (fixed, or free with its own pose); ``option`` the
    visualisation options (geom groups shown, ...); ``orientation`` how the image's pixels are
    laid out (:data:`vecsim.config.ImageOrientation`). The view reads ``data`` when rendered, so
    it shows the state ``data`` holds then.
    """

    model: mujoco.MjModel
    data: mujoco.MjData
    camera: mujoco.MjvCamera
    option: mujoco.MjvOption = field(default_factory=mujoco.MjvOption)
    orientation: ImageOrientation = "upright"


def fixed_camera(model: mujoco.MjModel, name: str) -> mujoco.MjvCamera:
    """Return a MuJoCo camera looking through the model's camera ``name``.

    Raises:
        ValueError: the model has no camera of that name (the message lists the ones it has).
    """
    camera_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, name)
    if camera_id < 0:
        names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_CAMERA, i) for i in range(model.ncam)]
        raise ValueError(f"no camera {name!r} in the scene; it has {names}")
    camera = mujoco.MjvCamera()
    camera.type = mujoco.mjtCamera.mjCAMERA_FIXED
    camera.fixedcamid = camera_id
    return camera


def _render_assets(model: mujoco.MjModel) -> list[tuple[str, np.ndarray]]:
    names = sorted(
        name for name in dir(model) if name.startswith(_RENDER_ASSET_PREFIXES) or name in _RENDER_ASSET_FIELDS
    )
    return [(name, value) for name in names if isinstance(value := getattr(model, name), np.ndarray)]


def _visual_settings(model: mujoco.MjModel) -> list[str]:
    settings = [
        f"{struct_name}.{name}={getattr(getattr(model.vis, struct_name), name)!r}"
        for struct_name in _VISUAL_STRUCTS
        for name in sorted(a for a in dir(getattr(model.vis, struct_name)) if not a.startswith("_"))
    ]
    return settings + [f"stat.{name}={getattr(model.stat, name)!r}" for name in ("extent", "center")]


def render_key(model: mujoco.MjModel) -> str:
    """Return a cheap digest of what a render context takes from ``model``.

    It covers the visual settings, every asset array's shape and the content of the small ones
    (textures and meshes can be hundreds of MB: LIBERO's scenes hold ~200 MB of textures), so
    models with different keys never share a context; :func:`same_render_assets` decides for
    models with the same key.
    """
    digest = hashlib.blake2b(digest_size=16)
    for name, value in _render_assets(model):
        digest.update(f"{name}:{value.dtype}:{value.shape}".encode())
        if value.nbytes <= _SMALL_ARRAY_BYTES:
            digest.update(np.ascontiguousarray(value).tobytes())
    for line in _visual_settings(model):
        digest.update(line.encode())
    return digest.hexdigest()


def same_render_assets(first: mujoco.MjModel, second: mujoco.MjModel) -> bool:
    """Return True when a render context made for ``first`` draws ``second`` exactly as its own.

    That holds when the two agree on every asset a context uploads (textures, meshes, height
    fields, skins, materials, plane and mesh geoms) and on the visual settings: the envs of one
    task do, as they are built from one scene under one seed.
    """
    if first is second:
        return True
    if _visual_settings(first) != _visual_settings(second):
        return False
    ours, theirs = _render_assets(first), _render_assets(second)
    return len(ours) == len(theirs) and all(
        name == other and _same_bytes(value, other_value) for (name, value), (other, other_value) in zip(ours, theirs)
    )


def _same_bytes(first: np.ndarray, second: np.ndarray) -> bool:
    # Bytes, not values: some asset arrays hold NaN (mesh_polynormal), which equals nothing.
    if first.shape != second.shape or first.dtype != second.dtype:
        return False
    return np.array_equal(np.ascontiguousarray(first).view(np.uint8), np.ascontiguousarray(second).view(np.uint8))


class _GL:
    """This process's one GL context, made on first use with the backend ``MUJOCO_GL`` names.

    ``api`` is PyOpenGL's ``OpenGL.GL``, imported once the backend has told PyOpenGL which
    platform to load.
    """

    context: Any = None
    backend: str | None = None
    api: Any = None
    priority: str | None = None

    @classmethod
    def _free_at_exit(cls) -> None:
        # Another library's exit handler (robosuite's, say) may have ended the EGL display
        # already, which frees every context of the process; nothing is left to do then.
        try:
            cls.context.free()
        except Exception as exc:
            log.debug("GL context not freed at exit: %s", exc)

    @classmethod
    def current(cls) -> Any:
        if cls.context is None:
            backend = os.environ.setdefault("MUJOCO_GL", "egl").lower()
            priority = render_priority()
            if backend == "egl":
                cls.context, cls.priority = _egl_context(priority)
            elif backend in ("osmesa", "glfw"):
                if priority != "medium":
                    log.warning(
                        "%s=%s applies to EGL only; MUJOCO_GL=%s renders at its default priority",
                        RENDER_PRIORITY_ENV,
                        priority,
                        backend,
                    )
                if backend == "osmesa":
                    from mujoco.osmesa import GLContext
                else:
                    from mujoco.glfw import GLContext  # type: ignore[no-redef]
                cls.context, cls.priority = GLContext(64, 64), None
            else:
                raise RuntimeError(f"MUJOCO_GL={backend!r}: vecsim renders with egl, osmesa or glfw")
            cls.backend = backend
            from OpenGL import GL

            cls.api = GL
            atexit.register(cls._free_at_exit)
        # Other libraries make their own contexts current (and making one releases ours).
        cls.context.make_current()
        return cls.context


def render_priority() -> str:
    """Return the GL context priority ``VECSIM_RENDER_PRIORITY`` asks for (``medium`` when unset).

    Raises:
        ValueError: a value other than ``low``, ``medium`` or ``high``.
    """
    value = os.environ.get(RENDER_PRIORITY_ENV, "").strip().lower() or "medium"
    if value not in _EGL_PRIORITY_LEVELS:
        raise ValueError(f"{RENDER_PRIORITY_ENV}={value!r}: expected one of {list(RENDER_PRIORITIES)}")
    return value


def _egl_context(priority: str) -> tuple[Any, str]:
    """Return an EGL context (MuJoCo's, on the device ``MUJOCO_EGL_DEVICE_ID`` names) made at
    ``priority`` where the display offers ``EGL_IMG_context_priority``, and the level the driver
    granted (``medium``, the default, where it offers no choice)."""
    from mujoco import egl
    from mujoco.egl import egl_ext as EGL

    # MuJoCo's context picks the device, initialises the display and chooses the framebuffer
    # configuration; only its context attributes (none) are not ours to set.
    context = egl.GLContext(64, 64)
    if priority == "medium":
        return context, "medium"
    display = egl.EGL_DISPLAY
    extensions = (EGL.eglQueryString(display, EGL.EGL_EXTENSIONS) or b"").split()
    if b"EGL_IMG_context_priority" not in extensions:
        log.warning("this EGL offers no EGL_IMG_context_priority: rendering at medium priority, not %s", priority)
        return context, "medium"
    configs = (EGL.EGLConfig * 1)()
    found = ctypes.c_long()
    EGL.eglChooseConfig(display, egl.EGL_ATTRIBUTES, configs, 1, found)
    attributes = (ctypes.c_int32 * 3)(_EGL_CONTEXT_PRIORITY_LEVEL_IMG, _EGL_PRIORITY_LEVELS[priority], EGL.EGL_NONE)
    EGL.eglBindAPI(EGL.EGL_OPENGL_API)
    handle = EGL.eglCreateContext(display, configs[0], EGL.EGL_NO_CONTEXT, attributes) if found.value else None
    if not handle:
        log.warning("EGL made no context at %s priority (error 0x%x): rendering at medium", priority, EGL.eglGetError())
        return context, "medium"
    # Swap the prioritised context in for the default one; GLContext's make_current and free
    # act on ``_context``.
    EGL.eglDestroyContext(display, context._context)
    context._context = handle
    granted = ctypes.c_int32(0)
    EGL.eglQueryContext(display, handle, _EGL_CONTEXT_PRIORITY_LEVEL_IMG, ctypes.byref(granted))
    level = _EGL_PRIORITY_NAMES.get(granted.value, f"0x{granted.value:x}")
    if level != priority:
        log.warning("asked EGL for a %s-priority GL context; the driver granted %s", priority, level)
    return context, level


def gl_info() -> dict[str, str]:
    """Return the GL backend, vendor, renderer and version strings of this process's GL context,
    and with EGL the context's granted priority."""
    _GL.current()
    GL = _GL.api

    def text(name: int) -> str:
        value = GL.glGetString(name)
        return value.decode() if value else ""

    return {
        "backend": str(_GL.backend),
        "vendor": text(GL.GL_VENDOR),
        "renderer": text(GL.GL_RENDERER),
        "version": text(GL.GL_VERSION),
        # The scheduling priority the driver granted the context (EGL only; see the module's text).
        **({"priority": _GL.priority} if _GL.priority else {}),
    }


class _SharedContext:
    """One MuJoCo render context (and scene) shared by every attached model with the same assets."""

    def __init__(self, model: mujoco.MjModel) -> None:
        self.model = model
        self.users = 0
        self.tiles_wanted = 0
        self.scene = mujoco.MjvScene(model, maxgeom=MAX_SCENE_GEOMS)
        self.context: mujoco.MjrContext | None = None
        self.columns = 0
        self.rows = 0
        # Built on the first context that wants them and kept: a bigger grid makes a new context.
        self.simplified: mesh_lod.SimplifiedMeshes | None = None

    @property
    def capacity(self) -> int:
        """Views one pass can hold: every tile but the drawing area."""
        return max(self.columns * self.rows - _DRAWING_TILES, 0)

    def free(self) -> None:
        if self.context is not None:
            _GL.current()
            self.context.free()
            self.context = None
            self.columns = self.rows = 0


class BatchRenderer:
    """Renders batches of camera views of ``height`` x ``width`` pixels under one render preset.

    ``preset`` is a preset's name or, to measure other combinations of passes, any
    :class:`~vecsim.engine.render.RenderSettings` (``preset`` then reads ``custom``).

    Envs ``attach`` their model (with how many cameras they will ask for) when they are built and
    ``detach`` it when they close; ``render`` draws any views of attached models.
    ``views_rendered`` and ``readbacks`` count the views drawn and the buffer reads so far. A render
    context's buffers hold a tile for every attached camera of its models, and one to draw in
    (up to ``MAX_BUFFER_SIDE`` pixels a side; bigger batches take several passes, each with one
    readback); they are made on the first render after that number grows.

    Raises:
        ValueError: an unknown preset, or a size that is not positive or over half
            ``MAX_BUFFER_SIDE``.
    """

    def __init__(self, height: int, width: int, preset: RenderPreset | str | RenderSettings) -> None:
        if height < 1 or width < 1:
            raise ValueError(f"camera size must be positive, got height {height} and width {width}")
        if 2 * height > MAX_BUFFER_SIDE or 2 * width > MAX_BUFFER_SIDE:
            raise ValueError(f"camera size must be at most {MAX_BUFFER_SIDE // 2} a side, got {height}x{width}")
        self.settings = render_presets.settings(preset)
        self.preset = preset if isinstance(preset, str) else "custom"
        self.height = height
        self.width = width
        self._contexts: dict[str, list[_SharedContext]] = {}
        self._attached: dict[int, tuple[mujoco.MjModel, _SharedContext, int]] = {}
        self._perturb = mujoco.MjvPerturb()
        self.views_rendered = 0
        self.readbacks = 0

    def attach(self, model: mujoco.MjModel, cameras: int) -> None:
        """Register ``model`` for ``cameras`` views a batch; models with the same assets share a context.

        Returns None.
        """
        held = self._attached.get(id(model))
        if held is not None:
            shared, count = held[1], held[2] + 1
        else:
            candidates = self._contexts.setdefault(render_key(model), [])
            shared = next((c for c in candidates if same_render_assets(c.model, model)), None)
            if shared is None:
                shared = _SharedContext(model)
                candidates.append(shared)
            count = 1
        # Holding the model keeps its id from being reused while it is attached.
        self._attached[id(model)] = (model, shared, count)
        shared.users += 1
        shared.tiles_wanted += cameras

    def detach(self, model: mujoco.MjModel, cameras: int) -> None:
        """Undo one :meth:`attach` of ``model``; free its render context when no model uses it.

        Returns None.

        Raises:
            KeyError: ``model`` is not attached.
        """
        held = self._attached.get(id(model))
        if held is None:
            raise KeyError("detach: the model is not attached to this renderer")
        _, shared, count = held
        if count > 1:
            self._attached[id(model)] = (model, shared, count - 1)
        else:
            del self._attached[id(model)]
        shared.users -= 1
        shared.tiles_wanted -= cameras
        if shared.users == 0:
            shared.free()
            for key, candidates in list(self._contexts.items()):
                if shared in candidates:
                    candidates.remove(shared)
                    if not candidates:
                        del self._contexts[key]

    def render(self, views: Sequence[CameraView], out: np.ndarray | None = None) -> np.ndarray:
        """Render ``views`` upright (row 0 is the top of the picture).

        Args:
            views: camera views of attached models, drawn as their data are now.
            out: where to write the images, shape ``(len(views), height, width, 3)`` uint8;
                a new array when None.

        Returns:
            ``out`` (or the new array), image ``i`` showing ``views[i]``.

        Raises:
            KeyError: a view of a model that is not attached.
            ValueError: ``out`` of the wrong shape or dtype.
        """
        shape = (len(views), self.height, self.width, 3)
        if out is None:
            out = np.empty(shape, dtype=np.uint8)
        elif out.shape != shape or out.dtype != np.uint8:
            raise ValueError(f"out: expected uint8 {shape}, got {out.dtype} {out.shape}")
        if not views:
            return out
        groups: dict[int, tuple[_SharedContext, list[int]]] = {}
        for index, view in enumerate(views):
            held = self._attached.get(id(view.model))
            if held is None:
                raise KeyError("render: a view of a model that is not attached to this renderer")
            groups.setdefault(id(held[1]), (held[1], []))[1].append(index)
        _GL.current()
        for shared, indices in groups.values():
            self._ensure_context(shared, len(indices))
            for first in range(0, len(indices), shared.capacity):
                chunk = indices[first : first + shared.capacity]
                self._render_pass(shared, [views[i] for i in chunk], out, chunk)
        return out

    def context_of(self, model: mujoco.MjModel) -> tuple[mujoco.MjrContext | None, mujoco.MjvScene]:
        """Return the render context (None before the first render) and scene that draw ``model``.

        Raises:
            KeyError: ``model`` is not attached.
        """
        shared = self._attached[id(model)][1]
        return shared.context, shared.scene

    def close(self) -> None:
        """Free every render context. Returns None."""
        for candidates in self._contexts.values():
            for shared in candidates:
                shared.free()
        self._contexts.clear()
        self._attached.clear()

    def _grid(self, views: int) -> tuple[int, int]:
        tiles = views + _DRAWING_TILES
        max_columns = max(1, MAX_BUFFER_SIDE // self.width)
        max_rows = max(1, MAX_BUFFER_SIDE // self.height)
        columns = min(max_columns, math.ceil(math.sqrt(tiles)))
        rows = min(max_rows, math.ceil(tiles / columns))
        return columns, rows

    def _ensure_context(self, shared: _SharedContext, views: int) -> None:
        wanted = max(views, shared.tiles_wanted, 1)
        columns, rows = self._grid(wanted)
        if shared.context is not None and columns * rows <= shared.columns * shared.rows:
            return
        shared.free()
        model = shared.model
        # A render context sizes its buffers from the model when it is made; set them for this
        # preset and grid, and put the model's own values back after.
        vis = model.vis
        saved = (vis.global_.offwidth, vis.global_.offheight, vis.quality.shadowsize, vis.quality.offsamples)
        try:
            vis.global_.offwidth = columns * self.width
            vis.global_.offheight = rows * self.height
            render_presets.apply_to_model(model, self.settings)
            with self._meshes(shared):
                shared.context = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_150)
        finally:
            vis.global_.offwidth, vis.global_.offheight, vis.quality.shadowsize, vis.quality.offsamples = saved
        shared.columns, shared.rows = columns, rows
        render_presets.apply_to_scene(shared.scene, self.settings)
        log.debug(
            "render context %dx%d tiles of %dx%d (%s preset)", columns, rows, self.width, self.height, self.preset
        )

    def _meshes(self, shared: _SharedContext) -> contextlib.AbstractContextManager[None]:
        cell = self.settings.mesh_cell
        if cell is None:
            return contextlib.nullcontext()
        if shared.simplified is None or shared.simplified.cell != cell:
            shared.simplified = mesh_lod.simplify_meshes(shared.model, cell)
            log.debug(
                "meshes simplified on a %.4g m grid: %d of %d triangles kept",
                cell,
                shared.simplified.faces_after,
                shared.simplified.faces_before,
            )
        return mesh_lod.drawn_with(shared.model, shared.simplified)

    def _tile_origin(self, shared: _SharedContext, tile: int) -> tuple[int, int]:
        row, column = divmod(tile + _DRAWING_TILES, shared.columns)
        return column * self.width, row * self.height

    def _render_pass(
        self, shared: _SharedContext, views: list[CameraView], out: np.ndarray, targets: list[int]
    ) -> None:
        GL = _GL.api
        context, scene = shared.context, shared.scene
        assert context is not None
        height, width = self.height, self.width
        drawing_area = mujoco.MjrRect(0, 0, width, height)
        # Multisampled pixels are resolved into the second buffer, as mjr_readPixels does;
        # without multisampling the tiles sit beside the drawing area in the one buffer.
        tiles_buffer = context.offFBO_r if context.offSamples else context.offFBO
        for tile, view in enumerate(views):
            mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, context)
            mujoco.mjv_updateScene(
                view.model, view.data, view.option, self._perturb, view.camera, mujoco.mjtCatBit.mjCAT_ALL, scene
            )
            mujoco.mjr_render(drawing_area, scene, context)
            x, y = self._tile_origin(shared, tile)
            GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, context.offFBO)
            GL.glBindFramebuffer(GL.GL_DRAW_FRAMEBUFFER, tiles_buffer)
            GL.glBlitFramebuffer(
                0, 0, width, height, x, y, x + width, y + height, GL.GL_COLOR_BUFFER_BIT, GL.GL_NEAREST
            )
        last_row = self._tile_origin(shared, len(views) - 1)[1] // height
        read_width = min(len(views) + _DRAWING_TILES, shared.columns) * width
        pixels = np.empty(((last_row + 1) * height, read_width, 3), dtype=np.uint8)
        GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, tiles_buffer)
        GL.glReadBuffer(GL.GL_COLOR_ATTACHMENT0)
        GL.glPixelStorei(GL.GL_PACK_ALIGNMENT, 1)
        GL.glReadPixels(0, 0, read_width, pixels.shape[0], GL.GL_RGB, GL.GL_UNSIGNED_BYTE, pixels)
        self.views_rendered += len(views)
        self.readbacks += 1
        for tile, (view, target) in enumerate(zip(views, targets)):
            x, y = self._tile_origin(shared, tile)
            out[target] = pixels[y : y + height, x : x + width][_ORIENTED[view.orientation]]


_RENDERERS: dict[tuple[int, int, str], BatchRenderer] = {}


def shared_renderer(height: int, width: int, preset: RenderPreset | str) -> BatchRenderer:
    """Return this process's renderer for ``height`` x ``width`` images under ``preset``.

    Every env of a process that renders at one size and preset shares it, so that a worker that
    hosts several envs draws all their cameras in one batch.

    Raises:
        ValueError: an unknown preset or a bad size.
    """
    render_presets.settings(preset)
    key = (int(height), int(width), str(preset))
    renderer = _RENDERERS.get(key)
    if renderer is None:
        renderer = _RENDERERS[key] = BatchRenderer(height, width, preset)
    return renderer
