"""A user's own gymnasium env, as a package of theirs would define it, served by id
``support.gym_custom_env:Custom-v0`` (the pod imports this module, which registers the id).

Its spaces are of every kind a vector env batches: a Dict observation holding a 0-d float64
Box, a Discrete, and a Tuple of a MultiBinary and a MultiDiscrete; a float64 Box action of
shape (2, 1). Its info has numbers, an array, a string and a nested dict; reset takes an
``options["offset"]``; an action of 42 raises ``ValueError`` in a step, and so does a reset with
seed 4242, or any reset while ``refuse_resets`` (settable) counts down to 0; ``gain`` can be set
and ``scaled(x)`` called.
"""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np
from gymnasium import spaces

ENV_ID = "Custom-v0"
BOOM = 42.0
BOOM_SEED = 4242


class CustomEnv(gymnasium.Env):
    metadata: dict[str, Any] = {"render_modes": []}

    def __init__(self, size: int = 5) -> None:
        self.size = size
        self.gain = 1.0
        self.refuse_resets = 0
        self.observation_space = spaces.Dict(
            {
                "level": spaces.Box(-np.inf, np.inf, (), np.float64),
                "cell": spaces.Discrete(size),
                "bits": spaces.Tuple((spaces.MultiBinary(3), spaces.MultiDiscrete([2, size]))),
            }
        )
        self.action_space = spaces.Box(-1.0, 1.0, (2, 1), np.float64)
        self._level = 0.0
        self._cell = 0
        self._steps = 0

    def _obs(self) -> dict[str, Any]:
        bits = self.np_random.integers(0, 2, 3).astype(np.int8)
        pair = np.array([self._steps % 2, self._cell], dtype=np.int64)
        return {"level": np.array(self._level), "cell": self._cell, "bits": (bits, pair)}

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        if seed == BOOM_SEED:
            raise ValueError(f"the custom env refuses seed {BOOM_SEED}")
        if self.refuse_resets > 0:
            self.refuse_resets -= 1
            raise ValueError("the custom env refuses this reset")
        super().reset(seed=seed)
        offset = float((options or {}).get("offset", 0.0))
        self._level = float(self.np_random.normal()) + offset
        self._cell = int(self.np_random.integers(self.size))
        self._steps = 0
        return self._obs(), {"offset": offset, "note": "reset"}

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        action = np.asarray(action)
        if action.shape != (2, 1) or action.dtype != np.float64:
            raise TypeError(f"expected a float64 (2, 1) action, got {action.dtype} {action.shape}")
        if action[0, 0] == BOOM:
            raise ValueError("the custom env refuses 42")
        self._steps += 1
        self._level += self.gain * float(action.sum()) + float(self.np_random.normal(scale=0.1))
        self._cell = (self._cell + 1 + int(action[1, 0] > 0)) % self.size
        terminated = abs(self._level) > 3.0
        info = {
            "steps": self._steps,
            "level_sq": np.float32(self._level**2),
            "trace": np.array([self._level, self.gain]),
            "detail": {"cell": self._cell, "even": self._steps % 2 == 0},
        }
        if self._steps % 3 == 0:
            info["every_third"] = "yes"
        return self._obs(), float(self._level), terminated, False, info

    def scaled(self, x: float) -> float:
        return x * self.gain


if ENV_ID not in gymnasium.registry:
    gymnasium.register(id=ENV_ID, entry_point=CustomEnv, max_episode_steps=7)
