"""Probe paths and thresholds of the pod and the controller, defined once.

The Kubernetes manifests (k8s/) and the local runner (``vecsim up``) both follow these values,
so a process is started, declared ready, and restarted the same way on a laptop and in a
cluster. Semantics are Kubernetes': a probe succeeds on an HTTP status in 200..399; the startup
probe runs first and the others only after it succeeded; ``failure_threshold`` consecutive
failures of the startup or liveness probe restart the container; the readiness probe only marks
it ready or not.
"""

from __future__ import annotations

from dataclasses import dataclass


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
