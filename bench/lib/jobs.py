"""Building a bench's local job: what one run builds (:class:`Plan`), its job config, starting it,
waiting for its routing table, and regrouping the table's pods into the trainer's stages.

Light to import (no torch, no pods' code at the top): a bench checks its options with
:class:`Plan` and :func:`parse_stage_layouts` before its heavy imports, so a refused option exits
at once.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import shutil
import tempfile
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import httpx
import psutil

from vecsim.config import (
    Assignment,
    CameraConfig,
    JobConfig,
    LiberoProtocol,
    RoutedPod,
    RoutedStage,
    RoutingTable,
    TaskBlock,
)

if TYPE_CHECKING:
    import torch

ROBOT_CAMERAS = ("agentview", "robot0_eye_in_hand")
MAX_EPISODE_STEPS = 520
# RLinf's LIBERO protocol (docs/trainers.md): 15 settle steps inside its reset(), with the
# gripper opening (reset_gripper_open: true, as vecsim's settle action does), and its fixtures
# placed as a fresh env's first reset places them (RLinf seeds an env before every reset). The
# mjwarp engine serves every LIBERO-10 task under it; its scenes are exported under it.
RLINF_PROTOCOL = LiberoProtocol(settle_steps=15, fixture_rule="first_reset")
STAGE_LAYOUTS = ("slices", "pods")  # vecsim.config.StageLayout's values, in --stage-layout's default order


def one_task_assignment(task: str, envs: int, size: int, engine: str) -> Assignment:
    """Pod ``sim-0``'s assignment for an engine built in process: ``envs`` envs of one task on
    ``engine``, both robot cameras at ``size`` x ``size`` (0: no camera)."""
    camera = CameraConfig(names=ROBOT_CAMERAS if size else (), height=size or 128, width=size or 128)
    return Assignment(
        generation=0,
        pod="sim-0",
        stage_id=0,
        engine=engine,
        camera=camera,
        tasks=(TaskBlock(task_id=task, env_start=0, num_envs=envs),),
    )


@dataclasses.dataclass(frozen=True)
class Plan:
    """What one run builds and measures. ``tasks`` is every pod's task mix (one block per task,
    ``envs_per_task`` envs each, all in one worker process)."""

    mode: str  # "scaling", "pipeline" or "render"
    tasks: tuple[str, ...]
    size: int
    envs_per_task: int
    pods: int
    pod_counts: tuple[int, ...]
    pipeline_cores: int
    horizon: int
    service_steps: int
    rounds: int
    device: str
    dtype: str
    vit_width: int
    vit_max_depth: int
    max_memory_gib: float
    deadline_s: float
    render_preset: str = "lean"
    render_gpu: int | None = None  # the EGL device pods render on (None: the default one)
    chunk: int = 1  # actions per env per call (the policy's chunk K)
    batch_wait_s: float = 0.0  # pipeline: EnvLoop's batch_wait_s (how long it gathers a stage's answers)
    # pipeline: also each 2-stage layout with each of these batch_wait_s, side by side
    compare_batch_wait_s: tuple[float, ...] = ()
    stage_layouts: tuple[str, ...] = ("slices", "pods")  # the 2-stage layouts measured
    pods_per_core: int = 2  # pipeline: pods pinned to each of the pipeline_cores cores
    compare_stages: tuple[int, ...] = ()  # pipeline: also 'slices' in each of these stage counts (>= 3)

    @property
    def envs_per_pod(self) -> int:
        return len(self.tasks) * self.envs_per_task

    @property
    def torch_dtype(self) -> torch.dtype:
        import torch

        return torch.bfloat16 if self.dtype == "bfloat16" else torch.float32


def camera(plan: Plan) -> dict[str, Any]:
    """The job's cameras: LIBERO's two (gym tasks: their one render camera), ``size`` square."""
    names = ("render",) if plan.tasks[0].startswith("gym/") else ROBOT_CAMERAS
    return {"names": list(names), "height": plan.size, "width": plan.size}


def job_config(plan: Plan, pins: Sequence[str], job_id: str, replicas: int) -> JobConfig:
    """``replicas`` pods, each serving the plan's whole task mix (``envs_per_task`` envs of each
    task) in one worker process: one job stage per pod, since the controller gives every stage
    every task. Pod ``i`` is pinned to ``pins[i % len(pins)]``."""
    from .pods import free_port, free_port_block  # the service's code, loaded only here: see above

    return JobConfig.model_validate(
        {
            "job": {
                "job_id": job_id,
                "tasks": list(plan.tasks),
                "group_size": plan.envs_per_task,
                "num_stages": replicas,
                "pods_per_stage": 1,
                "camera": camera(plan),
                "render": plan.render_preset,
                "envs_per_worker": plan.envs_per_pod,
                "max_episode_steps": MAX_EPISODE_STEPS,
            },
            "pods": {
                "replicas": replicas,
                "base_port": free_port_block(replicas),
                "max_envs": max(64, plan.envs_per_pod),
                "cpu_affinity": list(pins),
                "render_gpus": [] if plan.render_gpu is None else [plan.render_gpu],
            },
            "controller": {
                "port": free_port(),
                "heartbeat_interval_s": 2.0,
                "heartbeat_ttl_s": 60.0,
                "reconcile_interval_s": 0.5,
            },
        }
    )


@contextlib.contextmanager
def running_job(config: JobConfig, keep_logs: Path | None = None, env: dict[str, str] | None = None) -> Iterator[Any]:
    """Start a LocalJob (not waiting for it); yield it; stop every process it started on exit.
    When the body fails, the job's logs go to ``keep_logs/<job id>-logs.tar.gz``."""
    from service.runner.job import LocalJob

    job = LocalJob(config, log_dir=tempfile.mkdtemp(prefix="vecsim-gpu-scale-"), env=env, grace_s=10)
    try:
        job.start()
        yield job
    except BaseException:
        if keep_logs is not None:
            keep_logs.mkdir(parents=True, exist_ok=True)
            shutil.make_archive(str(keep_logs / f"{config.job.job_id}-logs"), "gztar", job.log_dir)
        raise
    finally:
        job.stop()


def wait_for_job(job: Any, timeout_s: float) -> RoutingTable:
    """Wait for the job to be ready, at most ``timeout_s``, failing as soon as a pod says its
    envs failed to build (its ``/readyz`` detail) rather than at the timeout.

    Raises:
        RuntimeError: a pod's build failed (names the pod and its error).
        TimeoutError, CrashLoopError, JobRejectedError: as ``LocalJob.wait_ready``.
    """
    end = time.monotonic() + timeout_s
    while True:
        left = end - time.monotonic()
        try:
            return job.wait_ready(timeout=max(min(5.0, left), 0.5))
        except TimeoutError:
            if left <= 5.0:
                raise
        for name in job.pod_names:
            with contextlib.suppress(httpx.HTTPError, ValueError):
                answer = httpx.get(f"{job.pod_url(name)}/readyz", timeout=5)
                detail = str(answer.json().get("detail", "")) if answer.status_code == 503 else ""
                if "failed" in detail:
                    raise RuntimeError(f"{name}: {detail}")


def pod_processes(job: Any) -> dict[str, dict[str, Any]]:
    """Per pod: its processes (the server and its env workers, the forkserver included) and
    their summed resident memory, GiB."""
    out = {}
    for name in job.pod_names:
        pid = job.processes[name].pid
        tree: list[psutil.Process] = []
        with contextlib.suppress(psutil.Error, TypeError):
            root = psutil.Process(pid)
            tree = [root, *root.children(recursive=True)]
        rss = 0
        for process in tree:
            with contextlib.suppress(psutil.Error):
                rss += process.memory_info().rss
        out[name] = {"processes": len(tree), "rss_gib": round(rss / 2**30, 2)}
    return out


def regroup(table: RoutingTable, pods: Sequence[str], stages: int) -> RoutingTable:
    """The trainer's view: the named pods of the job's table, in order, in ``stages`` stages."""
    by_name = {p.pod: p for stage in table.stages for p in stage.pods}
    per_stage = math.ceil(len(pods) / stages)
    grouped = [
        RoutedStage(stage_id=s, pods=tuple(by_name[name] for name in pods[s * per_stage : (s + 1) * per_stage]))
        for s in range(stages)
    ]
    return table.model_copy(update={"stages": tuple(grouped)})


def regroup_slices(table: RoutingTable, pods: Sequence[str], stages: int) -> RoutingTable:
    """The trainer's view in the ``slices`` layout: every named pod in every stage, its envs
    alternating stage by stage in env order, as ``vecsim.plan.slice_blocks`` lays out a
    ``slices`` job's pods. The alternation runs on from one pod to the next (the k-th env of
    all the pods' envs is on stage ``k % stages``), so that stages stay equal in size when a pod
    has an odd number of envs and the pods an even one."""
    by_name = {p.pod: p for stage in table.stages for p in stage.pods}
    grouped: list[list[RoutedPod]] = [[] for _ in range(stages)]
    first = 0  # the stage of the next pod's first env
    for name in pods:
        routed = by_name[name]
        envs = [(b.task_id, e) for b in routed.tasks for e in range(b.env_start, b.env_start + b.num_envs)]
        for s in range(stages):
            mine = envs[(s - first) % stages :: stages]
            blocks = tuple(TaskBlock(task_id=task, env_start=env, num_envs=1, stage_id=s) for task, env in mine)
            grouped[s].append(routed.model_copy(update={"tasks": blocks, "num_envs": len(blocks)}))
        first = (first + len(envs)) % stages
    stage_list = tuple(RoutedStage(stage_id=s, pods=tuple(grouped[s])) for s in range(stages))
    return table.model_copy(update={"stages": stage_list})


def requests_for(table: RoutingTable, waves: int = 1) -> list[tuple[str, int]]:
    """One request per env of the table, interleaved so that request ``i`` is on stage ``i % S``;
    with ``waves`` > 1, that many such lists one after another (each wave's state ids moved on by
    7), for EnvLoop's refill: an env whose trajectory ends takes the next request of its task.

    Raises:
        ValueError: the stages differ in size (request i's stage is i % S: they must not).
    """
    sizes = [stage.num_envs for stage in table.stages]
    if len(set(sizes)) > 1:
        raise ValueError(f"stages of {sizes} envs: every stage needs as many envs (change the pods or envs per task)")
    per_stage = [
        [
            (block.task_id, (pod_index * 7 + k) % 50)
            for pod_index, pod in enumerate(stage.pods)
            for block in pod.tasks
            for k in range(block.num_envs)
        ]
        for stage in table.stages
    ]
    one = [per_stage[i % len(per_stage)][i // len(per_stage)] for i in range(sum(map(len, per_stage)))]
    return [(task_id, (state_id + 7 * wave) % 50) for wave in range(waves) for task_id, state_id in one]


def parse_stage_layouts(text: str) -> tuple[str, ...]:
    """``--stage-layout``'s comma-separated layouts, in order, each once.

    Raises:
        SystemExit: none given, or one that is not in ``STAGE_LAYOUTS``.
    """
    layouts = tuple(dict.fromkeys(x for x in text.split(",") if x))
    if not layouts or set(layouts) - set(STAGE_LAYOUTS):
        raise SystemExit(f"--stage-layout: a comma-separated list of {list(STAGE_LAYOUTS)}, got {text!r}")
    return layouts
