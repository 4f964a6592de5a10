"""Pure routing: where each trajectory runs, given a routing table. No I/O here.

A trajectory is placed once, on a free env of its task on a pod of its stage, and the answer is
explicit: ``traj_key -> TrajRoute(pod, env_index, task_id, stage_id, state_id)``. Nothing
downstream recomputes it from a convention.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from vecsim.client.errors import CapacityError
from vecsim.config import RoutedPod, RoutedStage, RoutingTable, TaskBlock
from vecsim.plan import stage_of

__all__ = [
    "RoutedEnv",
    "TrajRoute",
    "changed_routes",
    "place_requests",
    "routed_envs",
    "routing_from_pod_infos",
    "stage_by_id",
    "validate_routes",
]


@dataclass(frozen=True)
class TrajRoute:
    """Where one trajectory runs for its whole episode."""

    pod: str
    env_index: int
    task_id: str
    stage_id: int
    state_id: int


@dataclass(frozen=True)
class RoutedEnv:
    """One env of a job as the routing table places it: ``(pod, env_index)``, its task and its
    stage (an ``HTTPVectorEnv``'s sub-env is one of these for its whole life)."""

    pod: str
    env_index: int
    task_id: str
    stage_id: int


def stage_by_id(table: RoutingTable) -> dict[int, RoutedStage]:
    """Return the table's stages keyed by stage id.

    A pod may be in several stages (the ``slices`` layout), each time with env ids of its own.

    Raises:
        ValueError: the stage ids are not exactly ``0..S-1``, a pod appears twice in one stage,
            or one env of a pod appears in two stages.
    """
    stages = {stage.stage_id: stage for stage in table.stages}
    if sorted(stages) != list(range(len(table.stages))):
        raise ValueError(
            f"routing table generation {table.generation}: stage ids must be 0..{len(table.stages) - 1}, "
            f"got {[s.stage_id for s in table.stages]}"
        )
    owner: dict[tuple[str, int], int] = {}
    for stage in table.stages:
        names = [pod.pod for pod in stage.pods]
        if len(set(names)) != len(names):
            twice = next(name for name in names if names.count(name) > 1)
            raise ValueError(
                f"routing table generation {table.generation}: pod {twice} appears twice in stage {stage.stage_id}"
            )
        for pod in stage.pods:
            for block in pod.tasks:
                for env in range(block.env_start, block.env_start + block.num_envs):
                    other = owner.setdefault((pod.pod, env), stage.stage_id)
                    if other != stage.stage_id:
                        raise ValueError(
                            f"routing table generation {table.generation}: env {env} of pod {pod.pod} is in "
                            f"stages {other} and {stage.stage_id}; an env belongs to one stage"
                        )
    return stages


def routed_envs(table: RoutingTable) -> list[RoutedEnv]:
    """Return every env of the table in stage-major order: stage, then pod, then env index.

    Raises:
        ValueError: as :func:`stage_by_id`.
    """
    stages = stage_by_id(table)
    envs = []
    for stage_id in sorted(stages):
        for pod in stages[stage_id].pods:
            for block in pod.tasks:
                envs.extend(
                    RoutedEnv(pod.pod, env, block.task_id, stage_id)
                    for env in range(block.env_start, block.env_start + block.num_envs)
                )
    return envs


def _task_at(pod: RoutedPod, env_index: int) -> str | None:
    for block in pod.tasks:
        if block.env_start <= env_index < block.env_start + block.num_envs:
            return block.task_id
    return None


def check_request(i: int, request: Any) -> tuple[str, int]:
    """Request ``i`` as ``(task_id, state_id)``; ``ValueError`` naming it when malformed."""
    if not isinstance(request, (tuple, list)) or len(request) != 2:
        raise ValueError(f"request {i}: expected a (task_id, state_id) pair, got {request!r}")
    task_id, state_id = request
    if not isinstance(task_id, str) or not task_id:
        raise ValueError(f"request {i}: task_id must be a non-empty str, got {task_id!r}")
    if isinstance(state_id, bool) or not hasattr(state_id, "__index__") or int(state_id) < 0:
        raise ValueError(f"request {i}: state_id must be an int >= 0, got {state_id!r}")
    return task_id, int(state_id)


def place_requests(
    table: RoutingTable,
    requests: Sequence[tuple[str, int]],
    traj_keys: Sequence[str],
    stages: Sequence[int] | None = None,
) -> dict[str, TrajRoute]:
    """Place request ``i`` on a free env of its task on a pod of stage ``stage_of(i, S)`` (or of
    stage ``stages[i]``, for a part of a larger batch that keeps the whole batch's stages).

    Within a stage a request goes to the pod with free envs of its task that holds the fewest
    trajectories of the batch so far (the pods of a stage step in parallel, so even loads finish
    together), then the one with the most free envs of the task, then the first; it takes that
    pod's lowest free env index of the task. Placement is a pure function of table and batch.
    Returns ``{traj_keys[i]: TrajRoute}`` in request order.

    Raises:
        ValueError: a malformed request, mismatched or duplicate traj_keys, or a table without
            stages for a non-empty batch (the message names the request or key).
        CapacityError: a stage lacks free envs of a task (names the task, the stage and the
            requests).
    """
    if len(traj_keys) != len(requests):
        raise ValueError(f"got {len(traj_keys)} traj_keys for {len(requests)} requests")
    if len(set(traj_keys)) != len(traj_keys):
        raise ValueError("traj_keys must be unique")
    if stages is not None and len(stages) != len(requests):
        raise ValueError(f"got {len(stages)} stages for {len(requests)} requests")
    checked = [check_request(i, r) for i, r in enumerate(requests)]
    if not checked:
        return {}
    by_id = stage_by_id(table)
    if not by_id:
        raise ValueError(f"routing table generation {table.generation} has no stages; is the job ready?")
    if stages is not None:
        for i, stage_id in enumerate(stages):
            if stage_id not in by_id:
                stages_in_table = f"stages 0..{len(by_id) - 1}"
                raise ValueError(f"request {i}: stage {stage_id} is not in the routing table ({stages_in_table})")
    stage_ids = list(stages) if stages is not None else [stage_of(i, len(by_id)) for i in range(len(checked))]

    # free[stage][task][pod] = env indices not yet taken, lowest first (popped from the end)
    free: dict[int, dict[str, dict[str, list[int]]]] = {}
    for stage_id, stage in by_id.items():
        by_task: dict[str, dict[str, list[int]]] = {}
        for pod in stage.pods:
            for block in pod.tasks:
                envs = list(range(block.env_start + block.num_envs - 1, block.env_start - 1, -1))
                by_task.setdefault(block.task_id, {}).setdefault(pod.pod, []).extend(envs)
        free[stage_id] = by_task

    wanted: dict[tuple[int, str], list[int]] = {}
    for i, (task_id, _) in enumerate(checked):
        wanted.setdefault((stage_ids[i], task_id), []).append(i)
    for (stage_id, task_id), indices in wanted.items():
        pods = free[stage_id].get(task_id, {})
        capacity = sum(len(envs) for envs in pods.values())
        if len(indices) > capacity:
            raise CapacityError(task_id, stage_id, capacity, indices, sorted(pods))

    load: dict[str, int] = {}
    routes = {}
    for i, (task_id, state_id) in enumerate(checked):
        stage_id = stage_ids[i]
        pods = free[stage_id][task_id]
        pod = min((name for name in pods if pods[name]), key=lambda name: (load.get(name, 0), -len(pods[name])))
        load[pod] = load.get(pod, 0) + 1
        routes[traj_keys[i]] = TrajRoute(pod, pods[pod].pop(), task_id, stage_id, state_id)
    return routes


def validate_routes(table: RoutingTable, routes: Mapping[str, TrajRoute]) -> None:
    """Check that every route names an env of its task on a pod of its stage, none shared.

    Raises:
        ValueError: naming the first traj_key whose route does not fit the table.
    """
    stages = stage_by_id(table)
    pods = {(stage_id, pod.pod): pod for stage_id, stage in stages.items() for pod in stage.pods}
    on_stages: dict[str, list[int]] = {}
    for stage_id, name in pods:
        on_stages.setdefault(name, []).append(stage_id)
    taken: dict[tuple[str, int], str] = {}
    for key, route in routes.items():
        if route.pod not in on_stages:
            raise ValueError(f"traj_key {key}: pod {route.pod} is not in routing generation {table.generation}")
        pod = pods.get((route.stage_id, route.pod))
        if pod is None:
            raise ValueError(
                f"traj_key {key}: pod {route.pod} is on stage(s) {on_stages[route.pod]}, not {route.stage_id}"
            )
        task = _task_at(pod, route.env_index)
        if task is None:
            raise ValueError(
                f"traj_key {key}: env {route.env_index} of pod {route.pod} is not one of stage {route.stage_id}'s envs"
            )
        if task != route.task_id:
            raise ValueError(
                f"traj_key {key}: env {route.env_index} of pod {route.pod} runs {task!r}, not {route.task_id!r}"
            )
        if route.state_id < 0:
            raise ValueError(f"traj_key {key}: state_id must be >= 0, got {route.state_id}")
        other = taken.setdefault((route.pod, route.env_index), key)
        if other != key:
            raise ValueError(f"traj_keys {other} and {key} share env {route.env_index} of pod {route.pod}")


def changed_routes(old: RoutingTable, new: RoutingTable, routes: Mapping[str, TrajRoute]) -> list[str]:
    """Return the traj_keys whose pod is not the same in ``new`` as in ``old``.

    A pod is the same when it keeps its URL and its task blocks in every stage it is in; any
    change to its blocks makes it rebuild its envs, so every trajectory on it is gone.
    """

    def index(table: RoutingTable) -> dict[str, dict[int, RoutedPod]]:
        pods: dict[str, dict[int, RoutedPod]] = {}
        for stage in table.stages:
            for pod in stage.pods:
                pods.setdefault(pod.pod, {})[stage.stage_id] = pod
        return pods

    def same(was: dict[int, RoutedPod], now: dict[int, RoutedPod]) -> bool:
        return sorted(was) == sorted(now) and all(
            was[s].url == now[s].url and was[s].tasks == now[s].tasks for s in was
        )

    before, after = index(old), index(new)
    moved = []
    for key, route in routes.items():
        was, now = before.get(route.pod), after.get(route.pod)
        if (
            was is None
            or now is None
            or not same(was, now)
            or route.stage_id not in now
            or _task_at(now[route.stage_id], route.env_index) != route.task_id
        ):
            moved.append(key)
    return moved


def _read_pod_info(url: str, info: Any) -> tuple[dict[int, RoutedPod], int | None, bool]:
    """``({stage_id: pod}, generation, ready)`` out of one pod's ``/v1/info`` answer: the pod
    once per stage it holds envs of (blocks without a stage of their own serve the pod's).

    Raises:
        ValueError: the answer is not a pod's (a field missing or of the wrong kind; URL named),
            or a block has no stage and neither has the pod.
    """
    unstaged = False
    try:
        name = str(info["pod"])
        pod_stage = info.get("stage_id")
        by_stage: dict[int, list[TaskBlock]] = {}
        for t in info["tasks"]:
            stage = t.get("stage_id")
            stage = pod_stage if stage is None else stage
            if stage is None:
                unstaged = True
                break
            by_stage.setdefault(int(stage), []).append(
                TaskBlock(
                    task_id=t["task_id"], env_start=t["env_start"], num_envs=t["num_envs"], stage_id=t.get("stage_id")
                )
            )
        if not by_stage and pod_stage is None:
            unstaged = True
        elif not by_stage:
            by_stage[int(pod_stage)] = []
        routed = {
            stage: RoutedPod(pod=name, url=url, num_envs=sum(b.num_envs for b in blocks), tasks=tuple(blocks))
            for stage, blocks in by_stage.items()
        }
        if len(routed) == 1 and pod_stage is not None:
            # One stage: the pod's num_envs, as it reports it.
            routed = {
                stage: pod.model_copy(update={"num_envs": int(info["num_envs"])}) for stage, pod in routed.items()
            }
        generation = info.get("generation")
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        what = f"no {exc} field" if isinstance(exc, KeyError) else f"{type(exc).__name__}: {exc}"
        raise ValueError(f"the /v1/info answer of {url} is not a pod's ({what})"[:500]) from None
    if unstaged:
        raise ValueError(f"pod {name} at {url} has no stage")
    return routed, None if generation is None else int(generation), bool(info.get("ready"))


def routing_from_pod_infos(infos: Sequence[tuple[str, Mapping[str, Any]]], job_id: str = "standalone") -> RoutingTable:
    """Build a routing table from pods' ``GET /v1/info`` answers, given as ``(url, info)`` pairs.

    For pods started without a controller (``vecsim pod --stage K ...``).

    Raises:
        ValueError: an answer that is not a pod's, a pod without a stage, pods on different
            generations, or a duplicate pod name.
    """
    pods = [_read_pod_info(url, info) for url, info in infos]
    generations = {generation for _, generation, _ in pods}
    if len(generations) > 1:
        raise ValueError(f"pods disagree on the generation: {sorted(map(str, generations))}")
    by_stage: dict[int, list[RoutedPod]] = {}
    seen: set[str] = set()
    for routed, _, _ in pods:
        name = next(iter(routed.values())).pod
        if name in seen:
            raise ValueError(f"two pods are named {name}")
        seen.add(name)
        for stage, pod in routed.items():
            by_stage.setdefault(stage, []).append(pod)
    generation = generations.pop() if generations else 0
    return RoutingTable(
        generation=int(generation or 0),
        job_id=job_id,
        ready=all(ready for _, _, ready in pods),
        stages=tuple(RoutedStage(stage_id=s, pods=tuple(by_stage[s])) for s in sorted(by_stage)),
    )
