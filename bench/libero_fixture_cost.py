"""What the published fixture rule costs: replaying LIBERO's resets, reading them back, and LIBERO's own.

Per task: a LIBERO env built as vecsim builds it (``hard_reset`` on), then
``vecsim.engine.tasks._libero.episode_fixtures(..., "published")`` with an empty cache (one real hard
reset, then 49 replayed ones, saved), the same read back from the cache (one hard reset, the file
read), and, for comparison, ``--real`` more real hard resets of that env (``env.reset()`` as the
published loop runs it, what computing episode ``k`` by ``k`` real resets would cost each).
Wall and CPU seconds (``time.process_time``: on a shared machine the wall time also counts the
time other processes held the cores).

    PYTHONPATH=$PWD MUJOCO_GL=egl python bench/libero_fixture_cost.py [--tasks libero_10/9 ...] [--real 5]
"""

from __future__ import annotations

import argparse
import logging
import os
import tempfile
import time
from typing import Any

import mujoco
from lib.records import write_result

from vecsim.engine.tasks import get_task
from vecsim.engine.tasks import (
    ensure_config,
    episode_fixtures,
    fixtures_path,
    libero_benchmark,
    load_fixtures,
    seeded_global_rngs,
)

log = logging.getLogger("bench.libero_fixture_cost")


def timed(run: Any) -> tuple[Any, float, float]:
    wall, cpu = time.perf_counter(), time.process_time()
    result = run()
    return result, round(time.perf_counter() - wall, 3), round(time.process_time() - cpu, 3)


def build(task_id: str) -> Any:
    from libero.libero.envs import OffScreenRenderEnv

    suite, index = task_id.split("/")
    return OffScreenRenderEnv(
        bddl_file_name=libero_benchmark(suite).get_task_bddl_file_path(int(index)),
        camera_names=[],
        use_camera_obs=False,
        hard_reset=True,
        ignore_done=True,
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--tasks", nargs="*", default=["libero_10/9", "libero_10/3"])
    parser.add_argument("--real", type=int, default=5, help="real hard resets timed per task")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    os.environ["VECSIM_CACHE_DIR"] = tempfile.mkdtemp(prefix="vecsim-fixture-cost-")
    ensure_config()
    rows = []
    for task_id in args.tasks:
        task = get_task(task_id)
        row: dict[str, Any] = {"task_id": task_id}
        for label in ("uncached", "cached"):
            wrapper = build(task_id)
            try:
                (fixtures, _replay), row[f"{label}_wall_s"], row[f"{label}_cpu_s"] = timed(
                    lambda: episode_fixtures(task, wrapper.env, args.seed, "published")
                )
                if label == "cached":
                    path = fixtures_path(task, args.seed)
                    _, row["read_wall_s"], row["read_cpu_s"] = timed(
                        lambda: load_fixtures(path, len(fixtures), wrapper.env.sim.model.nbody)
                    )
                    with seeded_global_rngs(args.seed):
                        _, wall, cpu = timed(lambda: [wrapper.env.reset() for _ in range(args.real)])
                    row["real_reset_wall_s"] = round(wall / args.real, 3)
                    row["real_reset_cpu_s"] = round(cpu / args.real, 3)
            finally:
                wrapper.close()
                mujoco.mj_clearCache(mujoco.mj_getCache())
        row["replay_cpu_s_each"] = round((row["uncached_cpu_s"] - row["cached_cpu_s"]) / (task.num_states - 1), 4)
        rows.append(row)
        log.info("%s", row)
    write_result("libero_fixture_cost", {"tasks": args.tasks, "real": args.real, "rows": rows})


if __name__ == "__main__":
    main()
