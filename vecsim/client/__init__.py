"""The trainer side of vecsim: a per-stage async client and a gymnasium ``VectorEnv`` over pods.

- :class:`StageClient`: places trajectories on pod envs (``reset_trajectories``) and resets or
  steps them one pipeline stage at a time (``reset_stage``/``step_stage``), all pods of a stage
  concurrently.
- :class:`HTTPVectorEnv`: every env of a job as one ``gymnasium.vector.VectorEnv``; registered as
  ``vecsim/HTTPVectorEnv-v0``, so ``gymnasium.make_vec("vecsim/HTTPVectorEnv-v0", num_envs=n,
  controller_url=...)`` builds one of the job's first n envs (``num_envs=None``: all of them)
  once this module is imported (or name the module in the id:
  ``"vecsim.client:vecsim/HTTPVectorEnv-v0"``). ``chunk_step`` takes chunks of K actions per env.
- :class:`VLAEnv`: a job with the ``reset(env_ids, state_ids)`` / ``chunk_step`` contract of
  VLA-RL trainers, observations under vecsim's or LeRobot's key names.
"""

from __future__ import annotations

import gymnasium

from vecsim.client.errors import (
    CapacityError,
    ClientError,
    PodRequestError,
    PodUnavailableError,
    RoutingChangedError,
    StaleGenerationError,
)
from vecsim.client.routing import RoutedEnv, TrajRoute, place_requests, routed_envs
from vecsim.client.stage import PendingCall, StageBatch, StageClient, StepActions, fetch_routing
from vecsim.client.vector_env import HTTPVectorEnv
from vecsim.client.vla_env import VLAEnv

__all__ = [
    "CapacityError",
    "ClientError",
    "HTTPVectorEnv",
    "PendingCall",
    "PodRequestError",
    "PodUnavailableError",
    "RoutedEnv",
    "RoutingChangedError",
    "StageBatch",
    "StageClient",
    "StaleGenerationError",
    "StepActions",
    "TrajRoute",
    "VLAEnv",
    "fetch_routing",
    "place_requests",
    "routed_envs",
]

ENV_ID = "vecsim/HTTPVectorEnv-v0"

if ENV_ID not in gymnasium.registry:
    # No num_envs in the spec's kwargs: make_vec would let it override the caller's num_envs.
    # make_vec passes its own default (1) when the caller gives none; num_envs=None takes the
    # whole job.
    gymnasium.register(id=ENV_ID, vector_entry_point="vecsim.client.vector_env:HTTPVectorEnv")
