"""Pinning a local job's pods to CPUs (``pods.cpu_affinity``), as a CPU limit confines a pod in
Kubernetes: the config names bad CPU lists, the runner refuses CPUs the machine lacks, and a
started pod, its env workers included, runs on exactly the CPUs it was given. Likewise
``pods.render_gpus``: the EGL device each pod (and its env workers) renders on."""

from __future__ import annotations

import os
from collections.abc import Iterator

import psutil
import pytest
from support.service_procs import free_port_block

from service.runner import JobRejectedError, LocalJob
from vecsim.config import (
    CameraConfig,
    ConfigError,
    ControllerConfig,
    JobConfig,
    JobSpec,
    PodsConfig,
    load_job_config,
)


def cheetah_config(
    cpu_affinity: tuple[str, ...], replicas: int = 1, render_gpus: tuple[int, ...] = ()
) -> JobConfig:
    base = free_port_block(replicas + 1)
    return JobConfig(
        job=JobSpec(
            job_id="pinned", tasks=("gym/HalfCheetah-v5",), group_size=2, num_stages=1, pods_per_stage=replicas,
            camera=CameraConfig(names=()), envs_per_worker=1, max_episode_steps=50,
        ),
        pods=PodsConfig(replicas=replicas, base_port=base + 1, max_envs=8, cpu_affinity=cpu_affinity,
                        render_gpus=render_gpus),
        controller=ControllerConfig(port=base, heartbeat_interval_s=0.5, heartbeat_ttl_s=5.0, reconcile_interval_s=0.2),
    )


def test_a_malformed_cpu_list_in_a_job_config_is_refused_naming_the_field(tmp_path):
    path = tmp_path / "job.yaml"
    path.write_text("job: {tasks: [gym/HalfCheetah-v5]}\npods: {cpu_affinity: ['0-x']}\n")
    with pytest.raises(ConfigError, match=r"pods\.cpu_affinity.*'0-x' is not a CPU list"):
        load_job_config(path)


def test_a_cpu_range_that_runs_backwards_is_refused():
    with pytest.raises(ValueError, match="runs backwards"):
        PodsConfig(cpu_affinity=("3-1",))


def test_pods_take_cpu_lists_in_turn_and_run_unpinned_without_any():
    pods = PodsConfig(replicas=3, cpu_affinity=("0", "1-2"))
    assert [pods.cpus_of(i) for i in range(3)] == ["0", "1-2", "0"]
    assert PodsConfig().cpus_of(0) is None


def test_pods_take_render_gpus_in_turn_and_a_negative_device_is_refused_naming_the_field(tmp_path):
    job = LocalJob(cheetah_config((), replicas=3, render_gpus=(1, 2)))
    assert [job.pod_env(f"sim-{i}").get("MUJOCO_EGL_DEVICE_ID") for i in range(3)] == ["1", "2", "1"]
    assert "MUJOCO_EGL_DEVICE_ID" not in LocalJob(cheetah_config(())).pod_env("sim-0")
    path = tmp_path / "job.yaml"
    path.write_text("job: {tasks: [gym/HalfCheetah-v5]}\npods: {render_gpus: [-1]}\n")
    with pytest.raises(ConfigError, match=r"pods\.render_gpus"):
        load_job_config(path)


def test_a_pinned_pod_runs_its_usual_command_under_taskset():
    unpinned = LocalJob(cheetah_config(())).pod_argv("sim-0")
    assert unpinned[-3:] == ["-m", "service.cli", "pod"]
    assert LocalJob(cheetah_config(("0",))).pod_argv("sim-0") == ["taskset", "-c", "0", *unpinned]


def test_a_job_pinned_to_cpus_the_machine_lacks_is_refused_before_anything_starts(tmp_path):
    missing = str(os.cpu_count() or 1)
    job = LocalJob(cheetah_config((missing,)), log_dir=tmp_path)
    with pytest.raises(JobRejectedError, match=rf"pods\.cpu_affinity: '{missing}' names CPUs \[{missing}\]"):
        job.start()
    assert job.processes == {}


@pytest.fixture
def pinned_job(tmp_path) -> Iterator[LocalJob]:
    cpu = max(os.sched_getaffinity(0))
    job = LocalJob(cheetah_config((str(cpu),), render_gpus=(0,)), log_dir=tmp_path, grace_s=5)
    try:
        job.start()
        job.wait_ready(timeout=120)
        yield job
    finally:
        job.stop()


@pytest.mark.timeout(180)
def test_a_pinned_pod_and_its_env_workers_run_only_on_their_cpu(pinned_job):
    cpu = max(os.sched_getaffinity(0))
    pod = psutil.Process(pinned_job.processes["sim-0"].pid)
    tree = [pod, *pod.children(recursive=True)]
    assert len(tree) >= 3  # the pod, its forkserver and at least one env worker
    assert {proc.pid: proc.cpu_affinity() for proc in tree} == {proc.pid: [cpu] for proc in tree}


@pytest.mark.timeout(180)
def test_a_pod_and_its_env_workers_get_the_egl_device_it_was_given(pinned_job):
    pod = psutil.Process(pinned_job.processes["sim-0"].pid)
    tree = [pod, *pod.children(recursive=True)]
    assert {proc.pid: proc.environ().get("MUJOCO_EGL_DEVICE_ID") for proc in tree} == {proc.pid: "0" for proc in tree}
