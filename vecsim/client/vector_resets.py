"""What :class:`~vecsim.client.vector_env.HTTPVectorEnv`'s reset arguments mean.

gymnasium's rules for a vector env's ``reset(seed=, options=)``: :func:`autoreset_mode_of` (an
:class:`AutoresetMode` in any spelling), :func:`env_seeds` (``seed + i``, ``seed[i]`` or None) and
:func:`reset_mask` (``options["reset_mask"]``, in gymnasium's own wording). :class:`StateDraws`:
the fixed initial state each env of a robot task resets to, drawn from the env's own generator
(which a seed reseeds, as a gymnasium env's ``np_random``), or given as ``options["state_ids"]``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from gymnasium.utils import seeding
from gymnasium.vector.vector_env import AutoresetMode

__all__ = ["StateDraws", "autoreset_mode_of", "env_seeds", "reset_mask"]

# A generator and the seed it was made from.
Rng = tuple[np.random.Generator, int]


def autoreset_mode_of(mode: AutoresetMode | str) -> AutoresetMode:
    """Return the :class:`AutoresetMode` that ``mode`` names: the enum, its value
    (``"NextStep"``), or its name in any case (``"next_step"``, ``"SAME_STEP"``).

    Raises:
        ValueError: no such mode (names the valid spellings).
    """
    if isinstance(mode, AutoresetMode):
        return mode
    wanted = str(mode).replace("_", "").replace("-", "").lower()
    for member in AutoresetMode:
        if wanted in (member.value.lower(), member.name.replace("_", "").lower()):
            return member
    raise ValueError(
        f"unknown autoreset_mode {mode!r}; use gymnasium.vector.AutoresetMode or one of "
        f"{[m.name.lower() for m in AutoresetMode]}"
    )


def reset_mask(mask: Any, num_envs: int) -> np.ndarray:
    """``options["reset_mask"]`` checked (a copy), or every env when it is None.

    Raises:
        TypeError, ValueError: not a bool array of ``num_envs`` with a True (gymnasium's words).
    """
    if mask is None:
        return np.ones(num_envs, dtype=bool)
    # gymnasium's own wording (SyncVectorEnv.reset), which its tests match.
    if not isinstance(mask, np.ndarray):
        raise TypeError(f"`options['reset_mask']` must be a numpy array, got {type(mask)}")
    if mask.shape != (num_envs,):
        raise ValueError(f"`options['reset_mask']` must have shape `({num_envs},)`, got {mask.shape}")
    if mask.dtype != np.bool_:
        raise TypeError(f"`options['reset_mask']` must have `dtype=np.bool_`, got {mask.dtype}")
    if not mask.any():
        raise ValueError(
            f"`options['reset_mask']` must contain a boolean array with at least one True value, got reset_mask={mask}"
        )
    return mask.copy()


def env_seeds(seed: Any, num_envs: int) -> list[int | None]:
    """Each env's seed by gymnasium's rule: ``seed + i``, ``seed[i]`` or None.

    Raises:
        ValueError: a list of another length than ``num_envs``.
        TypeError: a seed that is not an int or None.
    """
    if seed is None:
        return [None] * num_envs
    if isinstance(seed, (int, np.integer)) and not isinstance(seed, bool):
        return [int(seed) + i for i in range(num_envs)]
    seeds = list(seed)
    if len(seeds) != num_envs:
        raise ValueError(
            f"If seeds are passed as a list the length must match num_envs={num_envs} but got length={len(seeds)}."
        )
    for i, s in enumerate(seeds):
        if s is not None and (isinstance(s, bool) or not isinstance(s, (int, np.integer))):
            raise TypeError(f"seed for env {i} must be an int or None, got {s!r}")
    return [None if s is None else int(s) for s in seeds]


class StateDraws:
    """Each env's generator of state ids: env ``i`` of task ``task_ids[i]`` draws from
    ``0..num_states[task]-1``. A generator is made on first use from fresh entropy, as a
    gymnasium env's ``np_random`` is, and a seed replaces it (:meth:`reseed`)."""

    def __init__(self, task_ids: list[str], num_states: Mapping[str, int]) -> None:
        self.task_ids = task_ids
        self.num_states = dict(num_states)
        self._rngs: dict[int, Rng] = {}

    def reseeded(self, seeds: list[int | None], envs: np.ndarray) -> dict[int, Rng]:
        """New generators for the envs ``envs`` whose seed is not None (not taken yet: see :meth:`take`)."""
        return {int(i): seeding.np_random(seeds[i]) for i in envs if seeds[i] is not None}

    def take(self, reseeded: Mapping[int, Rng]) -> None:
        """Make ``reseeded`` the envs' generators (once their reset is sent)."""
        self._rngs.update(reseeded)

    def state_ids(self, reseeded: Mapping[int, Rng], given: Any, mask: np.ndarray) -> np.ndarray:
        """The state id of every env ``mask`` marks: ``given`` (``options["state_ids"]``, one per
        env), or drawn from the env's generator (``reseeded``'s where it has one).

        Raises:
            ValueError: ``given`` not one int per env, or an id outside its task's states.
        """
        num_envs = len(self.task_ids)
        if given is not None:
            ids = np.asarray(given)
            if ids.shape != (num_envs,) or ids.dtype.kind not in "iu":
                raise ValueError(
                    f"options['state_ids'] must be {num_envs} ints (one per env), got {ids.dtype} {list(ids.shape)}"
                )
            ids = ids.astype(np.int64)
        else:
            ids = np.array([self.draw(i, reseeded.get(i)) if m else 0 for i, m in enumerate(mask)], dtype=np.int64)
        for i in np.flatnonzero(mask):
            limit = self.num_states[self.task_ids[i]]
            if not 0 <= ids[i] < limit:
                raise ValueError(f"state id {ids[i]} for env {i} ({self.task_ids[i]}) is outside 0..{limit - 1}")
        return ids

    def draw(self, i: int, reseeded: Rng | None = None) -> int:
        """Env ``i``'s next state id, from its own generator (or ``reseeded``, its new one)."""
        limit = self.num_states[self.task_ids[i]]
        return int((reseeded or self.rng(i))[0].integers(limit))

    def rng(self, i: int) -> Rng:
        """Env ``i``'s generator and its seed."""
        if i not in self._rngs:
            self._rngs[i] = seeding.np_random()
        return self._rngs[i]
