"""How the pod answers what it refuses: JSON ``{"detail": "<what is wrong>"}`` with a status, and
a ``reason`` that labels ``vecsim_pod_refused_requests``.

The library's own errors are answered as they are (one class per concept, defined once in
:mod:`vecsim.engine.errors`): ``UnknownEnvError`` 404, ``InvalidRequestError`` 422, ``SimCrashedError`` 503
(:data:`LIBRARY_ERRORS`). The classes here are for what only the HTTP layer knows: a body it
cannot read, a media type it does not speak, a stale generation, a pod not ready.
"""

from __future__ import annotations

from vecsim.engine import InvalidRequestError, SimCrashedError, UnknownEnvError

__all__ = [
    "LIBRARY_ERRORS",
    "MalformedBodyError",
    "NotReadyError",
    "PodError",
    "StaleGenerationError",
    "UnsupportedMediaTypeError",
]


class PodError(Exception):
    """A request the pod refuses; ``detail`` names the field, env or pod at fault."""

    status_code = 400
    reason = "bad_request"

    def __init__(self, detail: str) -> None:
        super().__init__(detail)
        self.detail = detail


class MalformedBodyError(PodError):
    status_code = 400
    reason = "malformed_body"


class StaleGenerationError(PodError):
    """The request's generation is not the pod's (the client re-reads the routing table)."""

    status_code = 409
    reason = "stale_generation"


class UnsupportedMediaTypeError(PodError):
    status_code = 415
    reason = "unsupported_media_type"


class NotReadyError(PodError):
    status_code = 503
    reason = "not_ready"


# The library's errors the pod answers with, by class: (status, metric reason).
LIBRARY_ERRORS: dict[type[Exception], tuple[int, str]] = {
    UnknownEnvError: (404, "unknown_env"),
    InvalidRequestError: (422, "invalid_request"),
    SimCrashedError: (503, "sim_crashed"),
}
