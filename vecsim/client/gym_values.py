"""Values between gymnasium's forms and the wire's: actions out, an env's own observation back.

:func:`wire_actions`: a batch of actions as the pods take it, one array row per env. An array
action space (Box, Discrete, MultiDiscrete, MultiBinary) keeps the batch as it is
(:func:`vecsim.spaces.in_kind_of`). A Dict or Tuple action space's batch (gymnasium's batched form: a dict or
tuple of arrays with a leading env axis) becomes one flat row per env, gymnasium's ``flatten``
of that env's action (:func:`vecsim.spaces.wire_action_space`); the pod unflattens it.

    rows = wire_actions(single_action_space, action_space, actions, num_envs)

:func:`served_render_mode`, :func:`rendered`: ``render()`` of gym tasks, each env's
``render()`` called on its pod, as gymnasium's ``AsyncVectorEnv`` calls it in its workers.

:func:`env_observation`: one env's observation (a row of a batch) as an env hands it, for
``final_obs``: a Discrete value as a Python int, as gymnasium's own envs (FrozenLake, Taxi, ...)
return it.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import spaces
from gymnasium.vector.utils import iterate

from vecsim.spaces import in_kind_of, wire_action_space

__all__ = ["env_observation", "rendered", "served_render_mode", "wire_actions"]


def served_render_mode(envs: Any) -> str | None:
    """The render mode of ``envs`` (an HTTPVectorEnv of gym tasks): its first env's, as
    gymnasium's ``AsyncVectorEnv`` takes its first env's."""
    mode = envs.get_attr("render_mode")[0]
    return mode if isinstance(mode, str) else None


def rendered(render_mode: str | None, frames: tuple[Any, ...]) -> tuple[Any, ...]:
    """Each env's ``render()`` result (JSON values) as the env returned it: an ``rgb_array``
    frame (or each of an ``rgb_array_list``) a uint8 array, others as JSON holds them."""
    if render_mode == "rgb_array":
        return tuple(None if frame is None else np.asarray(frame, dtype=np.uint8) for frame in frames)
    if render_mode == "rgb_array_list":
        return tuple([np.asarray(image, dtype=np.uint8) for image in frame or ()] for frame in frames)
    return frames


def wire_actions(single: spaces.Space, batched: spaces.Space, actions: Any, num_envs: int) -> np.ndarray:
    """Return ``actions`` (a batch of ``num_envs`` actions of ``single``; ``batched`` is its batched
    space) as ``[num_envs, *wire shape]``: an array space's in the dtype sent where it is of the
    space's kind (:func:`vecsim.spaces.in_kind_of`), a flattened Dict or Tuple one's in the wire's dtype.

    Raises:
        TypeError: a scalar in place of a batch of array actions (as gymnasium's vector envs).
        ValueError: a batch of the wrong shape or length.
    """
    wire = wire_action_space(single)
    if wire is single:
        rows = in_kind_of(np.asarray(actions), single.dtype)
        if rows.ndim == 0:  # as gymnasium's vector envs, which cannot iterate over it
            raise TypeError(f"actions must be a batch of {num_envs} actions, got the scalar {rows!r}")
    else:
        try:
            rows = np.stack([spaces.flatten(single, action) for action in iterate(batched, actions)]).astype(wire.dtype)
        except (TypeError, ValueError, KeyError, IndexError, AssertionError) as exc:
            raise ValueError(f"actions must be a batch of {num_envs} actions of {single}: {exc}") from None
    expected = (num_envs, *wire.shape)
    if rows.shape != expected:
        raise ValueError(f"actions must have shape {list(expected)}, got {list(rows.shape)}")
    return rows


def env_observation(space: spaces.Space, value: Any) -> Any:
    """``value`` (one env's observation of ``space``, arrays) with each Discrete part an int."""
    if isinstance(space, spaces.Dict):
        return {key: env_observation(space[key], item) for key, item in value.items()}
    if isinstance(space, spaces.Tuple):
        return tuple(env_observation(sub, item) for sub, item in zip(space.spaces, value))
    return int(value) if isinstance(space, spaces.Discrete) else value
