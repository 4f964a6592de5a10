"""The local runner: supervised processes, and whole jobs of real controller and pod processes."""

from __future__ import annotations

import contextlib
import os
import secrets
import signal
import socket
import subprocess
import sys
from collections.abc import Iterator

import httpx
import psutil
import pytest
import yaml

from support.service_procs import free_port_block, wait_until

from service.probes import Probe, Probes
from service.runner import Backoff, JobRejectedError, LocalJob, ManagedProcess, PodStatus, format_status
from service.runner.main import main as up_main
from vecsim.config import CameraConfig, ControllerConfig, JobConfig, JobSpec, PodsConfig, RoutingTable

PYTHON = sys.executable


def tiny_config(replicas: int = 2, **job: object) -> JobConfig:
    base = free_port_block(replicas + 1)
    fields: dict[str, object] = dict(
        job_id="tiny-test",
        suite="tiny",
        group_size=1,
        num_stages=2,
        pods_per_stage=1,
        camera=CameraConfig(height=32, width=32),
        max_episode_steps=20,
    )
    fields.update(job)
    return JobConfig(
        job=JobSpec(**fields),
        pods=PodsConfig(replicas=replicas, base_port=base + 1, max_envs=8),
        controller=ControllerConfig(port=base, heartbeat_interval_s=0.5, heartbeat_ttl_s=3.0, reconcile_interval_s=0.2),
    )


# LocalJob's configuration of pods, without starting anything.


def test_pods_get_statefulset_names_ports_and_the_kubernetes_environment():
    config = tiny_config(replicas=3)
    job = LocalJob(config, namespace="ns1")
    base = config.pods.base_port
    assert job.pod_names == ["sim-0", "sim-1", "sim-2"]
    assert job.pod_env("sim-2") == {
        "POD_NAME": "sim-2",
        "POD_NAMESPACE": "ns1",
        "POD_IP": "127.0.0.1",
        "VECSIM_ADVERTISE_URL": f"http://127.0.0.1:{base + 2}",
        "CONTROLLER_URL": f"http://127.0.0.1:{config.controller.port}",
        "VECSIM_PORT": str(base + 2),
        "VECSIM_MAX_ENVS": "8",
        "VECSIM_HEARTBEAT_INTERVAL_S": "0.5",
        "VECSIM_HOST": "127.0.0.1",
    }


def test_an_unknown_pod_name_is_refused_naming_the_pods():
    with pytest.raises(KeyError, match="sim-0"):
        LocalJob(tiny_config()).pod_url("sim-7")


def test_a_job_with_too_few_replicas_is_refused_before_anything_starts(tmp_path):
    job = LocalJob(tiny_config(replicas=1), log_dir=tmp_path)
    with pytest.raises(JobRejectedError, match="raise pods.replicas to at least 2"):
        job.start()
    assert job.processes == {} and list(tmp_path.iterdir()) == []


def test_a_job_too_big_for_the_pods_is_refused_saying_what_to_change(tmp_path):
    job = LocalJob(tiny_config(group_size=4), log_dir=tmp_path)
    with pytest.raises(JobRejectedError, match="max_envs"):
        job.start()
    assert job.processes == {}


def test_a_job_whose_port_is_taken_is_refused_naming_the_port(tmp_path):
    config = tiny_config()
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", config.pods.base_port + 1))
        with pytest.raises(
            JobRejectedError, match=f"pods.base_port: port {config.pods.base_port + 1} on 127.0.0.1 is in use"
        ):
            LocalJob(config, log_dir=tmp_path).start()


def test_vecsim_up_with_a_broken_config_exits_2_naming_the_field(tmp_path, capsys):
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump({"job": {"suite": "tiny", "group_size": -1}}))
    assert up_main(["-c", str(path)]) == 2
    assert "group_size" in capsys.readouterr().err


def test_status_table_has_a_row_per_process_with_stage_tasks_and_restarts():
    rows = [
        PodStatus(name="controller", state="ready", pid=10, restarts=0, ready=True),
        PodStatus(
            name="sim-0",
            state="ready",
            pid=11,
            restarts=2,
            stage_id=0,
            tasks=("tiny/lift", "tiny/stack", "tiny/door"),
            num_envs=3,
            ready=True,
            generation=4,
        ),
    ]
    lines = format_status(rows).splitlines()
    assert lines[0].split() == ["POD", "STAGE", "TASKS", "ENVS", "READY", "GEN", "RESTARTS", "STATE", "PID"]
    assert lines[2].split() == ["sim-0", "0", "tiny/lift..tiny/door", "(3)", "3", "yes", "4", "2", "ready", "11"]


# ManagedProcess with real processes.


@pytest.fixture
def managed() -> Iterator[list[ManagedProcess]]:
    made: list[ManagedProcess] = []
    try:
        yield made
    finally:
        for process in made:
            process.stop(grace_s=2)


def test_a_crashing_process_is_restarted_with_backoff(managed, tmp_path):
    process = ManagedProcess(
        "crasher",
        [PYTHON, "-c", "import sys, time; time.sleep(0.1); sys.exit(3)"],
        env=os.environ,
        log_path=tmp_path / "crasher.log",
        backoff=Backoff(initial_s=0.05, max_s=0.2),
    )
    managed.append(process)
    process.start()
    wait_until(lambda: process.restarts >= 3, "three restarts", timeout_s=30)
    assert process.last_exit == "exited with code 3"
    assert (tmp_path / "crasher.log").read_text().count("=== ") >= 3


def test_stop_ends_the_whole_process_group_even_children_that_ignore_sigterm(managed, tmp_path):
    pid_file = tmp_path / "child.pid"
    script = (
        "import signal, subprocess, sys, time\n"
        "child = subprocess.Popen([sys.executable, '-c', "
        "'import signal, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); time.sleep(600)'])\n"
        f"open({str(pid_file)!r}, 'w').write(str(child.pid))\n"
        "time.sleep(600)\n"
    )
    process = ManagedProcess("parent", [PYTHON, "-c", script], env=os.environ, log_path=tmp_path / "p.log")
    managed.append(process)
    process.start()
    wait_until(lambda: pid_file.exists() and pid_file.read_text(), "the child's pid", timeout_s=30)
    child = psutil.Process(int(pid_file.read_text()))
    parent_pid = process.pid
    process.stop(grace_s=1)
    assert not psutil.pid_exists(parent_pid)
    assert not child.is_running() or child.status() == psutil.STATUS_ZOMBIE


def test_a_failing_liveness_probe_restarts_the_process_and_reruns_the_start_hook(managed, tmp_path):
    port = free_port_block(1)
    started: list[int] = []
    process = ManagedProcess(
        "web",
        [PYTHON, "-m", "http.server", str(port), "--bind", "127.0.0.1", "--directory", str(tmp_path)],
        env=os.environ,
        log_path=tmp_path / "web.log",
        url=f"http://127.0.0.1:{port}",
        # "/" answers 200; "/healthz" answers 404 from http.server, so liveness fails.
        probes=Probes(
            startup=Probe("/", period_s=0.1, failure_threshold=100, timeout_s=1),
            readiness=Probe("/", period_s=0.1, failure_threshold=3, timeout_s=1),
            liveness=Probe("/healthz", period_s=0.1, failure_threshold=3, timeout_s=1),
        ),
        backoff=Backoff(initial_s=0.05),
        grace_s=2,
        on_started=lambda: started.append(process.pid or 0),
    )
    managed.append(process)
    process.start()
    wait_until(lambda: process.restarts >= 1 and len(started) >= 2, "a restart and a second start", timeout_s=60)
    assert "liveness probe /healthz" in (process.last_exit or "")
    assert started[0] != started[1]


# Whole jobs: a real controller and real pods.


def routing(job: LocalJob) -> RoutingTable:
    return RoutingTable.model_validate(httpx.get(f"{job.controller_url}/v1/routing", timeout=5).json())


def layout(table: RoutingTable) -> list[tuple[int, str, tuple[str, ...]]]:
    return [(s.stage_id, p.pod, tuple(t.task_id for t in p.tasks)) for s in table.stages for p in s.pods]


def ready_at_least(job: LocalJob, generation: int) -> RoutingTable | None:
    try:
        if httpx.get(f"{job.controller_url}/readyz", timeout=2).status_code != 200:
            return None
        table = routing(job)
    except httpx.HTTPError:
        return None
    return table if table.ready and table.generation >= generation else None


@pytest.fixture(scope="module")
def tiny_job(tmp_path_factory) -> Iterator[LocalJob]:
    job = LocalJob(
        tiny_config(), log_dir=tmp_path_factory.mktemp("tiny-job"), grace_s=10, backoff=Backoff(initial_s=0.2)
    )
    with job:
        yield job


@pytest.mark.slow
def test_every_pod_registers_and_gets_ready_with_the_planned_routing(tiny_job):
    table = tiny_job.wait_ready(timeout=240)
    assert layout(table) == [
        (0, "sim-0", ("tiny/lift", "tiny/stack", "tiny/door")),
        (1, "sim-1", ("tiny/lift", "tiny/stack", "tiny/door")),
    ]
    for stage in table.stages:
        for pod in stage.pods:
            info = httpx.get(f"{pod.url}/v1/info", headers={"Accept": "application/json"}, timeout=5).json()
            assert (info["pod"], info["stage_id"], info["generation"], info["num_envs"]) == (
                pod.pod,
                stage.stage_id,
                table.generation,
                3,
            )
    pods = httpx.get(f"{tiny_job.controller_url}/v1/pods", timeout=5).json()
    assert [(p["pod"], p["url"], p["ready"]) for p in pods] == [
        (n, tiny_job.pod_url(n), True) for n in ("sim-0", "sim-1")
    ]


@pytest.mark.slow
def test_a_killed_pod_comes_back_under_its_name_into_its_slot_with_a_new_generation(tiny_job):
    before = tiny_job.wait_ready(timeout=240)
    process = tiny_job.processes["sim-1"]
    restarts, pid = process.restarts, process.pid
    os.kill(pid, signal.SIGKILL)
    after = wait_until(
        lambda: ready_at_least(tiny_job, before.generation + 1), "the job to be ready again", timeout_s=240
    )
    assert process.restarts == restarts + 1 and process.pid != pid
    assert layout(after) == layout(before)
    info = httpx.get(f"{tiny_job.pod_url('sim-1')}/v1/info", headers={"Accept": "application/json"}, timeout=5).json()
    assert info["generation"] == after.generation


@pytest.mark.slow
def test_a_restarted_controller_adopts_the_running_layout_without_reassigning(tiny_job):
    before = tiny_job.wait_ready(timeout=240)
    controller = tiny_job.processes["controller"]
    pid = controller.pid
    os.kill(pid, signal.SIGKILL)
    wait_until(lambda: controller.pid not in (None, pid), "a new controller process", timeout_s=60)
    after = wait_until(lambda: ready_at_least(tiny_job, 0), "the new controller to report the job ready", timeout_s=120)
    assert (after.generation, layout(after)) == (before.generation, layout(before))
    for name in ("sim-0", "sim-1"):
        info = httpx.get(f"{tiny_job.pod_url(name)}/v1/info", headers={"Accept": "application/json"}, timeout=5).json()
        assert info["generation"] == before.generation


@pytest.mark.slow
def test_ctrl_c_to_vecsim_up_leaves_no_process_behind(tmp_path):
    config = tiny_config(suite=None, tasks=("gym/Pendulum-v1",), camera=CameraConfig(names=()))
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(config.model_dump(mode="json")))
    runner = subprocess.Popen(
        [PYTHON, "-m", "service.cli", "up", "-c", str(path), "--log-dir", str(tmp_path / "logs"), "--grace", "10"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    started: list[psutil.Process] = []
    try:
        url = f"http://127.0.0.1:{config.controller.port}/readyz"

        def ready() -> bool:
            try:
                return httpx.get(url, timeout=2).status_code == 200
            except httpx.HTTPError:
                return False

        wait_until(ready, "vecsim up to get the job ready", timeout_s=240, every=0.5)
        started = psutil.Process(runner.pid).children(recursive=True)
        # Beyond the controller and the pods: the pods' own env worker processes.
        assert len(started) > len(psutil.Process(runner.pid).children()) == 3
        runner.send_signal(signal.SIGINT)
        output, _ = runner.communicate(timeout=60)
        assert runner.returncode == 0
        assert b"stopped." in output
        _, alive = psutil.wait_procs(started, timeout=10)
        assert alive == []
    finally:
        for process in [*started, psutil.Process(runner.pid) if runner.poll() is None else None]:
            if process is not None and process.is_running():
                process.kill()
        runner.wait(timeout=30)


def processes_marked(mark: str) -> list[psutil.Process]:
    """Every process of this user whose environment carries ``VECSIM_TEST_MARK=mark``."""
    found = []
    for process in psutil.process_iter():
        with contextlib.suppress(psutil.Error):
            if process.environ().get("VECSIM_TEST_MARK") == mark:
                found.append(process)
    return found


def port_held(port: int) -> bool:
    with socket.socket() as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind(("127.0.0.1", port))
        except OSError:
            return True
    return False


@pytest.mark.slow
def test_a_sigkilled_runner_leaves_no_process_and_no_port_behind(tmp_path):
    # SIGKILL lets the runner stop nothing itself: its children go because the kernel kills them
    # with it, the pods' workers because their parent goes with the pod.
    config = tiny_config(suite=None, tasks=("gym/Pendulum-v1",), camera=CameraConfig(names=()))
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(config.model_dump(mode="json")))
    mark = secrets.token_hex(8)
    runner = subprocess.Popen(
        [PYTHON, "-m", "service.cli", "up", "-c", str(path), "--log-dir", str(tmp_path / "logs")],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        env={**os.environ, "VECSIM_TEST_MARK": mark},
        start_new_session=True,
    )
    ports = [config.controller.port, *(config.pods.base_port + i for i in range(config.pods.replicas))]
    try:
        # Mid-rollout: the pods have started their env workers (more processes than the runner,
        # the controller and the two pods).
        wait_until(lambda: len(processes_marked(mark)) > 4, "the pods' env workers", timeout_s=240, every=0.2)
        assert any(port_held(port) for port in ports)
        runner.kill()
        runner.wait(timeout=10)
        wait_until(lambda: not processes_marked(mark), "every process the runner started to end", timeout_s=10)
        assert [port for port in ports if port_held(port)] == []
    finally:
        for process in processes_marked(mark):
            with contextlib.suppress(psutil.Error):
                process.kill()
        if runner.poll() is None:
            runner.kill()
        runner.wait(timeout=30)
