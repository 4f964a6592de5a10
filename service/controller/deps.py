"""FastAPI dependencies: the controller's state lives on ``app.state``, never in module globals,
so that several controller apps can live in one process (tests do)."""

from __future__ import annotations

from fastapi import Request

from .state import ControllerState


def get_state(request: Request) -> ControllerState:
    """Returns the controller's registry, job and plan."""
    return request.app.state.controller
