"""Env factories and a probe env for ``tests/client/test_gym_as_itself.py``, imported by the pods
as a user's package would be (``gym/support.gym_served_envs:<callable>``)."""

from __future__ import annotations

import time

import gymnasium
import numpy as np
from gymnasium import spaces


def seeded_cartpole(seed: int = 0) -> gymnasium.Env:
    """An env factory as gymnasium's own tests write them (``tests/vector/testing_utils.make_env``):
    CartPole with its spaces seeded and a first reset with ``seed``."""
    env = gymnasium.make("CartPole-v1")
    env.action_space.seed(seed)
    env.observation_space.seed(seed + 1)
    env.reset(seed=seed)
    return env


class ProbeEnv(gymnasium.Env):
    """Bool Box actions, answered in the observation and named in the info (their dtype); an
    episode ends after ``max_count`` steps once that attribute is set (no such attribute at first)."""

    def __init__(self) -> None:
        self.action_space = spaces.Box(0, 1, (3,), dtype=bool)
        self.observation_space = spaces.Box(0.0, np.inf, (3,), np.float64)
        self.count = 0

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self.count = 0
        return np.zeros(3), {}

    def step(self, action):
        self.count += 1
        obs = np.asarray(action, dtype=np.float64) * self.count
        terminated = self.count >= getattr(self, "max_count", np.inf)
        return obs, 0.0, bool(terminated), False, {"action_dtype": np.asarray(action).dtype.str}


def probe() -> gymnasium.Env:
    """A factory returning the probe env itself, no wrapper around it."""
    return ProbeEnv()


class ComposedActionEnv(gymnasium.Env):
    """A Dict action space holding a Box, a Discrete and a Tuple; each step answers its action
    flattened (``float64``) and checks that the action is in the space, as the env gets it."""

    def __init__(self) -> None:
        self.action_space = spaces.Dict(
            {
                "move": spaces.Box(-1.0, 1.0, (2,), np.float32),
                "pick": spaces.Discrete(3, start=1),
                "flags": spaces.Tuple((spaces.MultiBinary(2), spaces.MultiDiscrete([2, 4]))),
            }
        )
        self.observation_space = spaces.Box(-1.0, 1.0, (spaces.flatdim(self.action_space),), np.float64)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        return np.zeros(self.observation_space.shape), {}

    def step(self, action):
        if action not in self.action_space:
            raise ValueError(f"{action} is not in the action space")
        obs = spaces.flatten(self.action_space, action).astype(np.float64)
        return obs, float(action["pick"]), False, False, {"pick": int(action["pick"])}


def composed() -> gymnasium.Env:
    """A factory of the Dict-action env."""
    return ComposedActionEnv()


class SleepyEnv(gymnasium.Env):
    """gymnasium's own tests' ``SlowEnv`` in small: a float32 Box action of shape () that the
    step hands to ``time.sleep`` (which takes a Python float or a float64, not a float32), and
    answers with its type; an ``rgb_array`` render of the steps taken so far."""

    metadata = {"render_modes": ["rgb_array"]}

    def __init__(self, render_mode: str | None = None) -> None:
        self.action_space = spaces.Box(0.0, 0.01, (), np.float32)
        self.observation_space = spaces.Box(0.0, 1.0, (), np.float64)
        self.render_mode = render_mode
        self.count = 0

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self.count = 0
        return np.zeros(()), {}

    def step(self, action):
        time.sleep(action)
        self.count += 1
        return np.asarray(action, dtype=np.float64), 0.0, False, False, {"action_type": type(action).__name__}

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        # CartPole's frame size: as JSON, two of them outgrow the answer cap its observations set.
        return np.full((400, 600, 3), self.count, dtype=np.uint8)


def sleepy(render_mode: str | None = "rgb_array") -> gymnasium.Env:
    """A factory of the sleepy env, rendering rgb arrays unless told otherwise."""
    return SleepyEnv(render_mode)
