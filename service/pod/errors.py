"""The pod's HTTP errors: one exception type carrying status, kind and a detail for the caller.

Every error answer is JSON ``{"detail": "<what is wrong>"}``; ``kind`` labels the errors metric.
"""

from __future__ import annotations


class PodError(Exception):
    """A request the pod refuses; ``detail`` names the field, env or pod at fault."""

    status_code = 400
    kind = "bad_request"

    def __init__(self, detail: str) -> None:
        super().__init__(detail)
        self.detail = detail


class MalformedBodyError(PodError):
    status_code = 400
    kind = "malformed_body"


class UnknownEnvError(PodError):
    status_code = 404
    kind = "unknown_env"


class GenerationConflictError(PodError):
    status_code = 409
    kind = "generation_mismatch"


class UnsupportedMediaTypeError(PodError):
    status_code = 415
    kind = "unsupported_media_type"


class InvalidRequestError(PodError):
    status_code = 422
    kind = "invalid_request"


class NotReadyError(PodError):
    status_code = 503
    kind = "not_ready"


class SimCrashedError(PodError):
    status_code = 503
    kind = "sim_crashed"
