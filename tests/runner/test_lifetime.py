"""Processes that never outlive their parent (:mod:`vecsim.lifetime`): on Linux the kernel
kills them when their parent dies, even by SIGKILL, which lets the parent stop nothing itself."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys

import psutil
import pytest

from support import ROOT
from support.service_procs import PodSpec, standalone_pods

pytestmark = pytest.mark.skipif(sys.platform != "linux", reason="PR_SET_PDEATHSIG is Linux's")

PYTHON = sys.executable
# A parent that starts a long-sleeping child tied to it, prints the child's pid and sleeps on.
PARENT = """
import functools, os, subprocess, sys, time
from vecsim.lifetime import exit_with_parent
child = subprocess.Popen(
    [sys.executable, "-c", "import time; time.sleep(120)"],
    preexec_fn=functools.partial(exit_with_parent, os.getpid()),
)
print(child.pid, flush=True)
time.sleep(120)
"""


def test_a_child_dies_with_its_parent_killed_by_sigkill() -> None:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    parent = subprocess.Popen([PYTHON, "-c", PARENT], stdout=subprocess.PIPE, text=True, env=env)
    child = None
    try:
        child = psutil.Process(int(parent.stdout.readline()))
        parent.kill()
        parent.wait(timeout=10)
        _, alive = psutil.wait_procs([child], timeout=10)
        assert alive == []
    finally:
        if parent.poll() is None:
            parent.kill()
        parent.wait(timeout=10)
        parent.stdout.close()
        if child is not None:
            with contextlib.suppress(psutil.Error):
                child.kill()


def test_a_child_whose_parent_is_already_gone_exits_before_running_its_program() -> None:
    gone = subprocess.Popen([PYTHON, "-c", "pass"])
    gone.wait(timeout=30)
    code = f"from vecsim.lifetime import exit_with_parent; exit_with_parent({gone.pid}); print('ran')"
    proc = subprocess.run([PYTHON, "-c", code], capture_output=True, text=True, timeout=60, cwd=ROOT, check=False)
    assert (proc.returncode, proc.stdout) == (1, "")


@pytest.mark.slow
def test_a_pods_stuck_env_workers_end_when_the_pod_alone_is_sigkilled(tmp_path) -> None:
    with standalone_pods([PodSpec("sim-0", 0, [("gym/Pendulum-v1", 2)])], tmp_path) as (pod,):
        # The env workers are the forkserver's children; the forkserver ends with the pod.
        forkserver_and_tracker = psutil.Process(pod.pid).children()
        workers = [w for p in forkserver_and_tracker for w in p.children()]
        assert len(workers) == 2, "one worker process per env"
        try:
            # Stopped, they stand for workers busy in a long step or build: they would never
            # read that their pipe closed.
            for worker in workers:
                worker.suspend()
            # Not its process group: the workers are left to the kernel.
            os.kill(pod.pid, signal.SIGKILL)
            _, alive = psutil.wait_procs(workers, timeout=10)
            assert alive == []
        finally:
            for worker in workers:
                with contextlib.suppress(psutil.Error):
                    worker.kill()
