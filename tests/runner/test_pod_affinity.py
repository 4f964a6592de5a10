"""Sharing the machine's CPUs between a local job's pods (``pods.cpu_affinity``), as CPU limits
share a Kubernetes node: by default each pod gets an equal share of the runner's CPUs; the config
names bad CPU lists, the runner refuses CPUs it may not use, and a started pod, its env workers
included, runs on exactly the CPUs it was given, with ``auto`` envs per worker sized to them.
Likewise ``pods.render_gpus``: the EGL device each pod (and its env workers) renders on."""

from __future__ import annotations

import os
import re
from collections.abc import Iterator

import httpx
import psutil
import pytest
from support.service_procs import free_port_block

from service.runner import JobRejectedError, LocalJob
from service.runner.job import MJWARP_GPU_ENV
from vecsim.config import (
    CameraConfig,
    ConfigError,
    ControllerConfig,
    JobConfig,
    JobSpec,
    PodsConfig,
    load_job_config,
)
from vecsim.engine.mjwarp.settings import GPU_ENV


def cheetah_config(
    cpu_affinity: str | tuple[str, ...], replicas: int = 1, render_gpus: tuple[int, ...] = (), envs_per_worker: int = 1
) -> JobConfig:
    """A job of two HalfCheetah envs on each of ``replicas`` pods (a stage each)."""
    base = free_port_block(replicas + 1)
    return JobConfig(
        job=JobSpec(
            job_id="pinned",
            tasks=("gym/HalfCheetah-v5",),
            group_size=2,
            num_stages=max(replicas, 1),
            pods_per_stage=1,
            camera=CameraConfig(names=()),
            envs_per_worker=envs_per_worker,
            max_episode_steps=50,
        ),
        pods=PodsConfig(
            replicas=replicas, base_port=base + 1, max_envs=8, cpu_affinity=cpu_affinity, render_gpus=render_gpus
        ),
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


def test_pods_take_cpu_lists_in_turn_and_run_unpinned_when_turned_off():
    pods = PodsConfig(replicas=3, cpu_affinity=("0", "1-2"))
    assert [pods.cpus_of(i, usable=range(4)) for i in range(3)] == [[0], [1, 2], [0]]
    assert PodsConfig(cpu_affinity="off").cpus_of(0, usable=range(4)) is None
    assert PodsConfig(cpu_affinity=()).cpus_of(0, usable=range(4)) is None


@pytest.mark.parametrize("replicas", [1, 2, 3, 4, 5, 7])
@pytest.mark.parametrize("usable", [[0], [0, 1], [2, 3, 5, 6], list(range(6))])
def test_auto_shares_the_usable_cpus_evenly_between_pods(replicas, usable):
    shares = [PodsConfig(replicas=replicas).cpus_of(i, usable=usable) for i in range(replicas)]
    assert PodsConfig().cpu_affinity == "auto"
    if replicas <= len(usable):
        # Disjoint, contiguous in the usable order, covering all, sizes one apart at most.
        assert [cpu for share in shares for cpu in share] == sorted(usable)
        assert max(map(len, shares)) - min(map(len, shares)) <= 1
    else:
        # More pods than CPUs: one CPU each, every CPU used, none twice more than another.
        assert all(len(share) == 1 for share in shares)
        counts = [sum(share == [cpu] for share in shares) for cpu in usable]
        assert min(counts) >= 1 and max(counts) - min(counts) <= 1


def test_a_cpu_affinity_neither_a_list_nor_auto_nor_off_is_refused_naming_the_field(tmp_path):
    path = tmp_path / "job.yaml"
    path.write_text("job: {tasks: [gym/HalfCheetah-v5]}\npods: {cpu_affinity: sometimes}\n")
    with pytest.raises(ConfigError, match=r"pods\.cpu_affinity"):
        load_job_config(path)


def test_pods_take_render_gpus_in_turn_and_a_negative_device_is_refused_naming_the_field(tmp_path):
    job = LocalJob(cheetah_config((), replicas=3, render_gpus=(1, 2)))
    assert [job.pod_env(f"sim-{i}").get("MUJOCO_EGL_DEVICE_ID") for i in range(3)] == ["1", "2", "1"]
    # The mjwarp engine's CUDA device, of the same number, by the variable the engine reads.
    assert MJWARP_GPU_ENV == GPU_ENV
    assert [job.pod_env(f"sim-{i}").get(GPU_ENV) for i in range(3)] == ["1", "2", "1"]
    assert not {"MUJOCO_EGL_DEVICE_ID", GPU_ENV} & set(LocalJob(cheetah_config(())).pod_env("sim-0"))
    path = tmp_path / "job.yaml"
    path.write_text("job: {tasks: [gym/HalfCheetah-v5]}\npods: {render_gpus: [-1]}\n")
    with pytest.raises(ConfigError, match=r"pods\.render_gpus"):
        load_job_config(path)


def test_a_job_pinned_to_cpus_the_machine_lacks_is_refused_before_anything_starts(tmp_path):
    missing = str(os.cpu_count() or 1)
    job = LocalJob(cheetah_config((missing,)), log_dir=tmp_path)
    with pytest.raises(
        JobRejectedError, match=rf"pods\.cpu_affinity: '{missing}' names CPUs \[{missing}\], but this machine"
    ):
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


def pod_tree(job: LocalJob, name: str) -> tuple[list[psutil.Process], list[psutil.Process]]:
    """Every process of pod ``name`` (itself first), and its env workers: the forkserver's children."""
    pod = psutil.Process(job.processes[name].pid)
    workers = [worker for child in pod.children() for worker in child.children()]
    return [pod, *pod.children(recursive=True)], workers


def pod_cpus_metric(url: str) -> float:
    text = httpx.get(f"{url}/metrics", timeout=10).text
    return float(re.search(r"^vecsim_pod_cpus (\S+)$", text, re.M).group(1))


@pytest.mark.timeout(240)
def test_by_default_each_pod_runs_on_its_own_share_of_the_runners_cpus(tmp_path):
    usable = sorted(os.sched_getaffinity(0))
    replicas = min(len(usable), 2)
    job = LocalJob(cheetah_config("auto", replicas=replicas, envs_per_worker=0), log_dir=tmp_path, grace_s=5)
    try:
        job.start()
        job.wait_ready(timeout=180)
        seen: list[int] = []
        for name in job.pod_names:
            share = job.pod_cpus(name)
            tree, workers = pod_tree(job, name)
            assert {proc.pid: sorted(proc.cpu_affinity()) for proc in tree} == {proc.pid: share for proc in tree}
            # envs_per_worker auto: one env worker per CPU of the share, for the pod's 2 envs.
            assert len(workers) == min(len(share), 2)
            assert pod_cpus_metric(job.pod_url(name)) == len(share)
            assert f"on CPUs {share}" in job.processes[name].log_tail(200)
            seen += share
    finally:
        job.stop()
    assert sorted(seen) == usable


@pytest.mark.timeout(180)
def test_pods_of_a_job_with_affinity_off_may_each_run_on_every_cpu_of_the_runner(tmp_path):
    job = LocalJob(cheetah_config("off", replicas=2), log_dir=tmp_path, grace_s=5)
    assert job.pod_cpus("sim-0") is None and job.pod_cpus("sim-1") is None
    try:
        job.start()
        job.wait_ready(timeout=120)
        for name in job.pod_names:
            tree, _ = pod_tree(job, name)
            assert all(sorted(proc.cpu_affinity()) == sorted(os.sched_getaffinity(0)) for proc in tree), name
            assert pod_cpus_metric(job.pod_url(name)) == len(os.sched_getaffinity(0))
    finally:
        job.stop()
