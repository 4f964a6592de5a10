"""Probe paths and thresholds of the pod and the controller, defined once.

The Kubernetes manifests (k8s/) and the local runner (``vecsim up``) both follow these values,
so a process is started, declared ready, and restarted the same way on a laptop and in a
cluster. Semantics are Kubernetes': a probe succeeds on an HTTP status in 200..399; the startup
probe runs first and the others only after it succeeded; ``failure_threshold`` consecutive
failures of the startup or liveness probe restart the container; the readiness probe only marks
it ready or not.

Probe requests come every few seconds; :func:`quiet_probe_logs` logs them at DEBUG, not INFO, in
the request logs of the processes that serve or make them.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from urllib.parse import urlsplit


@dataclass(frozen=True)
class Probe:
    """One HTTP GET probe, with Kubernetes' field meanings."""

    path: str
    period_s: float
    failure_threshold: int
    timeout_s: float = 5.0
    initial_delay_s: float = 0.0

    @property
    def budget_s(self) -> float:
        """Returns how long the probe may keep failing before it counts as failed."""
        return self.initial_delay_s + self.period_s * self.failure_threshold


@dataclass(frozen=True)
class Probes:
    startup: Probe
    readiness: Probe
    liveness: Probe


# A pod is ready once its envs are built; LIBERO builds take minutes on CPU, so the startup
# probe allows 10 minutes before a restart.
POD = Probes(
    startup=Probe("/readyz", period_s=5, failure_threshold=120),
    readiness=Probe("/readyz", period_s=5, failure_threshold=3),
    liveness=Probe("/healthz", period_s=10, failure_threshold=3),
)

# The controller's /readyz says whether the *job* is ready, which depends on the pods; gating
# the controller's own Service on it would keep pods from registering. Its probes use /healthz.
CONTROLLER = Probes(
    startup=Probe("/healthz", period_s=1, failure_threshold=60, timeout_s=2),
    readiness=Probe("/healthz", period_s=5, failure_threshold=3),
    liveness=Probe("/healthz", period_s=10, failure_threshold=3),
)

# Seconds between SIGTERM and SIGKILL when a process is stopped (terminationGracePeriodSeconds).
TERMINATION_GRACE_S = 30

# Every path a probe of the pod or the controller requests.
PROBE_PATHS = frozenset(
    probe.path for probes in (POD, CONTROLLER) for probe in (probes.startup, probes.readiness, probes.liveness)
)
# The loggers that write a line per request: uvicorn's access log (a server's) and httpx's (a
# client's, such as the runner probing its processes).
REQUEST_LOGGERS = ("uvicorn.access", "httpx")


def _request_path(value: object) -> str | None:
    """The path of a logged request's path or URL argument (``/readyz?x=1``,
    ``http://host:port/readyz``), or None for an argument that is neither."""
    text = str(value)
    if text.startswith("/"):
        return text.split("?", 1)[0]
    if "://" in text:
        return urlsplit(text).path
    return None


class ProbeLogFilter(logging.Filter):
    """Moves the INFO line a request to a probe path logs down to DEBUG.

    A probe every few seconds from the runner or the kubelet would bury the requests that matter;
    at ``--log-level debug`` they still show. Any other line passes as it is.
    """

    def __init__(self, paths: frozenset[str] = PROBE_PATHS) -> None:
        super().__init__()
        self.paths = paths

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno != logging.INFO or not isinstance(record.args, tuple):
            return True
        if not any(_request_path(arg) in self.paths for arg in record.args):
            return True
        record.levelno, record.levelname = logging.DEBUG, logging.getLevelName(logging.DEBUG)
        return logging.getLogger(record.name).isEnabledFor(logging.DEBUG)


def quiet_probe_logs(paths: frozenset[str] = PROBE_PATHS) -> None:
    """Log the requests to ``paths`` (the probes') at DEBUG in every request logger of this
    process (see :class:`ProbeLogFilter`); idempotent."""
    for name in REQUEST_LOGGERS:
        logger = logging.getLogger(name)
        if not any(isinstance(f, ProbeLogFilter) for f in logger.filters):
            logger.addFilter(ProbeLogFilter(paths))
