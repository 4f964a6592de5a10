"""Render presets: how much of MuJoCo's rendering pipeline an env pays for.

Four presets, named in :class:`vecsim.config.Assignment` (``render``):

- ``full``: MuJoCo's and robosuite's defaults, untouched (shadows with the model's shadow map,
  usually 4096x4096; reflections; skybox).
- ``fast``: shadows on a 1024x1024 shadow map; no reflections.
- ``lean``: no shadows (and no shadow map at all), no reflections, no skybox.
- ``lowpoly``: ``lean``'s passes, drawing meshes simplified on a grid of ``LOWPOLY_CELL`` metres
  (:mod:`vecsim.engine.mesh_lod`). Physics keeps the model's meshes; only the render context gets the
  lighter ones. For scenes bound by triangle count (LIBERO's scanned objects and backgrounds).

The default 4096x4096 shadow map is what makes default rendering slow, on a GPU as much as in
Mesa's software renderer. Its size is read from ``model.vis.quality.shadowsize`` when the MuJoCo
render context (``MjrContext``) is made, so it must be set before that; the scene flags can change
at any time. Rendering is deterministic for a given model, state and preset.

vecsim's envs render through :mod:`vecsim.engine.batch_render`, which applies a preset with
:func:`apply_to_model` (to a render context it makes) and :func:`apply_to_scene`.
:func:`apply_to_robosuite` and :func:`apply_to_gymnasium` apply one to robosuite's and
gymnasium's own renderers: the default path, which tests and benchmarks compare against.
``docs/benchmarks.md`` shows frames of each preset and what each pass costs.

This module only touches MuJoCo objects; it imports robosuite and gymnasium nothing.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from typing import Any

import mujoco

from vecsim.engine import mesh_lod
from vecsim.config import RenderPreset


@dataclass(frozen=True)
class RenderSettings:
    """What one preset turns on.

    ``shadow_size`` None keeps the model's own shadow map size; ``multisamples`` None keeps the
    model's own multisampling of offscreen buffers (MuJoCo's default is 4 samples a pixel);
    ``mesh_cell`` None draws the model's own meshes, a length (metres) draws meshes simplified on
    a grid of that cell (:mod:`vecsim.engine.mesh_lod`).
    Benchmarks build other settings than the presets' to measure what each pass costs.
    """

    shadows: bool
    reflections: bool
    skybox: bool
    shadow_size: int | None
    multisamples: int | None = None
    mesh_cell: float | None = None


# The grid (metres) ``lowpoly`` simplifies meshes on: chosen by measurement, see docs/benchmarks.md.
LOWPOLY_CELL = 0.005

PRESETS: dict[str, RenderSettings] = {
    "full": RenderSettings(shadows=True, reflections=True, skybox=True, shadow_size=None),
    "fast": RenderSettings(shadows=True, reflections=False, skybox=True, shadow_size=1024),
    "lean": RenderSettings(shadows=False, reflections=False, skybox=False, shadow_size=0),
    "lowpoly": RenderSettings(shadows=False, reflections=False, skybox=False, shadow_size=0, mesh_cell=LOWPOLY_CELL),
}


def settings(preset: RenderPreset | str | RenderSettings) -> RenderSettings:
    """Return the :class:`RenderSettings` of ``preset`` (``preset`` itself if it is one).

    Raises:
        ValueError: ``preset`` is not one of ``full``, ``fast``, ``lean``, ``lowpoly``.
    """
    if isinstance(preset, RenderSettings):
        return preset
    try:
        return PRESETS[preset]
    except KeyError:
        raise ValueError(f"render: unknown preset {preset!r}; choose one of {sorted(PRESETS)}") from None


def apply_to_model(model: mujoco.MjModel, preset: RenderPreset | str | RenderSettings) -> None:
    """Set the model-side settings of ``preset`` (shadow map size, multisampling).

    Only render contexts made after this call see them. Returns None.

    Raises:
        ValueError: unknown preset.
    """
    chosen = settings(preset)
    if chosen.shadow_size is not None:
        model.vis.quality.shadowsize = chosen.shadow_size
    if chosen.multisamples is not None:
        model.vis.quality.offsamples = chosen.multisamples


def apply_to_scene(scene: mujoco.MjvScene, preset: RenderPreset | str | RenderSettings) -> None:
    """Set the scene flags of ``preset`` (shadows, reflections, skybox) on ``scene``. Returns None.

    Raises:
        ValueError: unknown preset.
    """
    chosen = settings(preset)
    scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = int(chosen.shadows)
    scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = int(chosen.reflections)
    scene.flags[mujoco.mjtRndFlag.mjRND_SKYBOX] = int(chosen.skybox)


def apply_to_robosuite(sim: Any, preset: RenderPreset | str) -> None:
    """Apply ``preset`` to a robosuite ``MjSim`` and its offscreen render context, if it has one.

    robosuite makes its render context while the env is constructed, before a caller can set
    the shadow map size, so when the size changes, or the preset draws simplified meshes, the
    context's ``MjrContext`` is made again (with the GL context current). Returns None.

    Raises:
        ValueError: unknown preset.
    """
    settings(preset)
    model = sim.model._model
    before = model.vis.quality.shadowsize
    apply_to_model(model, preset)
    context = sim._render_context_offscreen
    if context is None:
        return
    cell = settings(preset).mesh_cell
    if model.vis.quality.shadowsize != before or cell is not None:
        context.gl_ctx.make_current()
        context.con.free()
        with _meshes(model, cell):
            context._set_mujoco_context_and_buffers()
    apply_to_scene(context.scn, preset)


def apply_to_gymnasium(env: Any, preset: RenderPreset | str) -> Any:
    """Apply ``preset`` to a gymnasium MuJoCo env made with ``render_mode="rgb_array"``.

    Makes the env's offscreen viewer now (gymnasium makes it lazily on the first render), after
    setting the shadow map size, then sets the scene flags on it. Returns that viewer.

    Raises:
        ValueError: unknown preset, or ``env`` is not a gymnasium MuJoCo env rendering rgb arrays.
    """
    base = env.unwrapped
    renderer = getattr(base, "mujoco_renderer", None)
    if renderer is None or base.render_mode != "rgb_array":
        raise ValueError(
            f"render: {base.spec.id if base.spec else type(base).__name__} is not a MuJoCo env rendering rgb arrays"
        )
    apply_to_model(base.model, preset)
    with _meshes(base.model, settings(preset).mesh_cell):
        viewer = renderer._get_viewer(render_mode="rgb_array")
    apply_to_scene(viewer.scn, preset)
    return viewer


def _meshes(model: mujoco.MjModel, cell: float | None) -> contextlib.AbstractContextManager[None]:
    """Hold meshes simplified on a ``cell`` grid in ``model`` while a render context is made (None: no change)."""
    if cell is None:
        return contextlib.nullcontext()
    return mesh_lod.drawn_with(model, mesh_lod.simplify_meshes(model, cell))
