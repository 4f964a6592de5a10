"""Pydantic models of the controller's requests and responses (beside those in vecsim.config;
the heartbeat, which the pod sends, is in :mod:`service.contract`; the bodies both servers
answer alike, in :mod:`service.models`)."""

from __future__ import annotations

from pydantic import Field

from ..models import Problem


class JobProblems(Problem):
    """``PUT /v1/job``'s 422: the one-line refusal, and each problem on its own."""

    problems: list[str] = Field(description="each thing to change for the job to be accepted")
