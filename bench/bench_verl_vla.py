"""verl-vla over vecsim: a chunk in one call per pod against verl-vla's K one-action calls.

verl-vla's ``BaseEnv.step`` runs a chunk of K actions through the one-action hook
``env_step(action, env_ids)``, K times (src/verl_vla/envs/base.py:254-280 via its serial
executor); :class:`vecsim.trainers.verl_vla.VecsimLiberoEnv` sends the whole chunk in one
request per pod where nothing acts between two actions. This bench times both through the
adapter's own hooks on one LIBERO job: ``whole`` is what its ``step`` sends (one
``VLAEnv.chunk_step`` of ``[num_envs, K, 7]``), ``per_action`` is what ``BaseEnv``'s loop calls
(K ``env_step`` calls of ``[num_envs, 7]``). ``BaseEnv``'s own bookkeeping (the same in both)
is not timed. Rounds alternate the two; env-steps/s and their paired ratio are reported.

    python bench/bench_verl_vla.py [--pods 2] [--envs-per-pod 2] [--size 64] [--k 8] [--chunks 4] [--rounds 5]

Prints ``RESULT {json}`` and writes out/bench/bench_verl_vla.json.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import time
from typing import Any

import numpy as np
from lib.pods import READY_TIMEOUT_S, interleaved, paired_ratio, rate_spread, setup_logging, standalone_pods
from lib.records import write_result

from vecsim.config import Assignment, CameraConfig, TaskBlock
from vecsim.trainers.verl_vla import VecsimLiberoEnv

log = logging.getLogger("bench.verl_vla")


class _Base:
    """The part of verl-vla's ``BaseEnv.__init__`` the hooks need (base.py:73-85)."""

    def __init__(self, cfg: dict[str, Any], rank: int, world_size: int, stage_id: int = 0) -> None:
        self.cfg = cfg
        self.num_envs = int(cfg["num_envs"])
        self.env_init()


class Hooks(VecsimLiberoEnv, _Base):
    """The adapter's hooks alone, with no ``BaseEnv`` around them."""


def measure(pods: int, per_pod: int, size: int, k: int, chunks: int, rounds: int) -> dict[str, Any]:
    camera = CameraConfig(height=size, width=size)
    assignments = [
        Assignment(
            generation=0,
            job_id="bench-verl-vla",
            pod=f"sim-{p}",
            stage_id=0,
            camera=camera,
            max_episode_steps=None,
            tasks=(TaskBlock(task_id=f"libero_spatial/{p}", env_start=0, num_envs=per_pod),),
        )
        for p in range(pods)
    ]
    rng = np.random.default_rng(0)
    num_envs = pods * per_pod
    actions = rng.uniform(-0.3, 0.3, (chunks, num_envs, k, 7)).astype(np.float32)
    with contextlib.ExitStack() as stack:
        running = stack.enter_context(standalone_pods(assignments, ready_timeout_s=READY_TIMEOUT_S))
        cfg = {"num_envs": num_envs, "simulator": {"vecsim": {"pod_urls": [p.url for p in running]}}}
        env = Hooks(cfg, rank=0, world_size=1)
        stack.callback(env.env_close)
        every = np.arange(num_envs)
        env.env_reset(env_ids=every)

        def whole() -> float:
            started = time.perf_counter()
            for chunk in actions:
                env.vla.chunk_step(chunk, env_ids=env.job_env_ids)
            return chunks * k * num_envs / (time.perf_counter() - started)

        def per_action() -> float:
            started = time.perf_counter()
            for chunk in actions:
                for j in range(k):
                    env.env_step(chunk[:, j], env_ids=every)
            return chunks * k * num_envs / (time.perf_counter() - started)

        contenders = {"whole": whole, "per_action": per_action}
        for run in contenders.values():
            run()  # warm-up
        figures = interleaved(contenders, rounds)
    return {
        "pods": pods,
        "envs_per_pod": per_pod,
        "camera": camera.model_dump(mode="json"),
        "k": k,
        "chunks_per_round": chunks,
        "env_steps_per_s": {name: rate_spread(values) for name, values in figures.items()},
        "whole_over_per_action": paired_ratio(figures["whole"], figures["per_action"]),
        "per_round": figures,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pods", type=int, default=2)
    parser.add_argument("--envs-per-pod", type=int, default=2)
    parser.add_argument("--size", type=int, default=64, help="camera height and width (two cameras)")
    parser.add_argument("--k", type=int, default=8)
    parser.add_argument("--chunks", type=int, default=4, help="chunks per round")
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args()
    setup_logging()
    os.environ.setdefault("MUJOCO_GL", "egl")
    result = measure(args.pods, args.envs_per_pod, args.size, args.k, args.chunks, args.rounds)
    summary = {
        "baseline": "per_action: verl-vla's K one-action env_step calls per chunk",
        "ratio": result["whole_over_per_action"]["median"],
        **{key: value for key, value in result.items() if key != "per_round"},
    }
    write_result("bench_verl_vla", summary, result)


if __name__ == "__main__":
    main()
