"""Figures from measured rollouts: where a pod's time goes, the slowest pod of a call, overlap of
cores, the hand-off between stages, and the per-contender summary.
"""

from __future__ import annotations

import statistics
from collections.abc import Mapping, Sequence
from typing import Any

from .pods import rate_spread

from vecsim.rollout.intervals import covered, intersection, merge
from .measure import Measured

PIPELINE_TARGET = 1.8  # 2 stages over 1 stage (the performance issue's target)
SCALING_TARGET = 0.8  # of linear


def breakdown(measured: Sequence[Measured]) -> dict[str, float]:
    """Milliseconds per loop step (one policy call + one stage call), median over rollouts:
    policy, the client's stage call, the pods' step wall time, physics and render worker
    seconds per pod, and serving = the call beyond the pod's wall time; also the env-steps per
    policy call (its rows times K)."""
    rows = []
    for m in measured:
        stats, pods = m.stats, m.pods
        calls = pods["vecsim_pod_step_seconds_count"]
        # The first interval of each stage is its reset; the pods count steps only.
        seen: set[int] = set()
        sim_calls = []
        for what, stage, begin, end in stats.timeline:
            if what == "sim":
                if stage in seen:
                    sim_calls.append(end - begin)
                seen.add(stage)
        policy_calls = [end - begin for what, _, begin, end in stats.timeline if what == "policy"]
        pods_per_call = max(calls / max(len(sim_calls), 1), 1.0)
        pod_ms = 1000 * pods["vecsim_pod_step_seconds_sum"] / max(calls, 1)
        call_ms = 1000 * statistics.mean(sim_calls) if sim_calls else 0.0
        env_steps = max(pods["vecsim_pod_env_steps_total"], 1)
        rows.append(
            {
                "policy_ms": 1000 * statistics.mean(policy_calls) if policy_calls else 0.0,
                "stage_call_ms": call_ms,
                "pod_step_ms": pod_ms,
                "physics_ms_per_pod": 1000 * pods["vecsim_pod_physics_seconds_total"] / max(calls, 1),
                "render_ms_per_pod": 1000 * pods["vecsim_pod_render_seconds_total"] / max(calls, 1),
                "serving_ms": max(call_ms - pod_ms, 0.0),
                "physics_ms_per_env_step": 1000 * pods["vecsim_pod_physics_seconds_total"] / env_steps,
                "render_ms_per_env_step": 1000 * pods["vecsim_pod_render_seconds_total"] / env_steps,
                "envs_per_pod_call": pods["vecsim_pod_env_steps_total"] / max(calls, 1),
                "pods_per_call": pods_per_call,
                # The policy's batch: K actions per row, so rows per call = this / K.
                "env_steps_per_policy_call": stats.env_steps / max(len(policy_calls), 1),
            }
        )
    return {key: round(statistics.median(r[key] for r in rows), 2) for key in rows[0]}


def slowest_pod(measured: Sequence[Measured]) -> dict[str, Any]:
    """What waiting for the slowest pod costs. Per stage call (steps only): the client's round
    trips to the call's pods, their mean and the slowest one, medians over every call of the
    rollouts; ``wait_for_slowest_ms`` = slowest - mean. Also how often each pod was the slowest,
    and each pod's mean step wall time by its own ``/metrics`` (no HTTP)."""
    means, worsts, waits = [], [], []
    slowest_counts: dict[str, int] = {}
    sums: dict[str, list[float]] = {}
    for m in measured:
        by_pod: dict[str, list[float]] = {}
        for pod, op, begin, end in m.pod_calls:
            if op == "step":
                by_pod.setdefault(pod, []).append(end - begin)
        stages: dict[int, list[str]] = {}
        for pod in by_pod:
            stages.setdefault(m.stage_of_pod.get(pod, 0), []).append(pod)
        for pods in stages.values():
            for k in range(min(len(by_pod[p]) for p in pods)):
                times = {p: by_pod[p][k] for p in pods}
                mean, worst = statistics.mean(times.values()), max(times.values())
                means.append(mean)
                worsts.append(worst)
                waits.append(worst - mean)
                name = max(times, key=lambda p: times[p])
                slowest_counts[name] = slowest_counts.get(name, 0) + 1
        for pod, counters in m.per_pod.items():
            total = sums.setdefault(pod, [0.0, 0.0])
            total[0] += counters["vecsim_pod_step_seconds_sum"]
            total[1] += counters["vecsim_pod_step_seconds_count"]
    step_ms = {pod: round(1000 * s / c, 2) for pod, (s, c) in sums.items() if c > 0}

    def ms(values: list[float]) -> float | None:
        return round(1000 * statistics.median(values), 2) if values else None

    return {
        "calls": len(means),
        "pod_round_trip_mean_ms": ms(means),
        "pod_round_trip_slowest_ms": ms(worsts),
        "wait_for_slowest_ms": ms(waits),
        "slowest_pod_counts": dict(sorted(slowest_counts.items(), key=lambda item: -item[1])),
        "pod_step_ms_by_pod": step_ms,
        "pod_step_ms_spread": (
            {
                "min": min(step_ms.values()),
                "mean": round(statistics.mean(step_ms.values()), 2),
                "max": max(step_ms.values()),
            }
            if step_ms
            else {}
        ),
    }


def core_overlap(runs: Sequence[Measured], core_of: Mapping[str, int]) -> float:
    """The share of the pods' time in flight (the client's step and reset calls, summed over the
    pods) during which another pod pinned to the same core had a call in flight too, median over
    the rollouts: 0 when the pods of a core take turns, 1 when they always simulate together."""
    shares = []
    for m in runs:
        by_pod: dict[str, list[tuple[float, float]]] = {}
        for pod, _, begin, end in m.pod_calls:
            by_pod.setdefault(pod, []).append((begin, end))
        flights = {pod: merge(intervals) for pod, intervals in by_pod.items()}
        busy = together = 0.0
        for pod, own in flights.items():
            others = merge(i for p, f in flights.items() if p != pod and core_of.get(p) == core_of.get(pod) for i in f)
            busy += covered(own)
            together += intersection(own, others)
        shares.append(together / busy if busy > 0 else 0.0)
    return round(statistics.median(shares), 3) if shares else 0.0


def handoff(runs: Sequence[Measured]) -> dict[str, float | None]:
    """The trainer's side of a stage's turn, ms, medians over the rollouts' step calls (each a
    lane's call: its ``submitted_at`` to ``finished_at``, the client's whole call):

    - ``send``: from the end of the policy call that made a step call's actions to the call
      being submitted (the loop handing it to the client);
    - ``last_answer_to_policy``: from the last answer a policy call takes being in (its call
      finished) to that policy call starting;
    - ``last_answer_to_policy_idle``: the part of that spent outside any other stage's policy
      call: what waking, taking the answers and starting the policy cost, not the GPU being busy;
    - ``send_spread``: from the first to the last step call a policy call's actions went out in;
    - ``call_beyond_request``: a step call's time beyond its HTTP request to the pod (the
      client's work before and after it, and its wait to be run on the client's loop).
    """
    sends: list[float] = []
    handoffs: list[float] = []
    idles: list[float] = []
    spreads: list[float] = []
    beyond: list[float] = []
    for m in runs:
        requests: dict[str, list[tuple[float, float]]] = {}
        if m.started is not None:
            for pod, op, begin, end in m.pod_calls:
                if op == "step":
                    requests.setdefault(pod, []).append((begin - m.started, end - m.started))
        policies: dict[int, list[tuple[float, float]]] = {}
        for what, stage, begin, end in m.stats.timeline:
            if what == "policy":
                policies.setdefault(stage, []).append((begin, end))
        for calls in policies.values():
            calls.sort()
        last_in: dict[tuple[int, int], float] = {}  # (stage, policy call) -> its last answer's end
        sent: dict[tuple[int, float], list[float]] = {}  # (stage, the policy call's end) -> submit times
        for stage, pod, submitted, finished, _resets, steps in m.stats.pod_calls:
            if not steps:
                continue
            inside = [e - b for b, e in requests.get(pod, ()) if submitted <= b and e <= finished]
            if len(inside) == 1:
                beyond.append(finished - submitted - inside[0])
            own = policies.get(stage, [])
            if not own:
                continue
            made = [end for _, end in own if end <= submitted]
            if made:
                sends.append(submitted - made[-1])
                sent.setdefault((stage, made[-1]), []).append(submitted)
            taker = next((j for j, (begin, _) in enumerate(own) if begin >= finished), None)
            if taker is not None:
                last_in[(stage, taker)] = max(last_in.get((stage, taker), finished), finished)
        spreads.extend(max(times) - min(times) for times in sent.values())
        others = {
            stage: merge(call for s, calls in policies.items() if s != stage for call in calls) for stage in policies
        }
        for (stage, j), landed in last_in.items():
            begin = policies[stage][j][0]
            handoffs.append(begin - landed)
            idles.append(begin - landed - intersection([(landed, begin)], others[stage]))

    def ms(values: list[float]) -> float | None:
        return round(1000 * statistics.median(values), 2) if values else None

    return {
        "send": ms(sends),
        "send_spread": ms(spreads),
        "call_beyond_request": ms(beyond),
        "last_answer_to_policy": ms(handoffs),
        "last_answer_to_policy_idle": ms(idles),
    }


def thread_share(runs: Sequence[Measured]) -> dict[str, float]:
    """Where the trainer's thread spent a rollout's wall time, as fractions, medians over the
    rollouts: in policy calls (the inputs' preparation and the forward pass), waiting
    for a pod's answer, and on the rest of the loop (taking answers, buffering, sending actions)."""
    shares = []
    for m in runs:
        wall = max(m.stats.wall_s, 1e-9)
        policy, wait = m.stats.policy_s / wall, m.stats.wait_s / wall
        shares.append({"policy": policy, "wait": wait, "loop": max(1.0 - policy - wait, 0.0)})
    return {key: round(statistics.median(s[key] for s in shares), 3) for key in ("policy", "wait", "loop")}


def summarise(runs: Sequence[Measured]) -> dict[str, Any]:
    """Env-steps/s of one contender's rounds, its time split and the slowest-pod figures."""
    out = {
        "env_steps_per_s": rate_spread([m.env_steps_per_s for m in runs]),
        "time_split_ms": breakdown(runs),
        "slowest_pod": slowest_pod(runs),
        "overlap_fraction": round(statistics.median(m.stats.overlap_fraction for m in runs), 3),
        "thread_share": thread_share(runs),
        "handoff_ms": handoff(runs),
        "trajectories": int(statistics.median(m.stats.num_trajectories for m in runs)),
    }
    # With refill, how many trajectories each pod started (resets), in the first round: a pod on a
    # faster core takes more.
    started: dict[str, int] = {}
    for _, pod, _, _, resets, _ in runs[0].stats.pod_calls:
        started[pod] = started.get(pod, 0) + resets
    if started:
        out["trajectories_per_pod"] = {"min": min(started.values()), "max": max(started.values())}
    return out


def waiting(layout: str, wait_s: float, stages: int = 2) -> str:
    """The name of a contender of ``stages`` stages run with a ``--compare-batch-wait-s`` value."""
    return f"{layout}/stages={stages}/batch_wait={wait_s:g}s"
