"""Ready means ready: a pod answers ``/readyz`` only after its build has warmed the first step
and the cameras, and its log says what it warmed and for how long (issue 28)."""

from __future__ import annotations

import re
from pathlib import Path

import httpx
import pytest
from support.service_procs import READY_TIMEOUT_S, assignment_file, pod_server, running, wait_until

from vecsim.config import CameraConfig

CAMERA = CameraConfig(names=("agentview",), height=32, width=32)
WORKER_WARMED = re.compile(
    r"worker 1/1 ready: tiny/lift .*warmed the first step (\d+\.\d) s, warmed the cameras (\d+\.\d) s"
)
WARM_UP_DONE = re.compile(
    r"warm-up done: first step \(step path, compiled kernels\) (\d+\.\d) s, first render of every camera (\d+\.\d) s"
)


@pytest.mark.timeout(READY_TIMEOUT_S + 120)
def test_a_pod_answers_ready_only_after_its_warm_up_and_logs_what_it_warmed(tmp_path: Path) -> None:
    path = assignment_file(tmp_path, "sim-warm", [("tiny/lift", 1)], camera=CAMERA)
    server = pod_server("sim-warm", tmp_path, args=["--assignment", str(path)])
    seen: list[tuple[int, bool]] = []  # (/readyz status, the warm-up's line in the log once it answered)

    def ready() -> bool:
        status = httpx.get(f"{server.url}/readyz", timeout=5).status_code
        seen.append((status, WARM_UP_DONE.search(server.log_text()) is not None))
        return status == 200

    with running(server):  # serving (/healthz) while it builds
        wait_until(ready, "sim-warm to be ready", READY_TIMEOUT_S, every=0.05)
        log = server.log_text()

    assert seen[0] == (503, False), "the pod answered ready before it had built and warmed its envs"
    assert all(logged for status, logged in seen if status == 200)
    assert {status for status, _ in seen} == {200, 503}
    worker = WORKER_WARMED.search(log)
    done = WARM_UP_DONE.search(log)
    assert worker is not None and done is not None, log[-3000:]
    assert float(done.group(1)) == float(worker.group(1))  # one worker: its own times
    assert float(done.group(2)) == float(worker.group(2))
    assert log.index(done.group(0)) < log.index("ready, 1 envs")
