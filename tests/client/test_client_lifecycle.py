"""Starting and stopping, as a trainer and an operator meet them: a trainer started before the
job waits for it, Ctrl-C and exceptions leave the client usable and the interpreter's exit quiet,
``vecsim up`` restarts on the ports it just left, and probe requests stay out of the INFO logs.

Everything runs real processes on loopback: standalone pods, or whole jobs of the local runner.
"""

from __future__ import annotations

import logging
import os
import re
import signal
import subprocess
import sys
import textwrap
import threading
import time
from collections.abc import Iterator
from contextlib import closing

import gymnasium
import httpx
import numpy as np
import pytest
import yaml
from gymnasium.error import ResetNeeded
from gymnasium.vector.async_vector_env import AsyncState
from support.service_procs import (
    PodSpec,
    assignment_file,
    controller_server,
    free_port,
    job_config,
    pod_server,
    running,
    standalone_pods,
    wait_until,
)

from service.runner.job import LocalJob
from vecsim import trees
from vecsim.client import HTTPVectorEnv, StageClient
from vecsim.config import CameraConfig

PENDULUM = "gym/Pendulum-v1"
TOKEN = "lifecycle-token-0123456789abcdef0123"
PENDULUM_JOB = {"job_id": "lifecycle", "tasks": [PENDULUM], "group_size": 2, "num_stages": 1, "camera": {"names": []}}
# Rendering 256x256 cameras makes a step take about a tenth of a second, so that an interrupt
# lands while the step is in flight.
SLOW = PodSpec("sim-0", 0, [("tiny/lift", 2)], camera=CameraConfig(height=256, width=256), render=None)
STATE_IDS = np.array([1, 2])


def interrupt_main_after(delay_s: float) -> threading.Timer:
    """SIGINT to the main thread after ``delay_s``: a real Ctrl-C, which wakes a blocked wait."""
    timer = threading.Timer(delay_s, signal.pthread_kill, (threading.main_thread().ident, signal.SIGINT))
    timer.start()
    return timer


def interrupt_main_while_stepping(env: HTTPVectorEnv, after_s: float) -> threading.Thread:
    """SIGINT to the main thread, after ``after_s``, as soon as ``env`` has a step out that is not
    yet answered: a real Ctrl-C inside ``step``'s wait."""

    def step_out() -> bool:
        pending = env._pending
        return env._state == AsyncState.WAITING_STEP and pending is not None and not pending.done()

    def fire() -> None:
        time.sleep(after_s)  # let a few whole steps pass first; not synchronisation
        wait_until(step_out, "a step in flight", timeout_s=60, every=0.0005)
        signal.pthread_kill(threading.main_thread().ident, signal.SIGINT)

    thread = threading.Thread(target=fire, daemon=True)
    thread.start()
    return thread


@pytest.fixture
def default_sigint() -> Iterator[None]:
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


@pytest.fixture(scope="module")
def slow_pod(tmp_path_factory) -> Iterator[str]:
    with standalone_pods([SLOW], tmp_path_factory.mktemp("slow-pod")) as pods:
        yield pods[0].url


def test_make_vec_started_before_the_job_waits_for_its_controller_to_listen(tmp_path, caplog):
    config = job_config(PENDULUM_JOB, replicas=1)
    url = f"http://127.0.0.1:{config.controller.port}"
    job = LocalJob(config, log_dir=tmp_path, grace_s=10, token=TOKEN)
    starter = threading.Timer(2.0, job.start)  # the trainer is first: nothing listens yet
    starter.start()
    try:
        with caplog.at_level(logging.INFO, logger="vecsim.client.stage"):
            env = gymnasium.make_vec(
                "vecsim/HTTPVectorEnv-v0", num_envs=2, controller_url=url, wait_ready_s=240, timeout_s=30, token=TOKEN
            )
        with closing(env):
            obs, _ = env.reset(seed=0)
            assert env.num_envs == 2 and obs.shape == (2, 3)
            env.step(np.zeros((2, 1), np.float32))
    finally:
        starter.join()
        job.stop()
    waits = [r.getMessage() for r in caplog.records if r.levelno == logging.INFO and "waiting for" in r.getMessage()]
    assert waits and f"{url}/v1/routing" in waits[0] and "ConnectError" in waits[0]


def test_a_client_gives_up_on_a_controller_that_never_listens_naming_the_url_and_the_wait():
    url = f"http://127.0.0.1:{free_port()}"
    with pytest.raises(TimeoutError, match=re.escape("waited 1.0 s")) as caught:
        StageClient.from_controller(url, timeout_s=1, wait_ready_s=1.0)
    assert f"{url}/v1/routing" in str(caught.value) and "ConnectError" in str(caught.value)


@pytest.mark.slow
def test_ctrl_c_inside_step_leaves_the_next_reset_working_with_true_results(slow_pod, default_sigint):
    with closing(HTTPVectorEnv(pod_urls=[slow_pod], timeout_s=30)) as env:
        first, _ = env.reset(options={"state_ids": STATE_IDS})
        actions = np.zeros((2, *env.single_action_space.shape), np.float32)
        for _ in range(3):
            # Ctrl-C once a step is out and not yet answered, after a few whole steps: a Ctrl-C
            # between two steps would interrupt no call (and leave nothing to reset).
            timer = interrupt_main_while_stepping(env, after_s=0.25)
            with pytest.raises(KeyboardInterrupt):
                for _ in range(100_000):
                    env.step(actions)
            timer.join()
            # The interrupted step's envs are in an unknown state: a step is refused until a reset.
            with pytest.raises(ResetNeeded, match="interrupted"):
                env.step(actions)
            again, _ = env.reset(options={"state_ids": STATE_IDS})
            assert again.keys() == first.keys()
            for now, then in zip(trees.leaves(again), trees.leaves(first)):
                np.testing.assert_array_equal(now, then)


@pytest.mark.slow
def test_ctrl_c_while_an_answer_is_taken_in_leaves_the_envs_to_be_reset(slow_pod, monkeypatch):
    # The call was answered, but what the env holds of it is partly the old step's: no step
    # goes on from there; a reset does, with true results.
    with closing(HTTPVectorEnv(pod_urls=[slow_pod], timeout_s=30)) as env:
        first, _ = env.reset(options={"state_ids": STATE_IDS})
        actions = np.zeros((2, *env.single_action_space.shape), np.float32)
        applied = env._results.take_step

        def interrupted(*args):
            applied(*args)
            raise KeyboardInterrupt

        monkeypatch.setattr(env._results, "take_step", interrupted)
        with pytest.raises(KeyboardInterrupt):
            env.step(actions)
        monkeypatch.undo()
        with pytest.raises(ResetNeeded, match="interrupted"):
            env.step(actions)
        again, _ = env.reset(options={"state_ids": STATE_IDS})
        for now, then in zip(trees.leaves(again), trees.leaves(first)):
            np.testing.assert_array_equal(now, then)


@pytest.mark.slow
def test_ctrl_c_while_waiting_on_a_stage_call_frees_the_stage_at_once(slow_pod, default_sigint):
    with StageClient.from_pods([slow_pod], timeout_s=30) as client:
        client.reset_trajectories([("tiny/lift", 1), ("tiny/lift", 2)], ["a", "b"])
        client.reset_stage(0).result()
        action = np.zeros(client.action_space.shape, np.float32)
        timer = interrupt_main_after(0.25)
        with pytest.raises(KeyboardInterrupt):
            while True:
                pending = client.step_stage(0, {"a": action, "b": action})
                pending.result()
        timer.join()
        assert pending.done()
        batch = client.reset_stage(0).result()
    assert batch.traj_keys == ["a", "b"] and list(batch.state_ids) == [1, 2]


SCRIPT = """
import faulthandler, signal, sys, threading
# Ctrl-C as in a terminal: a shell that started the tests in the background left SIGINT ignored,
# and Python then installs no KeyboardInterrupt handler for its children.
signal.signal(signal.SIGINT, signal.default_int_handler)
# A hang shows where: every thread's stack on stderr, and the script ends, before the test's timeout.
faulthandler.dump_traceback_later(90, exit=True)
import numpy as np
from vecsim.client import HTTPVectorEnv

env = HTTPVectorEnv(pod_urls=[sys.argv[1]], timeout_s=30)
env.reset(options={"state_ids": np.array([1, 2])})
actions = np.zeros((2, *env.single_action_space.shape), np.float32)
env.step(actions)
if sys.argv[2] == "raise":
    raise RuntimeError("the trainer failed mid-rollout")
threading.Timer(0.25, signal.pthread_kill, (threading.main_thread().ident, signal.SIGINT)).start()
while True:
    env.step(actions)
"""


@pytest.mark.parametrize("how", ["raise", "ctrl-c"])
@pytest.mark.slow
def test_a_script_ended_by_an_exception_or_ctrl_c_mid_rollout_exits_quietly(slow_pod, tmp_path, how):
    script = tmp_path / "rollout.py"
    script.write_text(textwrap.dedent(SCRIPT))
    done = subprocess.run([sys.executable, str(script), slow_pod, how], capture_output=True, text=True, timeout=120)
    assert done.returncode != 0
    expected = "RuntimeError: the trainer failed mid-rollout" if how == "raise" else "KeyboardInterrupt"
    assert expected in done.stderr, done.stderr[-6000:]
    for noise in ("Exception ignored", "Unclosed", "Cannot close a running event loop"):
        assert noise not in done.stderr, done.stderr


@pytest.mark.slow
def test_a_job_restarts_on_the_same_ports_at_once_after_it_stopped(tmp_path):
    config = job_config(PENDULUM_JOB, replicas=1)
    first = LocalJob(config, log_dir=tmp_path / "first", grace_s=10, token=TOKEN)
    with first:
        table = first.wait_ready(timeout=240)
        # Kept-alive connections the servers close when they stop: TIME_WAIT on their own ports.
        with httpx.Client(timeout=10) as http:
            http.get(f"{first.controller_url}/v1/routing")
            http.get(f"{table.stages[0].pods[0].url}/healthz")
            first.stop()
    second = LocalJob(config, log_dir=tmp_path / "second", grace_s=10, token=TOKEN)
    with second:
        assert second.wait_ready(timeout=240).ready


def info_lines(log: str, path: str) -> list[str]:
    """The lines of ``log`` logged at INFO that name ``path``."""
    return [line for line in log.splitlines() if re.search(r"\bINFO\b", line) and path in line]


@pytest.mark.slow
def test_vecsim_up_logs_its_probes_at_debug_and_the_job_it_sent_at_info(tmp_path):
    config = job_config(PENDULUM_JOB, replicas=1)
    path = tmp_path / "job.yaml"
    path.write_text(yaml.safe_dump(config.model_dump(mode="json")))
    runner = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "service.cli",
            "up",
            "-c",
            str(path),
            "--log-dir",
            str(tmp_path / "logs"),
            "--grace",
            "10",
            "--status-every",
            "1",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
        env={**os.environ, "VECSIM_TOKEN": TOKEN},
    )
    try:
        with closing(HTTPVectorEnv(job_config=config, wait_ready_s=240, token=TOKEN)) as env:
            env.reset(seed=0)
    finally:
        runner.send_signal(signal.SIGINT)
        output, _ = runner.communicate(timeout=60)
    assert runner.returncode == 0, output
    assert info_lines(output, "/v1/job"), output  # the runner's real request
    for probe in ("/healthz", "/readyz", "/v1/pods"):
        assert info_lines(output, probe) == [], output


@pytest.mark.slow
def test_pod_and_controller_access_logs_keep_probes_out_of_info(tmp_path):
    path = assignment_file(tmp_path, "sim-0", [(PENDULUM, 1)], stage_id=0)
    pod = pod_server("sim-0", tmp_path, args=["--assignment", str(path), "--access-log"])
    controller = controller_server(tmp_path, args=["--access-log"])
    with running(pod, ready=True), running(controller):
        for server, real in ((pod, "/v1/info"), (controller, "/v1/pods")):
            for probe in ("/healthz", "/readyz", "/healthz?verbose=1"):
                httpx.get(f"{server.url}{probe}", timeout=10)
            assert httpx.get(f"{server.url}{real}", timeout=10).status_code == 200
    for server, real in ((pod, "/v1/info"), (controller, "/v1/pods")):
        log = server.log_text()
        assert info_lines(log, f"GET {real}"), log
        assert info_lines(log, "/healthz") == [] and info_lines(log, "/readyz") == [], log
