"""Measuring rollouts against a job: a stage client that times each pod's round trip, the pods'
counters scraped from ``/metrics``, the service alone and the pipelined loop, interleaved rounds.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import re
import time
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import httpx
import numpy as np
import torch
from gymnasium import spaces

from vecsim.client import StageClient
from vecsim.rollout import EnvLoop, RolloutStats
from .jobs import requests_for

log = logging.getLogger("bench.measure")


class TimedStageClient(StageClient):
    """A StageClient that records every request to a pod: ``(pod, op, begin, end)``
    (``time.perf_counter()``), the round trip as the client sees it (HTTP, the pod's work,
    decoding), so a stage call's per-pod times and its slowest pod are known. This bench's
    clients step ended envs on (``ended_envs="step"``): its service runs take a fixed number of
    one-action steps, the pods' work whether or not an episode ended."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.pod_calls: list[tuple[str, str, float, float]] = []
        self._pods.observe = lambda pod, op, begin, end: self.pod_calls.append((pod, op, begin, end))

    def take_pod_calls(self) -> list[tuple[str, str, float, float]]:
        """Return the requests recorded since the last take, and forget them."""
        calls, self.pod_calls = self.pod_calls, []
        return calls


_METRIC = re.compile(r"^(vecsim_pod_[a-z_]+?)(?:\{[^}]*\})? (\S+)$", re.M)
POD_COUNTERS = (
    "vecsim_pod_env_steps_total",
    "vecsim_pod_step_seconds_sum",
    "vecsim_pod_step_seconds_count",
    "vecsim_pod_physics_seconds_total",
    "vecsim_pod_render_seconds_total",
)


def scrape_per_pod(urls: Sequence[str]) -> dict[str, dict[str, float]]:
    """Return each pod's step counters (``POD_COUNTERS``), by URL."""
    out = {}
    for url in urls:
        totals = dict.fromkeys(POD_COUNTERS, 0.0)
        for name, value in _METRIC.findall(httpx.get(f"{url}/metrics", timeout=10).text):
            if name in totals:
                totals[name] += float(value)
        out[url] = totals
    return out


def scrape(urls: Sequence[str]) -> dict[str, float]:
    """Return the pods' step counters (``POD_COUNTERS``), summed over ``urls``."""
    per_pod = scrape_per_pod(urls)
    return {name: sum(pod[name] for pod in per_pod.values()) for name in POD_COUNTERS}


@dataclasses.dataclass
class Measured:
    """One rollout: its stats, the pods' counters over it (summed, and per pod name) and the
    client's per-pod requests."""

    stats: RolloutStats
    pods: dict[str, float]
    per_pod: dict[str, dict[str, float]] = dataclasses.field(default_factory=dict)
    pod_calls: list[tuple[str, str, float, float]] = dataclasses.field(default_factory=list)
    stage_of_pod: dict[str, int] = dataclasses.field(default_factory=dict)
    # The rollout's clock origin (``time.perf_counter()`` as ``EnvLoop.run`` was entered), by which
    # ``pod_calls`` line up with the stats' times; None where the run was not a loop.
    started: float | None = None

    @property
    def env_steps_per_s(self) -> float:
        return self.stats.env_steps_per_s


def _pod_urls(client: StageClient) -> dict[str, str]:
    return {p.pod: p.url for stage in client.routing.stages for p in stage.pods}


@contextlib.contextmanager
def counted(client: StageClient) -> Iterator[dict[str, Any]]:
    """Scrape the client's pods before and after the body; yield a dict that then holds
    ``pods`` (the counters' increase, summed), ``per_pod`` (by pod name), ``pod_calls`` (the
    client's requests, when it is a TimedStageClient) and ``stage_of_pod``."""
    urls = _pod_urls(client)
    if isinstance(client, TimedStageClient):
        client.take_pod_calls()
    before = scrape_per_pod(list(urls.values()))
    out: dict[str, Any] = {}
    yield out
    after = scrape_per_pod(list(urls.values()))
    out["per_pod"] = {pod: {k: after[url][k] - before[url][k] for k in POD_COUNTERS} for pod, url in urls.items()}
    out["pods"] = {k: sum(p[k] for p in out["per_pod"].values()) for k in POD_COUNTERS}
    out["pod_calls"] = client.take_pod_calls() if isinstance(client, TimedStageClient) else []
    out["stage_of_pod"] = {p.pod: stage.stage_id for stage in client.routing.stages for p in stage.pods}


class Chunked:
    """A policy acting in chunks of ``k`` actions: its one action per observation, repeated ``k``
    times (``[n, k, action_dim]``); ``k`` 1 is the policy itself."""

    def __init__(self, policy: Callable[..., torch.Tensor], k: int) -> None:
        self.policy, self.k = policy, k

    def __call__(self, obs: dict[str, Any], instructions: list[str], task_ids: list[str]) -> torch.Tensor:
        actions = self.policy(obs, instructions, task_ids)
        return actions if self.k == 1 else actions.unsqueeze(1).expand(-1, self.k, -1).contiguous()


def loop_rollout(
    client: StageClient,
    policy: Callable[..., torch.Tensor],
    horizon: int,
    device: str,
    batch_wait_s: float | str = 0.0,
    waves: int = 1,
) -> Measured:
    """Run one EnvLoop rollout (reset, then ``horizon`` steps of every env; with ``waves`` > 1,
    that many trajectories per env, refilled as envs free up); return its stats with the pods'
    counters and the client's per-pod requests over it.

    Raises:
        RuntimeError: trajectories were lost (a pod failed).
    """
    with counted(client) as seen:
        loop = EnvLoop(
            client, policy, horizon=horizon, device=device, keep_obs=(), log_every_s=60, batch_wait_s=batch_wait_s
        )
        started = time.perf_counter()  # EnvLoop.run takes its own a few microseconds later
        result = loop.run(requests_for(client.routing, waves))
    if result.lost:
        raise RuntimeError(f"{len(result.lost)} trajectories lost: {next(iter(result.lost.values())).reason}")
    return Measured(result.stats, **seen, started=started)


def scripted_actions(space: spaces.Box, step: int, n: int) -> np.ndarray:
    """``[n, action_dim]`` open-loop actions of step ``step``: a slow sine per dimension."""
    low, high = np.asarray(space.low, np.float32), np.asarray(space.high, np.float32)
    bounded = np.isfinite(low) & np.isfinite(high)
    center, scale = np.where(bounded, (low + high) / 2, 0.0), np.where(bounded, (high - low) / 2, 1.0)
    action = center + 0.5 * scale * np.sin(0.35 * step + 0.9 * np.arange(len(low)))
    return np.broadcast_to(action.astype(np.float32), (n, len(low)))


def scripted_chunks(space: spaces.Box, step: int, n: int, chunk: int) -> np.ndarray:
    """``scripted_actions`` of step ``step``; with ``chunk`` > 1, ``[n, chunk, action_dim]``
    (steps ``step * chunk`` onwards)."""
    if chunk == 1:
        return scripted_actions(space, step, n)
    return np.stack([scripted_actions(space, step * chunk + k, n) for k in range(chunk)], axis=1)


def service_rollout(client: StageClient, steps: int, timeout_s: float, chunk: int = 1) -> Measured:
    """The service alone, no policy: reset every env of the client's table, then ``steps`` calls
    stepping all of them with scripted actions, ``chunk`` per env and call (every stage's call
    sent at once, then all awaited). Env-steps/s count the steps' time only; the stats' timeline
    holds every call.

    Raises:
        TimeoutError: a call took longer than ``timeout_s``.
    """
    routes = client.reset_trajectories(requests_for(client.routing))
    stages = [s for s in range(client.num_stages) if client.stage_traj_keys(s)]
    action_space = client.action_space
    timeline: list[tuple[str, int, float, float]] = []
    with counted(client) as seen:
        started = time.perf_counter()
        for stage, batch in zip(stages, [c.result(timeout_s) for c in [client.reset_stage(s) for s in stages]]):
            timeline.append(("sim", stage, batch.submitted_at - started, batch.finished_at - started))
        stepping = time.perf_counter()
        for step in range(steps):
            keys = {s: client.stage_traj_keys(s) for s in stages}
            calls = {
                s: client.step_stage(s, dict(zip(keys[s], scripted_chunks(action_space, step, len(keys[s]), chunk))))
                for s in stages
            }
            for stage, call in calls.items():
                batch = call.result(timeout_s)
                timeline.append(("sim", stage, batch.submitted_at - started, batch.finished_at - started))
                if batch.terminated.any() or batch.truncated.any():  # stepped on all the same: the pod's work
                    log.warning(
                        "stage %d: %d envs ended at step %d",
                        stage,
                        int((batch.terminated | batch.truncated).sum()),
                        step,
                    )
        ended = time.perf_counter()
    env_steps = steps * len(routes) * chunk
    stats = RolloutStats(
        num_trajectories=len(routes),
        env_steps=env_steps,
        wall_s=ended - started,
        env_steps_per_s=env_steps / max(ended - stepping, 1e-9),
        simulation_s=ended - started,
        timeline=sorted(timeline, key=lambda item: item[2]),
    )
    return Measured(stats, **seen)


class Deadline:
    """Seconds left of the run's budget; measurements stop adding rounds once it is spent."""

    def __init__(self, seconds: float) -> None:
        self.end = time.monotonic() + seconds

    def left(self) -> float:
        return self.end - time.monotonic()


def interleave(
    contenders: dict[str, Callable[[], Measured]], rounds: int, deadline: Deadline, reserve_s: float
) -> dict[str, list[Measured]]:
    """Run each contender once per round, the order rotating; start another round only while
    the last round's duration plus ``reserve_s`` fits in what is left (one round always runs)."""
    names = list(contenders)
    out: dict[str, list[Measured]] = {name: [] for name in names}
    last_s = 0.0
    for r in range(rounds):
        if r and deadline.left() < 1.1 * last_s + reserve_s:
            log.warning(
                "deadline near (%.0f s left, a round takes %.0f s): %d of %d rounds run",
                deadline.left(),
                last_s,
                r,
                rounds,
            )
            break
        began = time.monotonic()
        for name in names[r % len(names) :] + names[: r % len(names)]:
            out[name].append(contenders[name]())
        last_s = time.monotonic() - began
        log.info("round %d (%.0f s): %s", r + 1, last_s, {n: round(v[-1].env_steps_per_s, 1) for n, v in out.items()})
    return out
