"""The node's simulation alone, in processes pinned to the pods' cores, no HTTP or pods in between:
the baselines ``bench_chunks.py`` measures serving against.

- :func:`physics_only`: the task mix stepped without cameras (``lib.physics.physics_worker``), all
  processes at once; the node's physics-only rate.
- :class:`CeilingProcesses`: the same mix with the pods' cameras rendered once per K actions
  (:func:`ceiling_worker`), kept up beside the job and measured in every round while the pods idle
  (issue 27's ceiling); :func:`ceiling_over_rounds` sums its rounds up.
"""

from __future__ import annotations

import dataclasses
import logging
import multiprocessing
import os
import queue
import statistics
import time
import traceback
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from .jobs import Plan, camera
from .physics import physics_worker
from .policies import random_actions


def _collect(procs: Sequence[Any], results: Any, kind_wanted: str, count: int, timeout_s: float) -> list[Any]:
    """Return the payloads of ``count`` ``(kind_wanted, index, payload)`` messages from the pinned
    processes ``procs`` on ``results``, in arrival order.

    Raises:
        RuntimeError: a process sent ``("error", index, traceback)``, exited, or fewer than
            ``count`` messages came within ``timeout_s``.
    """
    end = time.monotonic() + timeout_s
    payloads: list[Any] = []
    while len(payloads) < count:
        try:
            kind, index, payload = results.get(timeout=min(max(end - time.monotonic(), 0.1), 5.0))
        except queue.Empty:
            dead = [i for i, proc in enumerate(procs) if proc.exitcode not in (None, 0)]
            if dead:  # a process that died before it could report: fail now, not at the timeout
                raise RuntimeError(f"pinned processes {dead} exited without a {kind_wanted!r} message") from None
            if time.monotonic() < end:
                continue
            raise RuntimeError(
                f"{len(payloads)} of {count} {kind_wanted!r} messages came from the pinned processes "
                f"in {timeout_s:.0f} s"
            )
        if kind == "error":
            raise RuntimeError(f"pinned process {index} failed:\n{payload}")
        if kind == kind_wanted:
            payloads.append(payload)
    return payloads


def _stop(procs: Sequence[Any]) -> None:
    for proc in procs:
        proc.join(timeout=10)
        if proc.is_alive():
            proc.kill()


def _spawn(
    pins: Sequence[str], target: Callable[..., None], args: Callable[[int, int], tuple[Any, ...]]
) -> tuple[list[Any], Any, Any]:
    """Start ``target(index, cpu, *args(index, cpu), barrier, results)`` in one spawned process per
    pod core (``pins``), all sharing one barrier; return the processes, their ``results`` queue and
    the barrier, which the caller keeps while they run (a spawned child unpickles it after
    ``start`` has dropped its own reference)."""
    context = multiprocessing.get_context("spawn")
    barrier, results = context.Barrier(len(pins)), context.Queue()
    procs = []
    for i, pin in enumerate(pins):
        cpu = int(pin.split(",")[0])
        procs.append(context.Process(target=target, args=(i, cpu, *args(i, cpu), barrier, results), daemon=True))
    for proc in procs:
        proc.start()
    return procs, results, barrier


def _pinned(
    pins: Sequence[str],
    target: Callable[..., None],
    args: Callable[[int, int], tuple[Any, ...]],
    reports: int,
    timeout_s: float,
) -> list[Any]:
    """Run ``target`` in one process per pod core (:func:`_spawn`), all at once; return the
    ``reports`` payloads of its ``("rate", index, payload)`` messages, in arrival order.

    Raises:
        RuntimeError: a process failed (its traceback) or did not report within ``timeout_s``.
    """
    procs, results, _barrier = _spawn(pins, target, args)
    try:
        return _collect(procs, results, "rate", reports, timeout_s)
    finally:
        _stop(procs)


def _spread(rates: Sequence[float]) -> dict[str, float]:
    return {"min": round(min(rates), 2), "mean": round(statistics.mean(rates), 2), "max": round(max(rates), 2)}


def physics_only(pins: Sequence[str], tasks: Sequence[str], seconds: float, timeout_s: float) -> dict[str, Any]:
    """The node's physics-only rate: one process per pod core (``pins``), each stepping the
    task mix without cameras for ``seconds``, all at once; env-steps/s summed over them.

    Raises:
        RuntimeError: a process failed (its traceback) or did not answer within ``timeout_s``.
    """
    args = lambda i, cpu: (list(tasks), [len(pins)], ["exact"], 1, seconds)  # noqa: E731
    rates = [
        payload[3] for payload in _pinned(pins, physics_worker, args, len(pins), timeout_s)
    ]  # (round, count, path, rate)
    return {
        "env_steps_per_s": round(sum(rates), 1),
        "per_process": _spread(rates),
        # One process per core steps its envs one after another: a step's time is 1 / its rate.
        "ms_per_env_step": round(1000 / statistics.mean(rates), 3),
        "processes": len(pins),
        "pinned_to": list(pins),
        "seconds": seconds,
    }


def ceiling_runs(chunks: Sequence[int], reset_every: int) -> list[tuple[int, int]]:
    """The ceiling's runs, in order: ``(K, 0)`` for each K, followed by ``(K, reset_every)`` when
    ``reset_every`` > 0."""
    return [(k, every) for k in chunks for every in ([0, reset_every] if reset_every else [0])]


def ceiling_worker(
    index: int,
    cpu: int,
    tasks: list[str],
    camera: dict[str, Any],
    preset: str,
    envs_per_task: int,
    commands: Any,
    barrier: Any,
    results: Any,
) -> None:
    """Pin to ``cpu``; build the task mix as a pod's worker does (``envs_per_task`` envs of each
    task, the job's cameras and render preset), say ``("ready", index, None)``, then carry out
    each ``(K, reset_every, seconds)`` from ``commands`` (None: exit), in step with the other
    processes: for ``seconds``, apply K actions to every env (resetting one that ended), and
    render every env's cameras once, in one batch of the process's renderer, as the pod's worker
    does after a chunk (``vecsim.engine.worker.Worker._draw``); with ``reset_every`` > 0, resetting
    every env (to its next state id) after that many actions too, as a rollout of that horizon
    must. Reports ``("rate", index, (K, reset_every, env-steps/s, physics seconds, render seconds,
    env-steps))``; the resets' time counts as physics."""
    logging.basicConfig(level=logging.WARNING)
    try:
        os.sched_setaffinity(0, {cpu})
        from vecsim.config import CameraConfig
        from vecsim.engine.tasks import make_env

        cameras = CameraConfig(**camera)
        envs = [make_env(task, cameras, preset) for task in tasks for _ in range(envs_per_task)]
        for env in envs:
            env.defer_images = True
            env.reset(options={"state_id": 0})
        renderer = envs[0].renderer
        views = [env.camera_views[c] for c in range(len(envs[0].image_names)) for env in envs]
        rng = np.random.default_rng(index)
        actions = [random_actions(rng, env.action_space.shape) for env in envs]

        since_reset = [0] * len(envs)
        resets = [0] * len(envs)

        def chunk_all(turn: int, k: int, every: int = 0) -> tuple[int, float, float]:
            started, steps = time.perf_counter(), 0
            for e, (env, table) in enumerate(zip(envs, actions)):
                for j in range(k):
                    _, _, terminated, truncated, _ = env.step(table[(turn * k + j) % len(table)])
                    steps += 1
                    since_reset[e] += 1
                    if terminated or truncated or (every and since_reset[e] >= every):
                        resets[e] += 1
                        env.reset(options={"state_id": resets[e] % 50 if every else 0})
                        since_reset[e] = 0
                        break
            stepped = time.perf_counter()
            if renderer is not None:
                renderer.render(views)
            return steps, stepped - started, time.perf_counter() - stepped

        chunk_all(0, 1)  # warm-up: the renderer's first frame, the controller's first step
        results.put(("ready", index, None))
        while (command := commands.get()) is not None:
            k, every, seconds = command
            barrier.wait(timeout=900)
            since_reset[:] = [0] * len(envs)
            turns = steps = 0
            physics = render = 0.0
            started = time.perf_counter()
            while time.perf_counter() - started < seconds:
                applied, physics_s, render_s = chunk_all(turns, k, every)
                turns, steps, physics, render = turns + 1, steps + applied, physics + physics_s, render + render_s
            results.put(("rate", index, (k, every, steps / (time.perf_counter() - started), physics, render, steps)))
            barrier.wait(timeout=900)
    except Exception:
        results.put(("error", index, traceback.format_exc()))
        barrier.abort()


class CeilingProcesses:
    """The node's simulation alone (issue 27's ceiling): one process per pod core (``pins``), with
    the task mix of :func:`physics_only` and the pods' cameras rendered once per K actions
    (:func:`ceiling_worker`), no HTTP or pods. Built once and kept up beside the job, so that the
    ceiling is a contender of every round, run while the pods idle: on a shared machine the
    bare processes' own rate drifts by up to 30% over minutes (H200 node, 2026-11-28), so a ceiling
    measured before or after the rounds is no baseline for them.

    :meth:`measure` runs each K for ``seconds`` and, with ``reset_every``, again as
    ``K=k/reset_every_H`` with every env reset after H actions; per run, env-steps/s summed over
    the processes and the physics and render milliseconds per env-step.
    """

    def __init__(
        self, pins: Sequence[str], plan: Plan, chunks: Sequence[int], seconds: float, reset_every: int, timeout_s: float
    ) -> None:
        self.pins, self.plan, self.seconds, self.timeout_s = list(pins), plan, seconds, timeout_s
        self.runs = ceiling_runs(chunks, reset_every)
        self._procs: list[Any] = []
        self._commands: list[Any] = []

    def __enter__(self) -> CeilingProcesses:
        plan = self.plan
        self._commands = [multiprocessing.get_context("spawn").Queue() for _ in self.pins]
        self._procs, self._results, self._barrier = _spawn(
            self.pins,
            ceiling_worker,
            lambda i, cpu: (list(plan.tasks), camera(plan), plan.render_preset, plan.envs_per_task, self._commands[i]),
        )
        try:
            _collect(self._procs, self._results, "ready", len(self._procs), self.timeout_s)
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        for commands in self._commands:
            commands.put(None)
        _stop(self._procs)

    def measure(self) -> dict[str, Any]:
        """One run of every K (the class docstring): its figures by ``K=k`` and ``K=k/reset_every_H``.

        Raises:
            RuntimeError: a process failed (its traceback) or did not report within the timeout.
        """
        for k, every in self.runs:
            for commands in self._commands:
                commands.put((k, every, self.seconds))
        reports = _collect(
            self._procs,
            self._results,
            "rate",
            len(self._procs) * len(self.runs),
            self.timeout_s + len(self.runs) * self.seconds,
        )
        out: dict[str, Any] = {}
        for k, every in self.runs:
            mine = [r[2:] for r in reports if r[:2] == (k, every)]
            steps = max(sum(r[3] for r in mine), 1)
            out[ceiling_key(k, every)] = {
                "env_steps_per_s": round(sum(r[0] for r in mine), 1),
                "per_process": _spread([r[0] for r in mine]),
                "physics_ms_per_env_step": round(1000 * sum(r[1] for r in mine) / steps, 3),
                "render_ms_per_env_step": round(1000 * sum(r[2] for r in mine) / steps, 3),
            }
        return out

    def describe(self) -> dict[str, Any]:
        return {
            "processes": len(self.pins),
            "pinned_to": self.pins,
            "seconds_per_k": self.seconds,
            "camera": camera(self.plan),
            "render_preset": self.plan.render_preset,
        }


def ceiling_key(k: int, every: int) -> str:
    """A ceiling run's name: ``K=k``, or ``K=k/reset_every_H``."""
    return f"K={k}" + (f"/reset_every_{every}" if every else "")


@dataclasses.dataclass(frozen=True)
class CeilingRound:
    """The ceiling's figures of one round (:meth:`CeilingProcesses.measure`); its rate is that of
    run ``at`` (a ``ceiling_key``), so that it sits in the rounds beside the rollouts."""

    figures: dict[str, Any]
    at: str

    @property
    def env_steps_per_s(self) -> float:
        return self.figures[self.at]["env_steps_per_s"]


def ceiling_over_rounds(rounds: Sequence[CeilingRound], described: dict[str, Any]) -> dict[str, Any]:
    """The ceiling's record: ``described``, and per run the medians over ``rounds`` of its
    env-steps/s and milliseconds per env-step, its per-round rates and each round's spread
    over the processes."""
    out = dict(described)
    for key in rounds[0].figures:
        figures = [r.figures[key] for r in rounds]
        out[key] = {
            "env_steps_per_s": round(statistics.median(f["env_steps_per_s"] for f in figures), 1),
            "physics_ms_per_env_step": round(statistics.median(f["physics_ms_per_env_step"] for f in figures), 3),
            "render_ms_per_env_step": round(statistics.median(f["render_ms_per_env_step"] for f in figures), 3),
            "per_round": [f["env_steps_per_s"] for f in figures],
            "per_process_by_round": [f["per_process"] for f in figures],
        }
    return out
