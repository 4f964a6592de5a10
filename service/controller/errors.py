"""What the controller refuses, as :class:`service.errors.RefusedError` classes (answered as every
vecsim server answers a refusal: :mod:`service.errors`), counted in
``vecsim_controller_refused_requests``."""

from __future__ import annotations

from service.errors import RefusedError

__all__ = ["JobRejectedError", "NoJobError", "NoPlanError", "PodUrlConflictError", "UnknownPodError"]


class UnknownPodError(RefusedError):
    """A heartbeat from a pod that is not registered (it should register again)."""

    status_code = 404
    reason = "unknown_pod"


class PodUrlConflictError(RefusedError):
    """A heartbeat names another URL than the one its pod registered at.

    Pods are addressed by stable names (a StatefulSet's DNS names), so a live pod's URL does not
    change; a heartbeat that says otherwise is refused, and the pod keeps its registered URL. A
    pod that really moved registers again (``POST /v1/pods``), which counts as a restart.
    """

    status_code = 409
    reason = "url_conflict"


class NoJobError(RefusedError):
    """The controller has no job yet."""

    status_code = 404
    reason = "no_job"


class NoPlanError(RefusedError):
    """The controller has a job but no plan yet (it waits for pods to report)."""

    status_code = 503
    reason = "no_plan"


class JobRejectedError(RefusedError):
    """A job that cannot run; the answer lists each problem on its own (``problems``)."""

    status_code = 422
    reason = "job_rejected"

    def __init__(self, job_id: str, problems: list[str]) -> None:
        super().__init__(f"job {job_id!r} rejected: " + "; ".join(problems), problems=problems)
