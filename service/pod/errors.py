"""What the pod refuses, as :class:`service.errors.RefusedError` classes (answered as every
vecsim server answers a refusal: :mod:`service.errors`), counted in ``vecsim_pod_refused_requests``.

The library's own errors are answered as they are (one class per concept, defined once in
:mod:`vecsim.engine.errors`): ``UnknownEnvError`` 404, ``InvalidRequestError`` 422, ``SimCrashedError`` 503
(:data:`LIBRARY_ERRORS`). The classes here are for what only the HTTP layer knows: a body it
cannot read, a media type it does not speak, a stale generation, a pod not ready.
"""

from __future__ import annotations

from service.errors import RefusedError
from vecsim.engine import InvalidRequestError, SimCrashedError, UnknownEnvError

__all__ = [
    "LIBRARY_ERRORS",
    "MalformedBodyError",
    "NotReadyError",
    "StaleGenerationError",
    "UnsupportedMediaTypeError",
]


class MalformedBodyError(RefusedError):
    status_code = 400
    reason = "malformed_body"


class StaleGenerationError(RefusedError):
    """The request's generation is not the pod's (the client re-reads the routing table)."""

    status_code = 409
    reason = "stale_generation"


class UnsupportedMediaTypeError(RefusedError):
    status_code = 415
    reason = "unsupported_media_type"


class NotReadyError(RefusedError):
    status_code = 503
    reason = "not_ready"


# The library's errors the pod answers with, by class: (status, metric reason).
LIBRARY_ERRORS: dict[type[Exception], tuple[int, str]] = {
    UnknownEnvError: (404, "unknown_env"),
    InvalidRequestError: (422, "invalid_request"),
    SimCrashedError: (503, "sim_crashed"),
}
