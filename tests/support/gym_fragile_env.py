"""A gymnasium env that breaks when told to, served by id ``support.gym_fragile_env:Fragile-v0``
(the pod imports this module, which registers the id): for rollouts in which one env raises.

The observation is ``[level, steps, tag]`` (float64): ``level`` moves by each action, ``steps``
counts the actions applied, and ``tag``, drawn at reset, tells a policy which trajectory a row
is. The action is one float32 in [-2, 2]. An action of ``BREAK`` or more raises ``ValueError``
in the step; one of ``-BREAK`` or less raises too and breaks the env's next reset as well
(``refuse_resets``, as ``support.gym_custom_env`` names it). All else follows from the reset's
seed, so an episode is the same whatever the env did before.
"""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np
from gymnasium import spaces

ENV_ID = "Fragile-v0"
BREAK = 1.5


class FragileEnv(gymnasium.Env):
    metadata: dict[str, Any] = {"render_modes": []}

    def __init__(self) -> None:
        self.observation_space = spaces.Box(-np.inf, np.inf, (3,), np.float64)
        self.action_space = spaces.Box(-2.0, 2.0, (1,), np.float32)
        self.refuse_resets = 0
        self._level = 0.0
        self._steps = 0
        self._tag = 0.0

    def _obs(self) -> np.ndarray:
        return np.array([self._level, self._steps, self._tag])

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        if self.refuse_resets > 0:
            self.refuse_resets -= 1
            raise ValueError("the fragile env is broken: it refuses this reset")
        super().reset(seed=seed)
        self._level = float(self.np_random.normal())
        self._tag = float(self.np_random.integers(1, 2**20))
        self._steps = 0
        return self._obs(), {}

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        value = float(np.asarray(action).reshape(-1)[0])
        if value <= -BREAK:
            self.refuse_resets = 1
            raise ValueError(f"the fragile env breaks at action {value}")
        if value >= BREAK:
            raise ValueError(f"the fragile env refuses action {value}")
        self._steps += 1
        self._level += value
        return self._obs(), -(self._level**2), False, False, {}


if ENV_ID not in gymnasium.registry:
    gymnasium.register(id=ENV_ID, entry_point=FragileEnv, max_episode_steps=50)
