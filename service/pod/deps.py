"""FastAPI dependencies handing routes the pod's shared state (kept on ``app.state``, never in
module globals, so that several pod apps can live in one process). They are ``async`` because
FastAPI runs a plain ``def`` dependency on a thread pool: a thread hop on every reset and step."""

from __future__ import annotations

from fastapi import Request

from .state import PodState


async def get_state(request: Request) -> PodState:
    """The pod's state: assignment, envs and worker thread."""
    return request.app.state.pod
