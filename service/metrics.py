"""What both servers count alike: requests answered with an error, by reason, under one name
(``vecsim_<server>_refused_requests{reason}``) so one alert rule reads either."""

from __future__ import annotations

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
