"""What the pod and the controller say to each other (beside the assignment, which lives in
:mod:`vecsim.config` because trainers read it too): one definition both servers import."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

from vecsim.config import Assignment


class Heartbeat(BaseModel):
    """``POST /v1/pods/{pod}/heartbeat``: what the pod runs now."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    url: str = Field(description="the URL the pod is reached at")
    generation: int | None = Field(None, description="generation of the assignment it runs (null: none)")
    assignment: Assignment | None = Field(None, description="the assignment it runs (null: none yet)")
    ready: bool = Field(False, description="its envs are built and it answers data-plane requests")


class HeartbeatAnswer(BaseModel):
    generation: int | None = Field(description="the generation of the controller's plan (null: no plan yet)")
