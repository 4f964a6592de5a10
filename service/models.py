"""The bodies both servers (pod and controller) answer alike: liveness, readiness and the
one-line refusal. Each server's own bodies are in ``service.pod.models`` and
``service.controller.models``."""

from __future__ import annotations

from pydantic import BaseModel, Field


class Problem(BaseModel):
    """Every refusal and failure: one line naming what is wrong (docs/api.md)."""

    detail: str


class Health(BaseModel):
    """``GET /healthz``: the process answers."""

    status: str


class Readiness(BaseModel):
    """``GET /readyz`` when ready: the generation served, and (a pod) how many envs it runs."""

    status: str
    generation: int | None
    num_envs: int | None = Field(None, description="a pod's envs; absent for the controller")
