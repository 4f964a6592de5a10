"""Two stages on one pod: what the ``slices`` layout's env order buys, and how a pod takes two
stages' calls at once.

One standalone pod runs a ``slices`` assignment (``vecsim.plan.slice_blocks``: a task's envs
alternate stage 0, stage 1, ...), ``--envs-per-worker`` consecutive envs per worker process, so
each worker holds envs of both stages. The client sees the same pod's envs three ways:

- ``slices``: the pod's own blocks (every worker holds envs of both stages);
- ``stage_major``: stage 0 = the first half of the envs, stage 1 = the rest (each worker holds
  envs of one stage only: what stage-major blocks would give);
- ``one_stage``: every env on stage 0.

Probe (the pod's concurrency): one stage's chunk-step call alone, then both stages' calls sent
at once; the pod runs calls one at a time (one sim thread, ``service/pod/state.py``), so both
together take about twice one, and a call of a stage whose envs sit on one worker leaves the
other workers idle. Rollouts: ``EnvLoop`` with a policy that sleeps ``--policy-ms`` per call (a
GPU forward pass, which takes no pod core, for a batch of every env, pro rata for fewer;
default: the one-stage call time measured by the probe), chunks of ``--chunk`` actions,
interleaved rounds; env-steps/s and each two-stage
contender against ``one_stage``.

    python bench/bench_stage_slices.py --quick   # smoke: gym scene, 8x8, under a minute
    python bench/bench_stage_slices.py           # dev box: tiny/lift 32x32, 8 envs, 2 workers, K=8

Prints ``RESULT {json}`` and writes out/bench/bench_stage_slices.json.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import statistics
import time
from typing import Any

import numpy as np
import torch
from lib.pods import READY_TIMEOUT_S, interleaved, paired_ratio, rate_spread, setup_logging, standalone_pods
from lib.records import with_flags, write_result

from vecsim.client import StageClient
from vecsim.config import Assignment, CameraConfig, RoutedPod, RoutedStage, RoutingTable, TaskBlock
from vecsim.plan import slice_blocks
from vecsim.rollout import EnvLoop

log = logging.getLogger("bench.stage_slices")

VIEWS = ("slices", "stage_major", "one_stage")


class SleepPolicy:
    """Zero chunks ``[n, K, action_dim]``, a call of n rows taking ``batch_s x n / batch`` (a
    sleep: a forward pass that takes no pod core and whose time follows its batch, as a large
    GPU batch's does)."""

    def __init__(self, action_dim: int, chunk: int, batch_s: float, batch: int) -> None:
        self.action_dim, self.chunk, self.batch_s, self.batch = action_dim, chunk, batch_s, batch

    def __call__(self, obs: dict[str, Any], instructions: list[str], task_ids: list[str]) -> torch.Tensor:
        if self.batch_s > 0:
            time.sleep(self.batch_s * len(task_ids) / self.batch)
        return torch.zeros((len(task_ids), self.chunk, self.action_dim))


def view(table: RoutingTable, name: str) -> RoutingTable:
    """The pod's envs (one pod, two stages in ``table``) as the contender ``name`` sees them."""
    (pod,) = {p.pod: p for stage in table.stages for p in stage.pods}.values()
    if name == "slices":
        return table
    envs = sorted(
        (b.env_start + k, b.task_id)
        for stage in table.stages
        for p in stage.pods
        for b in p.tasks
        for k in range(b.num_envs)
    )
    parts = [envs] if name == "one_stage" else [envs[: len(envs) // 2], envs[len(envs) // 2 :]]
    stages = tuple(
        RoutedStage(
            stage_id=s,
            pods=(
                RoutedPod(
                    pod=pod.pod,
                    url=pod.url,
                    num_envs=len(part),
                    tasks=tuple(TaskBlock(task_id=task, env_start=env, num_envs=1, stage_id=s) for env, task in part),
                ),
            ),
        )
        for s, part in enumerate(parts)
    )
    return table.model_copy(update={"stages": stages})


def chunk_of(client: StageClient, keys: list[str], chunk: int) -> dict[str, np.ndarray]:
    shape = (chunk, *client.action_space.shape)
    return {key: np.zeros(shape, np.float32) for key in keys}


def probe(client: StageClient, chunk: int, calls: int) -> dict[str, float]:
    """Median ms of stage 0's chunk step alone and of both stages' steps sent at once."""
    placed = [
        (b.task_id, s)
        for s, stage in enumerate(client.routing.stages)
        for p in stage.pods
        for b in p.tasks
        for _ in range(b.num_envs)
    ]
    envs, stages = [(task, 0) for task, _ in placed], [s for _, s in placed]
    client.reset_trajectories(envs, stages=stages)
    for s in range(client.num_stages):
        client.reset_stage(s).result()
    keys = {s: client.stage_traj_keys(s) for s in range(client.num_stages)}
    alone, both = [], []
    for _ in range(calls):
        began = time.perf_counter()
        client.step_stage(0, chunk_of(client, keys[0], chunk)).result()
        alone.append(time.perf_counter() - began)
        if client.num_stages > 1:
            began = time.perf_counter()
            pending = [client.step_stage(s, chunk_of(client, keys[s], chunk)) for s in (0, 1)]
            for call in pending:
                call.result()
            both.append(time.perf_counter() - began)
    out = {"stage0_alone_ms": round(1000 * statistics.median(alone), 1)}
    if both:
        out["both_stages_at_once_ms"] = round(1000 * statistics.median(both), 1)
        out["both_over_alone"] = round(statistics.median(both) / statistics.median(alone), 2)
    return out


def settings(args: argparse.Namespace) -> dict[str, Any]:
    if args.quick:
        mode = {
            "task": "gym/HalfCheetah-v5",
            "group_size": 2,
            "envs_per_worker": 2,
            "size": 8,
            "chunk": 4,
            "horizon": 16,
            "rounds": 2,
            "probe_calls": 3,
        }
    else:
        mode = {
            "task": "tiny/lift",
            "group_size": 4,
            "envs_per_worker": 4,
            "size": 32,
            "chunk": 8,
            "horizon": 48,
            "rounds": 3,
            "probe_calls": 5,
        }
    return with_flags(mode, args)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="tiny sizes, for the smoke test")
    parser.add_argument("--task")
    parser.add_argument("--group-size", type=int, help="envs per stage (the pod holds 2x this)")
    parser.add_argument("--envs-per-worker", type=int)
    parser.add_argument("--size", type=int, help="camera height and width")
    parser.add_argument("--chunk", type=int, help="actions per env per call (K)")
    parser.add_argument("--horizon", type=int, help="actions per trajectory")
    parser.add_argument("--rounds", type=int)
    parser.add_argument("--probe-calls", type=int)
    parser.add_argument(
        "--policy-ms",
        type=float,
        help="the policy's sleep for a batch of every env, pro rata for fewer (default: the probe's "
        "one-stage call: policy as slow as the simulation)",
    )
    args = parser.parse_args()
    setup_logging()
    os.environ.setdefault("MUJOCO_GL", "egl")
    mode = settings(args)
    names = ("render",) if mode["task"].startswith("gym/") else ("agentview",)
    assignment = Assignment(
        generation=0,
        job_id="bench-stage-slices",
        pod="sim-0",
        stage_id=None,
        tasks=slice_blocks([mode["task"]], mode["group_size"], 2),
        camera=CameraConfig(names=names, height=mode["size"], width=mode["size"]),
        render="lean",
        envs_per_worker=mode["envs_per_worker"],
        max_episode_steps=10 * mode["horizon"],
    )
    with contextlib.ExitStack() as stack:
        (pod,) = stack.enter_context(standalone_pods([assignment], ready_timeout_s=READY_TIMEOUT_S))
        own = stack.enter_context(StageClient.from_pods([pod.url], timeout_s=120))
        clients = {name: stack.enter_context(StageClient(view(own.routing, name), timeout_s=120)) for name in VIEWS}
        probes = {name: probe(clients[name], mode["chunk"], mode["probe_calls"]) for name in VIEWS}
        log.info("probe: %s", probes)
        policy_ms = args.policy_ms if args.policy_ms is not None else probes["one_stage"]["stage0_alone_ms"]
        policy = SleepPolicy(int(np.prod(own.action_space.shape)), mode["chunk"], policy_ms / 1000, assignment.num_envs)

        def rollout(name: str) -> float:
            # Request i on stage i % S, as the sampler interleaves them; one per env.
            per_stage = [
                [(b.task_id, k) for p in stage.pods for b in p.tasks for k in range(b.num_envs)]
                for stage in clients[name].routing.stages
            ]
            batch = [per_stage[i % len(per_stage)][i // len(per_stage)] for i in range(sum(map(len, per_stage)))]
            stats = EnvLoop(clients[name], policy, horizon=mode["horizon"], keep_obs=()).run(batch).stats
            return stats.env_steps / stats.wall_s

        rates = interleaved({name: (lambda n=name: rollout(n)) for name in VIEWS}, mode["rounds"])
    summary = {
        "baseline": "one_stage: the same pod's envs in one stage, the same policy",
        "ratio": paired_ratio(rates["slices"], rates["one_stage"])["median"],
        "ratio_stage_major": paired_ratio(rates["stage_major"], rates["one_stage"])["median"],
        "setup": {
            **mode,
            "envs": assignment.num_envs,
            "workers": -(-assignment.num_envs // mode["envs_per_worker"]),
            "policy_ms": policy_ms,
            "cameras": list(names),
            "cores": len(os.sched_getaffinity(0)),
        },
        "probe": probes,
        "env_steps_per_s": {name: rate_spread(values) for name, values in rates.items()},
        "two_stages_over_one": {
            name: paired_ratio(rates[name], rates["one_stage"]) for name in ("slices", "stage_major")
        },
    }
    write_result("bench_stage_slices", summary, {"per_round": rates})


if __name__ == "__main__":
    main()
