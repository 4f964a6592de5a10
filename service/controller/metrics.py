"""The controller's Prometheus metrics, in a registry of its own (one per app)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

from prometheus_client import CollectorRegistry, Counter, Histogram
from prometheus_client.core import GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

from ..metrics import refused_requests


@dataclass(frozen=True)
class Gauges:
    """Values read from the controller's state at scrape time."""

    pods: int
    ready_pods: int
    generation: int
    unfilled_slots: int
    job_ready: bool
    # Stage id -> slots of that stage whose pod is registered and ready (in the ``slices``
    # layout every slot serves every stage).
    stage_ready_pods: dict[int, int] = field(default_factory=dict)


class _StateCollector(Collector):
    def __init__(self, read: Callable[[], Gauges]) -> None:
        self._read = read

    def collect(self) -> Iterator[Metric]:
        g = self._read()
        yield GaugeMetricFamily("vecsim_controller_pods", "Registered pods (heard from within the TTL).", value=g.pods)
        yield GaugeMetricFamily(
            "vecsim_controller_ready_pods", "Registered pods that report ready.", value=g.ready_pods
        )
        yield GaugeMetricFamily(
            "vecsim_controller_generation", "Generation of the current plan (0: none).", value=g.generation
        )
        yield GaugeMetricFamily(
            "vecsim_controller_unfilled_slots", "Slots of the plan without a pod.", value=g.unfilled_slots
        )
        yield GaugeMetricFamily(
            "vecsim_controller_job_ready", "1 when every slot's pod runs the plan and is ready.", value=int(g.job_ready)
        )
        stages = GaugeMetricFamily(
            "vecsim_controller_stage_ready_pods",
            "Pods of the plan serving a stage that are registered and ready, by stage.",
            labels=["stage"],
        )
        for stage, count in sorted(g.stage_ready_pods.items()):
            stages.add_metric([str(stage)], count)
        yield stages


class ControllerMetrics:
    """Counters and histograms the controller updates, plus gauges read from its state."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        self.heartbeats = Counter("vecsim_controller_heartbeats", "Heartbeats received.", registry=self.registry)
        self.url_conflicts = Counter(
            "vecsim_controller_heartbeat_url_conflicts",
            "Heartbeats refused for naming another URL than their pod registered at.",
            registry=self.registry,
        )
        self.registrations = Counter(
            "vecsim_controller_registrations", "Pod registrations received.", registry=self.registry
        )
        self.expired = Counter(
            "vecsim_controller_pods_expired", "Pods dropped for missing heartbeats.", registry=self.registry
        )
        self.stalls = Counter(
            "vecsim_controller_stalls",
            "Stalls of the controller's own event loop (gaps over its stall threshold).",
            registry=self.registry,
        )
        self.stalled_seconds = Counter(
            "vecsim_controller_stalled_seconds",
            "Time the controller's event loop stalled; not counted against pods' heartbeat TTL.",
            registry=self.registry,
        )
        self.pushes = Counter(
            "vecsim_controller_pushes", "Assignment pushes by result.", ["result"], registry=self.registry
        )
        self.refused = refused_requests(self.registry, "controller")
        self.reconcile_seconds = Histogram(
            "vecsim_controller_reconcile_seconds",
            "Duration of one reconcile pass, pushes included.",
            buckets=(0.001, 0.005, 0.01, 0.05, 0.1, 0.5, 1.0, 5.0, 10.0),
            registry=self.registry,
        )

    def watch(self, read: Callable[[], Gauges]) -> None:
        """Reports the gauges ``read`` returns at every scrape."""
        self.registry.register(_StateCollector(read))
