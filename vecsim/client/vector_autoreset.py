"""How :class:`~vecsim.client.vector_env.HTTPVectorEnv`'s steps reach the pods under gymnasium's
autoreset modes. Pods never autoreset: the client sends the resets that stand for it.

- NEXT_STEP: the envs that ended on the previous step are reset in place of their step, in the
  same call as the others' steps.
- SAME_STEP: every env steps; those that end are reset in a second call right after, on the
  client's loop, and the pair answers as one.
- DISABLED: every env steps (what an env that ended does is the client's ``ended_envs``).

An autoreset is a gym task's own ``reset()`` (no seed, as gymnasium's vector envs do), or a
robot task's reset to a state id drawn from the env's own generator.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium.vector.vector_env import AutoresetMode

from vecsim.client.calls import PendingCall, StageBatch, StepActions
from vecsim.client.errors import PodUnavailableError, RoutingChangedError, call_error
from vecsim.client.stage import StageClient
from vecsim.client.vector_resets import StateDraws

__all__ = ["Autoresets"]


class Autoresets:
    """Sends a vector env's steps with the resets its ``mode`` asks for. ``keys[i]`` is env ``i``'s
    traj_key; ``native``: every env is a gym task reset by seed; ``draws``: the robot tasks'
    state ids."""

    def __init__(
        self, client: StageClient, keys: list[str], draws: StateDraws, native: bool, mode: AutoresetMode
    ) -> None:
        self.client, self.keys, self.draws, self.native, self.mode = client, keys, draws, native, mode
        self._key_index = {key: i for i, key in enumerate(keys)}

    def step(
        self, actions: np.ndarray, envs: np.ndarray, ended: np.ndarray
    ) -> PendingCall[tuple[StageBatch, StageBatch]]:
        """Send the step of the envs ``envs`` marks (``actions``: a row per env of the vector env)
        and the autoresets of the envs ``ended`` marks; the call's answer is ``(reset_batch,
        step_batch)``."""
        resetting = ended if self.mode == AutoresetMode.NEXT_STEP else np.zeros_like(ended)
        stepped = np.flatnonzero(envs & ~resetting)
        step = self.client.step_actions([self.keys[i] for i in stepped], actions[stepped])
        if self.mode == AutoresetMode.SAME_STEP:
            return self.client.submit(self._step_then_reset(step))
        return self.client.call(step=step, **self.requests(np.flatnonzero(resetting)))

    def requests(self, envs: Any) -> dict[str, Any]:
        """The ``client.call`` arguments that autoreset ``envs``."""
        if self.native:
            return {"seeds": {self.keys[i]: None for i in envs}} if len(envs) else {}
        return {"reset": {self.keys[i]: self.draws.draw(i) for i in envs}}

    async def _step_then_reset(self, step: StepActions) -> tuple[StageBatch, StageBatch]:
        # A pod failing either call fails only its envs: the answered envs that ended are reset
        # all the same, and one error names every env left without an answer.
        errors: list[BaseException] = []

        async def answered(pick: int, **work: Any) -> StageBatch:
            """Item ``pick`` of the call's answer; after a lone failure, its answered rows."""
            try:
                return (await self.client.call(**work))[pick]
            except (PodUnavailableError, RoutingChangedError) as error:
                if error.answered is None:
                    raise
                errors.append(error)
                return error.answered[pick]

        stepped = await answered(1, step=step)
        raised = {key for key, _, _ in stepped.errors}  # to be reset by the caller, not here
        ended = [
            self._key_index[key] for key, end in zip(stepped.traj_keys, stepped.ended()) if end and key not in raised
        ]
        again = await answered(0, **self.requests(ended))
        if errors:
            raise call_error(errors, (again, stepped))
        return again, stepped
