"""VLAEnv: a vecsim job as the env a VLA-RL trainer drives.

VLA-RL trainers (RLinf's ``LiberoEnv``, verl-vla's ``BaseEnv``) talk to their simulator through
the same small contract: ``reset`` of chosen envs to chosen initial states, and
``chunk_step(actions[num_envs, K, action_dim])`` answering per-action rewards, terminations and
truncations. :class:`VLAEnv` gives a vecsim job that shape, so a trainer swaps its in-process
simulator for vecsim pods by constructing this class instead::

    env = VLAEnv("http://controller:8000", keys="lerobot")
    obs, info = env.reset(env_ids=[0, 1, 2], state_ids=[4, 4, 7])
    obs, rewards, terminations, truncations, infos = env.chunk_step(actions)   # [num_envs, K, A]

What differs from those envs, on purpose: state ids are vecsim's, per task (each env's task is
fixed by the job, ``env.task_ids``), where RLinf numbers the initial states of a whole suite in
one range; and every action's termination and truncation is reported where it happened, also
with ``auto_reset`` (RLinf moves them to the chunk's last column then).

It is a thin layer over :class:`~vecsim.client.vector_env.HTTPVectorEnv`: autoreset disabled, or
gymnasium's same-step autoreset with ``auto_reset=True``.
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Literal

import httpx
import numpy as np
from gymnasium.vector import AutoresetMode

from vecsim.client.vector_env import HTTPVectorEnv
from vecsim.config import RoutingTable, RunnerConfig

__all__ = ["VLAEnv"]

Keys = Literal["vecsim", "lerobot"]


class VLAEnv:
    """A vecsim job with the reset/chunk_step contract of VLA-RL trainers (module docstring).

    The job is named as for :class:`HTTPVectorEnv` (exactly one of ``controller_url``,
    ``job_config``, ``routing``, ``pod_urls``). ``keys`` picks the observation's key names:

    - ``"vecsim"``: ``{"images": {camera: uint8[n, H, W, 3]}, "proprio": float[n, d],
      "instruction": [str] * n}``;
    - ``"lerobot"``: LeRobot's names, ``{"observation.images.<camera>": ...,
      "observation.state": ..., "task": [str] * n}``.

    Every observation is batched over all ``num_envs`` envs, in env order, with ``task_id`` (the
    vecsim task of each env) beside it. ``auto_reset``: envs that end inside a chunk are reset to
    a fresh state id (drawn from the seed of the last ``reset(seed=...)``) once the chunk is
    over; ``infos["final_obs"]`` then holds their last observation (same key names, one env
    each). Without it, an env that ended must be reset before the next chunk.
    """

    def __init__(
        self,
        controller_url: str | None = None,
        *,
        job_config: RunnerConfig | str | Path | None = None,
        routing: RoutingTable | None = None,
        pod_urls: Sequence[str] | None = None,
        keys: Keys = "vecsim",
        auto_reset: bool = False,
        timeout_s: float = 30.0,
        transport: httpx.AsyncBaseTransport | None = None,
        token: str | None = None,
    ) -> None:
        """Connect to the job; nothing is reset yet.

        Raises:
            ValueError: ``keys`` neither ``"vecsim"`` nor ``"lerobot"``; and as
                :class:`HTTPVectorEnv`.
            PodUnavailableError, PodRequestError, TimeoutError: as :class:`HTTPVectorEnv`.
        """
        if keys not in ("vecsim", "lerobot"):
            raise ValueError(f"keys must be 'vecsim' or 'lerobot', got {keys!r}")
        self.keys = keys
        self.auto_reset = auto_reset
        self.vector_env = HTTPVectorEnv(
            controller_url,
            job_config=job_config,
            routing=routing,
            pod_urls=pod_urls,
            autoreset_mode=AutoresetMode.SAME_STEP if auto_reset else AutoresetMode.DISABLED,
            timeout_s=timeout_s,
            transport=transport,
            token=token,
        )
        self.num_envs = self.vector_env.num_envs
        self.task_ids = list(self.vector_env.task_ids)
        instructions = self.vector_env.client.instructions
        self.instructions = [instructions.get(task, "") for task in self.task_ids]
        self.action_dim = int(np.prod(self.vector_env.single_action_space.shape))
        self._obs: Any = None

    def reset(
        self,
        env_ids: Sequence[int] | np.ndarray | None = None,
        state_ids: Sequence[int] | np.ndarray | None = None,
        seed: int | None = None,
    ) -> tuple[dict[str, Any], dict[str, Any]]:
        """Reset ``env_ids`` (default: all) to ``state_ids`` (one per env id, of that env's task;
        default: drawn, seeded by ``seed``). The other envs do not change; no env ids is a no-op.

        Returns:
            ``(obs, info)``: the observation of every env (the named ones just reset), and the
            vector env's reset info (``state_id`` and ``success`` with their ``_`` masks).

        Raises:
            ValueError: an env id out of range or named twice, state ids not one per env id, or
                a state id outside its task's range.
        """
        ids = np.arange(self.num_envs) if env_ids is None else np.asarray(env_ids, dtype=np.int64).reshape(-1)
        if ids.size == 0:
            if self._obs is None:
                raise ValueError("no env ids and no env was ever reset: there is no observation to answer")
            return self._present(copy.deepcopy(self._obs)), {}
        if ((ids < 0) | (ids >= self.num_envs)).any() or len(set(ids.tolist())) != ids.size:
            raise ValueError(f"env_ids must be distinct vector indices 0..{self.num_envs - 1}, got {ids.tolist()}")
        mask = np.zeros(self.num_envs, dtype=bool)
        mask[ids] = True
        options: dict[str, Any] = {"reset_mask": mask}
        if state_ids is not None:
            states = np.asarray(state_ids).reshape(-1)
            if states.shape != ids.shape or states.dtype.kind not in "iu":
                raise ValueError(f"state_ids must be {ids.size} integers, one per env id, got {states.tolist()}")
            full = np.zeros(self.num_envs, dtype=np.int64)
            full[ids] = states
            options["state_ids"] = full
        obs, info = self.vector_env.reset(seed=seed, options=options)
        self._obs = obs
        return self._present(obs), info

    def chunk_step(
        self, actions: Any
    ) -> tuple[dict[str, Any], np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Apply a chunk of K actions to every env (``[num_envs, K, action_dim]``, numpy or torch).

        Returns:
            ``(obs, rewards float[num_envs, K], terminations bool[num_envs, K], truncations
            bool[num_envs, K], infos)``: each env stops at its first termination or truncation
            (later entries 0/false), ``obs`` is after each env's last applied action (after its
            reset, with ``auto_reset``), ``infos["num_steps"]`` the actions each env applied.

        Raises:
            ResetNeeded: (without ``auto_reset``) an env ended and was not reset, or was never reset.
            ValueError: a chunk of the wrong shape or not finite.
        """
        if hasattr(actions, "detach"):  # a torch tensor, without importing torch here
            actions = actions.detach().cpu().numpy()
        obs, rewards, terminations, truncations, infos = self.vector_env.chunk_step(actions)
        self._obs = obs
        if "final_obs" in infos:
            infos["final_obs"] = np.array(
                [None if row is None else self._rename(row) for row in infos["final_obs"]], dtype=object
            )
        return self._present(obs), rewards, terminations, truncations, infos

    def close(self) -> None:
        """Close the connections to the job. Idempotent."""
        self.vector_env.close()

    def __enter__(self) -> VLAEnv:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _rename(self, obs: dict[str, Any]) -> dict[str, Any]:
        """The observation's arrays under this env's key names (batched or one env's)."""
        images = obs.get("images", {})
        if self.keys == "vecsim":
            return {"images": dict(images), "proprio": obs["proprio"]}
        named = {f"observation.images.{camera}": image for camera, image in images.items()}
        named["observation.state"] = obs["proprio"]
        return named

    def _present(self, obs: dict[str, Any]) -> dict[str, Any]:
        presented = self._rename(obs)
        presented["task" if self.keys == "lerobot" else "instruction"] = list(self.instructions)
        presented["task_id"] = list(self.task_ids)
        return presented
