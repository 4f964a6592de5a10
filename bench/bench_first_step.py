"""Where a first step's time goes: each pod's calls one at a time, the client's round trip
against the pod's own time for that call.

Starts a local job (``--config``, default the demo's ``configs/tiny.yaml``), resets every env
to a task-balanced batch's state ids, then steps each pod ``--steps`` times with the demo's CNN
policy, one pod call at a time, so that the pod's ``/metrics`` counters read before and after a
call are that call's: the seconds its workers spent in the step request (``step``), in physics
and in rendering (both summed over the pod's workers). The client's round trip less the pod's
``step`` time is HTTP, the wire and the client; a first step whose ``physics`` or ``render``
stands out is the pod's to warm during its build (issue 28: "ready means ready").

    python bench/bench_first_step.py       # the tiny job, 8 steps per pod, from the checkout's root
    cd <other checkout> && PYTHONPATH=$PWD python <this checkout>/bench/bench_first_step.py
                                           # the same on another checkout's code (pods import the cwd's)

Prints one line per call and ``RESULT {json}`` (per pod: each call's times, and the first
step's client and physics time over the later steps' medians).
"""

from __future__ import annotations

import argparse
import json
import logging
import re
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from service.demo import with_free_ports
from service.runner import LocalJob
from vecsim.client import StageClient
from vecsim.config import load_job_config
from vecsim.rollout import ExampleCNNPolicy
from vecsim.rollout.sampler import TaskBalancedSampler, TaskInstances
from vecsim.transport import get_answer

COUNTERS = {
    "step": "vecsim_pod_step_seconds_sum",
    "physics": "vecsim_pod_physics_seconds_total",
    "render": "vecsim_pod_render_seconds_total",
}


def pod_counters(url: str) -> dict[str, float]:
    """The pod's step, physics and render seconds so far, from its ``/metrics``."""
    response = get_answer(f"{url}/metrics", timeout_s=30)
    if response.status_code != 200:
        raise RuntimeError(f"{url}/metrics answered {response.status_code}")
    text = response.text
    found = {}
    for name, metric in COUNTERS.items():
        match = re.search(rf"^{metric} (\S+)$", text, re.M)
        found[name] = float(match.group(1)) if match else 0.0
    return found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", default="configs/tiny.yaml")
    parser.add_argument("--steps", type=int, default=8, help="step calls per pod (default 8)")
    args = parser.parse_args()
    logging.basicConfig(level="WARNING")

    config = with_free_ports(load_job_config(args.config))
    logs = Path(tempfile.mkdtemp(prefix="bench-first-step-"))
    per_pod: dict[str, list[dict[str, float]]] = {}
    with LocalJob(config, log_dir=logs) as local:
        started = time.perf_counter()
        table = local.wait_ready(timeout=900)
        print(f"job ready in {time.perf_counter() - started:.1f} s (pod logs in {logs})", flush=True)
        client = StageClient.from_controller(local.controller_url, token=local.token, timeout_s=300)
        try:
            urls = {routed.pod: routed.url for stage in table.stages for routed in stage.pods}
            tasks = sorted({block.task_id for stage in table.stages for pod in stage.pods for block in pod.tasks})
            dataset = TaskInstances.from_tasks(tasks, num_states=10)
            sampler = TaskBalancedSampler.for_job(dataset, config.job, batch_size=table.num_envs, seed=0)
            requests = [dataset[i] for i in next(iter(sampler))]
            keys = client.new_traj_keys(len(requests))
            routes = client.reset_trajectories(requests, keys, [i % client.num_stages for i in range(len(requests))])
            policy = ExampleCNNPolicy(client.observation_space, client.action_space, noise_std=0.3)
            last = {}
            for call in range(args.steps + 1):
                for pod in sorted(urls):
                    mine = [key for key, route in routes.items() if route.pod == pod]
                    policy_s = 0.0
                    if call == 0:
                        step: dict[str, Any] = {}
                    else:
                        batch = last[pod]
                        obs = {
                            "images": {c: torch.from_numpy(np.asarray(v)) for c, v in batch.obs["images"].items()},
                            "proprio": torch.from_numpy(np.asarray(batch.obs["proprio"])),
                        }
                        begin = time.perf_counter()
                        with torch.no_grad():
                            actions = policy(
                                obs, [client.instructions.get(t, "") for t in batch.task_ids], batch.task_ids
                            )
                        policy_s = time.perf_counter() - begin
                        step = {key: actions[j].numpy() for j, key in enumerate(batch.traj_keys)}
                    before = pod_counters(urls[pod])
                    begin = time.perf_counter()
                    answer = client.pod_call(pod, reset=[] if step else mine, step=step).result()
                    client_s = time.perf_counter() - begin
                    after = pod_counters(urls[pod])
                    last[pod] = answer[1] if step else answer[0]
                    row = {
                        "call": call,
                        "kind": "step" if step else "reset",
                        "client_s": client_s,
                        "policy_s": policy_s,
                        **{f"{k}_s": after[k] - before[k] for k in COUNTERS},
                    }
                    per_pod.setdefault(pod, []).append(row)
                    print(
                        f"{pod} {row['kind']} {call}: client {client_s:.3f} s, pod step {row['step_s']:.3f} s "
                        f"(physics {row['physics_s']:.3f}, render {row['render_s']:.3f} worker-s), policy {policy_s:.3f} s",
                        flush=True,
                    )
        finally:
            client.close()
    summary = {}
    for pod, rows in per_pod.items():
        steps = [row for row in rows if row["kind"] == "step"]
        later = steps[1:] or steps
        summary[pod] = {
            "first_client_over_median": steps[0]["client_s"] / statistics.median(r["client_s"] for r in later),
            "first_physics_s": steps[0]["physics_s"],
            "later_physics_median_s": statistics.median(r["physics_s"] for r in later),
            "calls": rows,
        }
    print("RESULT " + json.dumps(summary))


if __name__ == "__main__":
    main()
