"""The local job runner: the controller and N pods as processes, StatefulSet-style.

``LocalJob(config)`` is the library entry point; ``vecsim up -c configs/<job>.yaml`` (``main.py``)
the command.
"""

from __future__ import annotations

from .job import CrashLoopError, JobRejectedError, LocalJob
from .process import Backoff, ManagedProcess
from .status import PodStatus, format_status

__all__ = ["Backoff", "CrashLoopError", "JobRejectedError", "LocalJob", "ManagedProcess", "PodStatus", "format_status"]
