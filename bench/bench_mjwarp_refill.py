"""What a refill costs on the ``mjwarp`` engine: resets riding in a step, against a step alone
and against the reset and the step as two calls.

A rollout loop with auto-reset sends the envs whose episodes ended as resets inside the next
step's request (a refill). MuJoCo Warp draws every world of a batch, so the engine runs a
refill's resets and its chunk in one turn at the GPU and draws once (docs/mjwarp.md, Resets and
refills). This bench builds one engine of ``--worlds`` worlds and times three kinds of call on
it, interleaved call by call (the order turns each round), so the three share the machine's
noise:

- ``step``: a chunk of K actions for every env, no reset (the baseline);
- ``refill``: ``--share`` of the envs reset to LIBERO init states, the others stepped, in one
  ``reset_and_step_envs`` call;
- ``reset_then_step``: the same resets and the same chunk as ``reset_envs`` then
  ``chunk_step_envs``, what a refill cost before it drew once.

Each kind reports seconds per call, env-steps/s (stepped envs x K), physics and render seconds
and env renders per call; the record gives ``refill`` over ``reset_then_step`` and ``refill``
over ``step`` in env-steps/s. The reset envs rotate through the batch, so every env is reset in
turn::

    python bench/bench_mjwarp_refill.py --worlds 8192 --size 256 --share 0.125 --calls 6 \\
        --out out/bench/bench_mjwarp_refill.json

Runs in the ``mjwarp`` extra's environment on a GPU (on warp's CPU device too, with
``VECSIM_MJWARP_ALLOW_CPU=1``: minutes for a few worlds, to try it). The JSON record is written
after every round, so a run cut short still leaves one.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np
from lib.jobs import one_task_assignment
from lib.records import command_line, machine_info, write_record

log = logging.getLogger("bench_mjwarp_refill")

KINDS = ("step", "refill", "reset_then_step")
# LIBERO-10's init states per task: a reset env starts at its id modulo this.
INIT_STATES = 50


def reset_window(envs: int, share: float, call: int) -> np.ndarray:
    """The envs reset in call ``call``: ``round(share * envs)`` of them (at least one, never
    all), the window moving on by its own length each call and wrapping at the end."""
    if not 0.0 < share < 1.0:
        raise ValueError(f"share: {share} is not between 0 and 1 (exclusive)")
    count = min(max(1, round(share * envs)), envs - 1)
    return (call * count + np.arange(count)) % envs


def one_call(engine: Any, kind: str, envs: int, resets: np.ndarray, actions: np.ndarray) -> dict[str, float]:
    """One call of ``kind``: its seconds, env-steps, physics and render seconds, env renders."""
    stepped = np.arange(envs) if kind == "step" else np.setdiff1d(np.arange(envs), resets)
    chunk = actions[stepped]
    started = time.perf_counter()
    physics = render = renders = 0.0
    if kind == "refill":
        _, result = engine.reset_and_step_envs(resets, resets % INIT_STATES, stepped, chunk, step_past_end=True)
    else:
        if kind == "reset_then_step":
            engine.reset_envs(resets, resets % INIT_STATES)
            physics, render, renders = (
                engine.last_timing.physics_s,
                engine.last_timing.render_s,
                engine.last_timing.renders,
            )
        result = engine.chunk_step_envs(stepped, chunk, step_past_end=True)
    seconds = time.perf_counter() - started
    return {
        "seconds": seconds,
        "env_steps": float(result.num_steps.sum()),
        "physics_s": physics + engine.last_timing.physics_s,
        "render_s": render + engine.last_timing.render_s,
        "renders": renders + engine.last_timing.renders,
    }


def summary(calls: list[dict[str, float]]) -> dict[str, float]:
    """Per call averages and the rate over all of a kind's calls."""
    total = {key: sum(call[key] for call in calls) for key in calls[0]}
    count = len(calls)
    return {
        "calls": count,
        "env_steps_per_s": total["env_steps"] / total["seconds"],
        "s_per_call": total["seconds"] / count,
        "physics_s_per_call": total["physics_s"] / count,
        "render_s_per_call": total["render_s"] / count,
        "renders_per_call": total["renders"] / count,
    }


def ratios(kinds: dict[str, dict[str, float]]) -> dict[str, float]:
    """``refill`` against the two others, in env-steps/s."""
    rate = {kind: kinds[kind]["env_steps_per_s"] for kind in kinds}
    return {
        "refill_over_reset_then_step": rate["refill"] / rate["reset_then_step"],
        "refill_over_step": rate["refill"] / rate["step"],
    }


def run(args: argparse.Namespace) -> dict[str, Any]:
    from vecsim.engine.base import engine_kind

    deadline = time.monotonic() + args.budget_s
    record: dict[str, Any] = {
        "name": "bench_mjwarp_refill",
        "command": command_line(),
        "machine": {**machine_info(), "name": args.machine},
        "task": args.task,
        "worlds": args.worlds,
        "size": args.size,
        "chunk": args.chunk,
        "share": args.share,
        "complete": False,
    }
    started = time.monotonic()
    engine = engine_kind("mjwarp").build(one_task_assignment(args.task, args.worlds, args.size, "mjwarp"))
    record["build_s"] = time.monotonic() - started
    log.info("built %d worlds in %.0f s", args.worlds, record["build_s"])
    calls: dict[str, list[dict[str, float]]] = {kind: [] for kind in KINDS}
    rng = np.random.default_rng(0)
    try:
        ids = np.arange(args.worlds)
        engine.reset_envs(ids, ids % INIT_STATES)
        # A first call of each kind, untimed: kernels and graphs of every path are warm.
        for call in range(-1, args.calls):
            order = KINDS[call % 3 :] + KINDS[: call % 3]
            for kind in order:
                actions = rng.uniform(-0.3, 0.3, (args.worlds, args.chunk, 7)).astype(np.float32)
                measured = one_call(engine, kind, args.worlds, reset_window(args.worlds, args.share, call + 1), actions)
                if call >= 0:
                    calls[kind].append(measured)
            if call >= 0:
                record["kinds"] = {kind: summary(calls[kind]) for kind in KINDS}
                record.update(ratios(record["kinds"]))
                write_record(record, args.out)
                log.info(
                    "round %d of %d: refill %.2fx reset then step",
                    call + 1,
                    args.calls,
                    record["refill_over_reset_then_step"],
                )
            if time.monotonic() > deadline:
                record["cut_short"] = f"budget of {args.budget_s} s spent after {call + 1} rounds"
                write_record(record, args.out)
                return record
    finally:
        engine.close()
    record["complete"] = True
    write_record(record, args.out)
    return record


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--task", default="libero_10/0")
    parser.add_argument("--worlds", type=int, default=1024)
    parser.add_argument("--size", type=int, default=256, help="both cameras' size (0: no camera)")
    parser.add_argument("--chunk", type=int, default=8)
    parser.add_argument("--share", type=float, default=0.125, help="the share of envs reset in a refill")
    parser.add_argument("--calls", type=int, default=6, help="timed rounds, one call of each kind a round")
    parser.add_argument("--budget-s", type=float, default=420.0)
    parser.add_argument("--machine", default="unnamed")
    parser.add_argument("--out", type=Path, default=Path("out/bench/bench_mjwarp_refill.json"))
    args = parser.parse_args()
    if args.worlds < 2:
        parser.error(f"--worlds: {args.worlds} leaves no env to step beside a reset (at least 2)")
    if not 0.0 < args.share < 1.0:
        parser.error(f"--share: {args.share} is not between 0 and 1 (exclusive)")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    record = run(args)
    print("RESULT", json.dumps(record))
    if not record["complete"]:
        raise SystemExit(f"cut short: {record['cut_short']}")


if __name__ == "__main__":
    main()
