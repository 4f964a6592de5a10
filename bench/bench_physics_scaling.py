"""The machine's own scaling: MuJoCo physics in P pinned processes, no vecsim in between.

The baseline for "scaling >= 0.8 of linear": if P processes that only step physics (no HTTP, no
rendering, no pods) already fall short of P x one process, the shortfall is the machine's (shared
caches, memory bandwidth, a virtual machine's CPUs), and no serving layer can make it up.

Each of ``max(--procs)`` processes is pinned to a core of its own (``os.sched_setaffinity``),
builds the same task mix (``--tasks``, one env each, no cameras) and then, in lockstep (a barrier
before each measurement), the first P of them step their envs with small random actions for
``--seconds``; rounds interleave the values of P. Per P: env-steps/s of all processes, of the
slowest and the fastest process, and the ratio to P x the 1-process figure of the same round.

    python bench/bench_physics_scaling.py                         # LIBERO-10's ten tasks, P = 1,2,4,8,12
    python bench/bench_physics_scaling.py --procs 1,2 --tasks libero_10/0,libero_10/1 --seconds 2
    python bench/bench_physics_scaling.py --step-paths exact,library   # vecsim's step path vs robosuite's

``--step-paths`` names the robot envs' step paths to measure (``vecsim.engine.tasks._fast_step``:
``exact``, vecsim's default, and ``library``, the env's own ``step``), interleaved within each
round; both give the same trajectories, so their rates compare directly (``over_library``).

Writes out/bench/bench_physics_scaling[_<tag>].json and prints ``RESULT {json}``.
"""

from __future__ import annotations

import argparse
import logging
import multiprocessing
import os
import statistics
import time
from typing import Any

from lib.physics import physics_worker
from lib.records import write_result

log = logging.getLogger("bench_physics_scaling")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tasks", help="comma-separated task ids (default: LIBERO-10's ten)")
    parser.add_argument("--procs", default="1,2,4,8,12", help="comma-separated process counts")
    parser.add_argument("--seconds", type=float, default=6.0, help="length of each measurement")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--step-paths", default="exact", help="comma-separated robot step paths: exact, library")
    parser.add_argument("--tag", help="suffix of the output file's name")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    if args.tasks:
        tasks = [t for t in args.tasks.split(",") if t]
    else:
        from vecsim.engine.tasks import suite_tasks

        tasks = [t.task_id for t in suite_tasks("libero_10")]
    counts = sorted({int(c) for c in args.procs.split(",")} | {1})
    paths = [p for p in args.step_paths.split(",") if p]
    if not paths or set(paths) - {"exact", "library"}:
        raise SystemExit(f"--step-paths takes exact and/or library, got {args.step_paths!r}")
    cpus = sorted(os.sched_getaffinity(0))
    if counts[-1] > len(cpus):
        raise SystemExit(f"--procs asks for {counts[-1]} processes, this process may run on {len(cpus)} CPUs")

    context = multiprocessing.get_context("spawn")
    barrier, results = context.Barrier(counts[-1]), context.Queue()
    procs = [
        context.Process(
            target=physics_worker, args=(i, cpus[i], tasks, counts, paths, args.rounds, args.seconds, barrier, results)
        )
        for i in range(counts[-1])
    ]
    started = time.monotonic()
    for proc in procs:
        proc.start()
    rates: dict[tuple[int, int, str], list[float]] = {}
    built = 0
    expected = args.rounds * sum(counts) * len(paths)
    got = 0
    deadline = started + 1800
    while got < expected:
        kind, index, payload = results.get(timeout=max(1.0, deadline - time.monotonic()))
        if kind == "error":
            for proc in procs:
                proc.kill()
            raise SystemExit(f"process {index} failed:\n{payload}")
        if kind == "built":
            built += 1
            if built == len(procs):
                log.info("%d processes built %d envs each in %.0f s", built, len(tasks), time.monotonic() - started)
            continue
        round_, count, path, rate = payload
        rates.setdefault((round_, count, path), []).append(rate)
        got += 1
        if len(rates[(round_, count, path)]) == count:
            total = sum(rates[(round_, count, path)])
            log.info("round %d, %d processes, %s step: %.1f env-steps/s", round_ + 1, count, path, total)
    for proc in procs:
        proc.join(timeout=60)

    by_path: dict[str, dict[str, Any]] = {}
    for path in paths:
        rows = by_path[path] = {}
        for count in counts:
            totals = [sum(rates[(r, count, path)]) for r in range(args.rounds)]
            ratios = [sum(rates[(r, count, path)]) / (count * rates[(r, 1, path)][0]) for r in range(args.rounds)]
            per_proc = [x for r in range(args.rounds) for x in rates[(r, count, path)]]
            rows[str(count)] = {
                "env_steps_per_s": round(statistics.median(totals), 1),
                "per_process_mean": round(statistics.mean(per_proc), 2),
                "per_process_min": round(min(per_proc), 2),
                "per_process_max": round(max(per_proc), 2),
                "ratio_to_linear": round(statistics.median(ratios), 3),
            }
            if path != "library" and "library" in paths:
                # The same round's library-path rate: the step path's gain at this process count.
                gains = [sum(rates[(r, count, path)]) / sum(rates[(r, count, "library")]) for r in range(args.rounds)]
                rows[str(count)]["over_library"] = round(statistics.median(gains), 3)
    rows = by_path[paths[0]]
    summary = {
        "baseline": "1 process of the same task mix, same round; linear = P x that",
        "ratio": rows[str(counts[-1])]["ratio_to_linear"],
        "setup": {
            "tasks": tasks,
            "envs_per_process": len(tasks),
            "cameras": "none (physics only)",
            "procs": counts,
            "pinned_to": cpus[: counts[-1]],
            "seconds": args.seconds,
            "rounds": args.rounds,
            "step_paths": paths,
        },
        "rows": rows,
        "rows_by_step_path": by_path,
        "seconds_total": round(time.monotonic() - started, 1),
    }
    write_result("bench_physics_scaling" + (f"_{args.tag}" if args.tag else ""), summary)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
