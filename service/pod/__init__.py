"""One sim pod: task-grouped MuJoCo envs behind FastAPI, registered with the controller.

``create_app(settings)`` builds the FastAPI app; ``vecsim pod`` (``main.py``) serves it.
"""

from __future__ import annotations

from .app import create_app
from .settings import PodSettings

__all__ = ["PodSettings", "create_app"]
