"""What the client knows of the job from the pods' ``/v1/info``: spaces, instructions, reset
kinds, state counts and each pod's build, and the answer caps that follow from the spaces. Pure."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from gymnasium import Space
from gymnasium.spaces import Dict
from gymnasium.vector.utils import create_empty_array

from vecsim import trees
from vecsim.client.errors import PodRequestError, PodUnavailableError
from vecsim.spaces import space_from_json, wire_action_space, without_rng
from vecsim.transport import DEFAULT_MAX_ANSWER_BYTES

__all__ = ["JobInfo"]

# Bytes an env's answer may hold besides its observation: reward, flags, env id, task id, info.
_PER_ENV_EXTRA_BYTES = 4096
# A chunk's answer carries reward, terminated, truncated and success per action of each env.
_PER_ACTION_BYTES = 16


class JobInfo:
    """The job as its pods describe it; ``spaces`` is None until read, ``()`` for a job without envs."""

    def __init__(self) -> None:
        self.spaces: tuple[Space, Space] | tuple[()] | None = None
        self.instructions: dict[str, str] = {}
        self.reset_kinds: dict[str, str] = {}
        self.num_states: dict[str, int] = {}
        self.instances: dict[str, str | None] = {}  # pod -> its envs' build ("instance" in /v1/info)
        self._env_answer_bytes: int | None = None  # what one env's answer can take, from the spaces

    @property
    def observation_space(self) -> Space | None:
        return self.spaces[0] if self.spaces else None

    @property
    def action_space(self) -> Space | None:
        """The action space as the pods take it: a Dict or Tuple one flattened."""
        return wire_action_space(self.spaces[1]) if self.spaces else None

    @property
    def served_action_space(self) -> Space | None:
        """The envs' own action space."""
        return self.spaces[1] if self.spaces else None

    def adopt(self, infos: Mapping[str, Mapping[str, Any]]) -> None:
        """Take instructions and spaces from pods' ``/v1/info`` answers (pods with envs only).

        Raises:
            PodUnavailableError: a pod without spaces yet (envs not built).
            PodRequestError: pods whose spaces differ.
        """
        spaces_json = None
        first = next(iter(infos), None)
        for pod, info in infos.items():
            self.instances[pod] = info.get("instance")
            for task in info.get("tasks", []):
                self.instructions.setdefault(task["task_id"], task.get("instruction", ""))
                self.reset_kinds.setdefault(task["task_id"], task.get("reset", "state_id"))
                if "num_states" in task:
                    self.num_states.setdefault(task["task_id"], int(task["num_states"]))
            here = (info.get("observation_space"), info.get("action_space"))
            if here[0] is None or here[1] is None:
                raise PodUnavailableError({pod: []}, "envs not built yet (no spaces in /v1/info)")
            if spaces_json is None:
                spaces_json = here
            elif without_rng(here) != without_rng(spaces_json):
                # Generators aside: the first pod's seeded spaces are taken, as gymnasium's vector
                # envs take their first env's.
                raise PodRequestError(pod, None, f"its spaces differ from pod {first}'s; one job, one space")
        if spaces_json is not None:
            self.spaces = (space_from_json(spaces_json[0]), space_from_json(spaces_json[1]))
        else:
            self.spaces = ()

    def answer_cap(self, num_envs: int, max_answer_bytes: int | None) -> int:
        """The most bytes a pod of ``num_envs`` envs may answer with: ``max_answer_bytes`` when
        given, else twice what its envs can produce plus a MiB (the default cap before the spaces
        are known)."""
        if max_answer_bytes is not None:
            return max_answer_bytes
        if not self.spaces:
            return DEFAULT_MAX_ANSWER_BYTES
        if self._env_answer_bytes is None:
            one_env = create_empty_array(self.spaces[0], n=1, fn=np.zeros)
            # Besides the observation, each env answers a few flags, its reward, ids and info.
            self._env_answer_bytes = sum(leaf.nbytes for leaf in trees.leaves(one_env)) + _PER_ENV_EXTRA_BYTES
        return 2 * max(num_envs, 1) * self._env_answer_bytes + (1 << 20)

    def chunk_answer_bytes(self, num_envs: int, chunk: int | None, num_recorded: int) -> int:
        """What a chunk step's answer carries beyond one observation per env: K per-action flags
        per env and, for each recorded env, K frames of every camera."""
        if chunk is None:
            return 0
        frames = 0
        if num_recorded and self.spaces:
            images = self.spaces[0].spaces.get("images") if isinstance(self.spaces[0], Dict) else None
            if images is not None:
                frames = sum(int(np.prod(space.shape)) * space.dtype.itemsize for space in images.spaces.values())
        return chunk * (num_envs * _PER_ACTION_BYTES + num_recorded * frames)
