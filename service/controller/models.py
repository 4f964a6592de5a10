"""Pydantic models of the controller's requests and responses (beside those in vecsim.config;
the heartbeat, which the pod sends, is in :mod:`service.contract`)."""

from __future__ import annotations

from pydantic import BaseModel, Field


class JobProblems(BaseModel):
    detail: str
    problems: list[str] = Field(description="each thing to change for the job to be accepted")

