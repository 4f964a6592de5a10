"""The pod engine: what a sim pod runs (the ``pod`` install extra). The trainer's client never
imports this package (tests/docs/test_layering.py).

- ``base``: the engine seam: :class:`PodEngine`, what a pod asks of an engine, and
  :func:`engine_kind`, which builds the one a job names (``cpu`` or ``mjwarp``); the pod
  imports no concrete engine itself (tests/docs/test_engine_seam.py);
- ``cpu``, ``vector_env``: the CPU engine, :class:`TaskGroupedVectorEnv`, a pod's envs stepped
  and reset by env index in worker processes;
- ``mjwarp``: the MuJoCo Warp engine (docs/mjwarp.md);
- ``checks``: what a call must satisfy before any worker is touched;
- ``answers``: a call's answer, row by row, from what the workers left;
- ``supervisor``, ``pool``, ``worker``, ``protocol``: the workers' life (built, spoken to one call
  at a time, watched), their processes, what runs in each, and the messages between them and the pod;
- ``errors``: what the engines raise (the pod answers them as they are);
- ``tasks``: the task registry and its envs; ``render``, ``batch_render``, ``mesh_lod``: drawing
  the envs' cameras.

Names are imported on first use, so ``from vecsim.engine import InvalidRequestError`` loads
no engine's packages.
"""

from __future__ import annotations

import importlib
from typing import Any

# Public name -> the module that defines it.
_WHERE = {
    "DEFAULT_MAX_CHUNK": "vecsim.engine.base",
    "CallTiming": "vecsim.engine.base",
    "ChunkResult": "vecsim.engine.base",
    "PodEngine": "vecsim.engine.base",
    "engine_kind": "vecsim.engine.base",
    "EnvError": "vecsim.engine.errors",
    "InvalidRequestError": "vecsim.engine.errors",
    "SimBuildError": "vecsim.engine.errors",
    "SimCrashedError": "vecsim.engine.errors",
    "SpacesDifferError": "vecsim.engine.errors",
    "UnknownEnvError": "vecsim.engine.errors",
    "TaskGroupedVectorEnv": "vecsim.engine.vector_env",
    "assignment_spaces": "vecsim.engine.checks",
    "auto_envs_per_worker": "vecsim.engine.pool",
    "available_cores": "vecsim.engine.pool",
    "resolve_envs_per_worker": "vecsim.engine.pool",
}

__all__ = sorted(_WHERE)


def __getattr__(name: str) -> Any:
    module = _WHERE.get(name)
    if module is None:
        raise AttributeError(f"module 'vecsim.engine' has no attribute {name!r}")
    return getattr(importlib.import_module(module), name)
