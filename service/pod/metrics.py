"""The pod's Prometheus metrics, in a registry of their own so that several apps can live in one
process (tests, the local runner) without clashing in the global registry."""

from __future__ import annotations

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram

from ..metrics import refused_requests


class PodMetrics:
    """Counters, gauges and the step latency histogram of one pod app."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry(auto_describe=True)
        self.env_steps = Counter(
            "vecsim_pod_env_steps", "Env steps simulated (one per action applied to an env).",
            registry=self.registry,
        )
        self.env_resets = Counter(
            "vecsim_pod_env_resets", "Env resets done (one per env per reset request).",
            registry=self.registry,
        )
        self.step_seconds = Histogram(
            "vecsim_pod_step_seconds", "Time one step request spends in the simulation worker.",
            buckets=(0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0),
            registry=self.registry,
        )
        self.physics_seconds = Counter(
            "vecsim_pod_physics_seconds",
            "Worker seconds of step requests spent in physics, summed over the pod's workers.",
            registry=self.registry,
        )
        self.render_seconds = Counter(
            "vecsim_pod_render_seconds",
            "Worker seconds of step requests spent rendering cameras, summed over the pod's workers.",
            registry=self.registry,
        )
        self.env_renders = Counter(
            "vecsim_pod_env_renders",
            "Env renders of step requests (all of one env's cameras drawn once): one per env per "
            "request, plus one per recorded frame.",
            registry=self.registry,
        )
        self.idempotency_key_repeats = Counter(
            "vecsim_pod_idempotency_key_repeats",
            "Resets and steps answered from memory: a repeated Idempotency-Key, nothing applied again.",
            registry=self.registry,
        )
        self.idempotency_key_answers = Gauge(
            "vecsim_pod_idempotency_key_answers",
            "Answers held for repeats of an Idempotency-Key (at most one per env).",
            registry=self.registry,
        )
        self.envs = Gauge("vecsim_pod_envs", "Envs this pod runs now.", registry=self.registry)
        self.ready = Gauge("vecsim_pod_ready", "1 when the envs are built and serving.", registry=self.registry)
        self.refused = refused_requests(self.registry, "pod")
