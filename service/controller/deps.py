"""FastAPI dependencies: the controller's state lives on ``app.state``, never in module globals,
so that several controller apps can live in one process (tests do). ``async``, because FastAPI
runs a plain ``def`` dependency on a thread pool: a thread hop on every heartbeat."""

from __future__ import annotations

from fastapi import Request

from .state import ControllerState


async def get_state(request: Request) -> ControllerState:
    """Returns the controller's registry, job and plan."""
    return request.app.state.controller
