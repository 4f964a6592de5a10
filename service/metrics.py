"""What both servers count alike: requests answered with an error, by reason, under one name
(``vecsim_<server>_refused_requests{reason}``) so one alert rule reads either; and the one way
both answer such a request (:func:`refusal`)."""

from __future__ import annotations

from fastapi.responses import JSONResponse
from prometheus_client import CollectorRegistry, Counter


def refused_requests(registry: CollectorRegistry, server: str) -> Counter:
    """The counter of ``server``'s (``"pod"``, ``"controller"``) requests answered with an
    error, labelled ``reason`` (``unauthorized``, ``body_too_large``, ``stale_generation``, ...)."""
    return Counter(
        f"vecsim_{server}_refused_requests",
        "Requests answered with an error (refused, or failed as sim_crashed), by reason.",
        ["reason"],
        registry=registry,
    )


def refusal(refused: Counter, status: int, reason: str, detail: str, **extra: object) -> JSONResponse:
    """The answer to a request refused (or failed) with ``status``: ``{"detail": detail}`` plus
    ``extra`` (docs/api.md), counted in ``refused`` under ``reason``."""
    refused.labels(reason=reason).inc()
    return JSONResponse({"detail": detail, **extra}, status_code=status)
