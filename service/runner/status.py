"""The runner's status view: one row per process, from the runner's own supervision and the
controller's registry and routing table."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import httpx

from vecsim.config import PodRecord, RoutingTable

from .process import ManagedProcess


@dataclass(frozen=True)
class PodStatus:
    """One process of a local job as the status table shows it."""

    name: str
    state: str  # the runner's view: pending, starting, running, ready, restarting, stopping
    pid: int | None
    restarts: int
    stage_id: int | None = None
    tasks: tuple[str, ...] = ()
    num_envs: int | None = None
    ready: bool | None = None  # the controller's view (None: unknown)
    generation: int | None = None


def collect_status(
    controller_url: str, processes: Mapping[str, ManagedProcess], timeout: float = 2.0
) -> list[PodStatus]:
    """Returns a row per process; pod rows carry what the controller knows (if it answers)."""
    records: dict[str, PodRecord] = {}
    routed: dict[str, tuple[int, tuple[str, ...], int]] = {}
    try:
        with httpx.Client(base_url=controller_url, timeout=timeout) as client:
            response = client.get("/v1/pods")
            if response.status_code == 200:
                records = {record.pod: record for record in map(PodRecord.model_validate, response.json())}
            response = client.get("/v1/routing")
            if response.status_code == 200:
                table = RoutingTable.model_validate(response.json())
                for stage in table.stages:
                    for pod in stage.pods:
                        if pod.pod in routed:  # a pod of every stage ('slices'): no one stage, all its envs
                            _, tasks, num_envs = routed[pod.pod]
                            more = tuple(t.task_id for t in pod.tasks if t.task_id not in tasks)
                            routed[pod.pod] = (None, tasks + more, num_envs + pod.num_envs)
                        else:
                            tasks = tuple(dict.fromkeys(t.task_id for t in pod.tasks))
                            routed[pod.pod] = (stage.stage_id, tasks, pod.num_envs)
    except (httpx.HTTPError, ValueError):
        pass
    rows = []
    for name, process in processes.items():
        record = records.get(name)
        stage_id, tasks, num_envs = routed.get(name, (None, (), None))
        rows.append(
            PodStatus(
                name=name,
                state=process.state,
                pid=process.pid,
                restarts=process.restarts,
                stage_id=stage_id,
                tasks=tasks,
                num_envs=num_envs,
                ready=record.ready if record is not None else (process.ready if name == "controller" else None),
                generation=record.generation if record is not None else None,
            )
        )
    return rows


def _tasks_cell(tasks: tuple[str, ...]) -> str:
    if len(tasks) <= 2:
        return ",".join(tasks) or "-"
    return f"{tasks[0]}..{tasks[-1]} ({len(tasks)})"


def _cell(value: object) -> str:
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    return str(value)


def format_status(rows: list[PodStatus]) -> str:
    """Returns the rows as an aligned text table (pod, stage, tasks, envs, ready, ...)."""
    header = ("POD", "STAGE", "TASKS", "ENVS", "READY", "GEN", "RESTARTS", "STATE", "PID")
    lines = [header] + [
        (
            r.name,
            _cell(r.stage_id),
            _tasks_cell(r.tasks),
            _cell(r.num_envs),
            _cell(r.ready),
            _cell(r.generation),
            str(r.restarts),
            r.state,
            _cell(r.pid),
        )
        for r in rows
    ]
    widths = [max(len(line[i]) for line in lines) for i in range(len(header))]
    return "\n".join("  ".join(cell.ljust(w) for cell, w in zip(line, widths)).rstrip() for line in lines)
