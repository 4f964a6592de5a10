"""The controller: pod registry, the job's plan, a reconcile loop pushing assignments, routing.

``create_app(settings)`` builds the FastAPI app; ``vecsim controller`` (``main.py``) serves it.
"""

from __future__ import annotations

from .app import create_app
from .settings import ControllerSettings

__all__ = ["ControllerSettings", "create_app"]
