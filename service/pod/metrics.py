"""The pod's Prometheus metrics, in a registry of their own so that several apps can live in one
process (tests, the local runner) without clashing in the global registry. docs/kubernetes.md
lists them."""

from __future__ import annotations

import os
import threading
from collections.abc import Iterable

import numpy as np
from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram

from ..metrics import refused_requests


class PodMetrics:
    """Counters, gauges and the step latency histogram of one pod app."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry(auto_describe=True)
        self.env_steps = Counter(
            "vecsim_pod_env_steps",
            "Env steps simulated (one per action applied to an env).",
            registry=self.registry,
        )
        self.env_resets = Counter(
            "vecsim_pod_env_resets",
            "Env resets done (one per env per reset request).",
            registry=self.registry,
        )
        self.step_seconds = Histogram(
            "vecsim_pod_step_seconds",
            "Time one step request spends in the simulation worker.",
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
        self.gpu_turn_wait_seconds = Counter(
            "vecsim_pod_gpu_turn_wait_seconds",
            "Seconds of step requests spent waiting for this pod's turn at a GPU that other pods share "
            "(mjwarp; VECSIM_MJWARP_TURNS).",
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
        self.cpus = Gauge(
            "vecsim_pod_cpus",
            "CPUs this pod and its env workers may run on (its CPU affinity; a local job's share).",
            registry=self.registry,
        )
        self.cpus.set_function(lambda: len(os.sched_getaffinity(0)))
        self.refused = refused_requests(self.registry, "pod")
        # Waiting work, both ways: envs waiting for a trajectory, calls waiting for the sim thread.
        self._num_envs = 0
        self._in_episode: set[int] = set()
        self.idle_envs = Gauge(
            "vecsim_pod_idle_envs",
            "Envs with no episode in progress: not reset since they were built, or ended (terminated "
            "or truncated) since their last reset.",
            registry=self.registry,
        )
        self.idle_envs.set_function(lambda: self._num_envs - len(self._in_episode))
        self.queued_calls = Gauge(
            "vecsim_pod_queued_calls",
            "Calls (reset, step, builds) waiting for the pod's simulation thread, not yet started.",
            registry=self.registry,
        )

    def serving(self, num_envs: int) -> None:
        """The pod serves ``num_envs`` newly built envs, none of them in an episode."""
        self._num_envs = num_envs
        self._in_episode = set()
        self.envs.set(num_envs)
        self.ready.set(1)

    def episodes_started(self, env_indices: Iterable[int]) -> None:
        """``env_indices`` were reset: each is in an episode."""
        self._in_episode = self._in_episode | {int(i) for i in env_indices}

    def episodes_ended(self, env_indices: np.ndarray, terminated: np.ndarray, truncated: np.ndarray) -> None:
        """A step of ``env_indices`` answered these flags (``[n]``, or ``[n, K]`` for a chunk): the
        envs with any flag set are out of their episode."""
        n = len(env_indices)
        if n == 0:
            return
        ended = np.asarray(terminated, bool).reshape(n, -1).any(1) | np.asarray(truncated, bool).reshape(n, -1).any(1)
        if ended.any():  # most steps end no episode: no new set then
            self._in_episode = self._in_episode - set(np.asarray(env_indices)[ended].tolist())

    def queued(self) -> QueuedCall:
        """A call now counted in :attr:`queued_calls`, until its :meth:`QueuedCall.started`."""
        return QueuedCall(self.queued_calls)


class QueuedCall:
    """One call counted in a gauge of queued calls. :meth:`started` uncounts it, once: called when
    it starts, and again from a ``finally`` for a call cancelled before it ran."""

    def __init__(self, gauge: Gauge) -> None:
        self._gauge = gauge
        self._counted = True
        self._lock = threading.Lock()
        gauge.inc()

    def started(self) -> None:
        with self._lock:
            if self._counted:
                self._counted = False
                self._gauge.dec()
