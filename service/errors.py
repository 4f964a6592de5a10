"""How both servers refuse a request: a route raises a :class:`RefusedError` subclass, and one
handler (:func:`answer_refusal`, wired by :func:`service.app.server_app`) turns it into the wire's
refusal, JSON ``{"detail": "<what is wrong>", ...}`` with the class's status, counted in
``vecsim_<server>_refused_requests`` under the class's ``reason`` (docs/api.md).

Each server keeps its own classes beside its routes (``service.pod.errors``,
``service.controller.errors``); what both refuse alike lives here.
"""

from __future__ import annotations

import logging

from fastapi import Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse

from .http import describe_validation_error
from .metrics import refusal

__all__ = ["InvalidFieldError", "RefusedError", "answer_library_error", "answer_refusal", "answer_validation_error"]

log = logging.getLogger(__name__)


class RefusedError(Exception):
    """A request a server refuses; ``detail`` names the field, env or pod at fault, and ``extra``
    holds further members of the answer's JSON (a rejected job's ``problems``)."""

    status_code = 400
    reason = "bad_request"

    def __init__(self, detail: str, **extra: object) -> None:
        super().__init__(detail)
        self.detail = detail
        self.extra = extra


class InvalidFieldError(RefusedError):
    """A body that parses but whose fields cannot be served as given."""

    status_code = 422
    reason = "invalid_request"


async def answer_refusal(request: Request, exc: RefusedError) -> JSONResponse:
    """The wire's answer to ``exc``, counted in the app's ``refused_requests`` counter."""
    log.debug("%s %s -> %d: %s", request.method, request.url.path, exc.status_code, exc.detail)
    return refusal(request.app.state.refused_requests, exc.status_code, exc.reason, exc.detail, **exc.extra)


async def answer_validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
    """A body or parameter FastAPI could not validate: 422 naming each field at fault."""
    return await answer_refusal(request, InvalidFieldError(describe_validation_error(exc)))


async def answer_library_error(request: Request, exc: Exception) -> JSONResponse:
    """One of the library's own errors, answered with the (status, reason) the app's
    ``library_errors`` table gives its class."""
    status, reason = next(a for cls, a in request.app.state.library_errors.items() if isinstance(exc, cls))
    log.debug("%s %s -> %d: %s", request.method, request.url.path, status, exc)
    return refusal(request.app.state.refused_requests, status, reason, str(exc))
