"""The pod engine: what a sim pod runs (the ``pod`` install extra). The trainer's client never
imports this package (tests/docs/test_layering.py).

- ``vector_env``: :class:`TaskGroupedVectorEnv`, a pod's envs stepped and reset by env index;
- ``checks``: what a call must satisfy before any worker is touched;
- ``pool``, ``worker``, ``protocol``: the worker processes, what runs in each, and the messages
  between them and the pod;
- ``errors``: what the engine raises (the pod answers them as they are);
- ``tasks``: the task registry and its envs; ``render``, ``batch_render``, ``mesh_lod``: drawing
  the envs' cameras.
"""

from vecsim.engine.checks import assignment_spaces
from vecsim.engine.errors import EnvError, InvalidRequestError, SimBuildError, SimCrashedError, UnknownEnvError
from vecsim.engine.pool import auto_envs_per_worker, available_cores, resolve_envs_per_worker
from vecsim.engine.vector_env import CallTiming, ChunkResult, TaskGroupedVectorEnv
from vecsim.engine.worker import DEFAULT_MAX_CHUNK

__all__ = [
    "DEFAULT_MAX_CHUNK",
    "CallTiming",
    "ChunkResult",
    "EnvError",
    "InvalidRequestError",
    "SimBuildError",
    "SimCrashedError",
    "TaskGroupedVectorEnv",
    "UnknownEnvError",
    "assignment_spaces",
    "auto_envs_per_worker",
    "available_cores",
    "resolve_envs_per_worker",
]
