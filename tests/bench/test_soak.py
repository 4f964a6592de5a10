"""The soak benchmark at CI size: `bench/soak.py` for 30 s, three trainer clients, one job."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
from support import ROOT
from support.service_procs import clean_env

REPO = ROOT
CLIENTS = 3


@pytest.fixture(scope="module")
def soak(tmp_path_factory) -> dict:
    out = tmp_path_factory.mktemp("soak")
    result = subprocess.run(
        [
            sys.executable,
            str(REPO / "bench" / "soak.py"),
            "--seconds",
            "30",
            "--window-s",
            "10",
            "--clients",
            str(CLIENTS),
            "--json",
            str(out / "soak.json"),
            "--log-dir",
            str(out / "logs"),
        ],
        cwd=REPO,
        env=clean_env(),
        capture_output=True,
        text=True,
        timeout=420,
    )
    assert (out / "soak.json").exists(), result.stdout[-3000:] + result.stderr[-3000:]
    record = json.loads((out / "soak.json").read_text())
    record["returncode"] = result.returncode
    return record


@pytest.mark.slow
def test_several_clients_soak_one_job_without_a_single_error(soak):
    assert (soak["errors"], soak["details"]["errors"], soak["returncode"]) == (0, [], 0)
    assert soak["clients"] == CLIENTS and soak["env_steps"] > 0


@pytest.mark.slow
def test_every_window_of_the_soak_has_calls_and_a_p99_latency(soak):
    assert [w["window"] for w in soak["windows"]] == [0, 1, 2]
    for window in soak["windows"]:
        assert window["calls"] > 0 and window["p99_ms"] >= window["p50_ms"] > 0


@pytest.mark.slow
def test_pod_memory_is_reported_at_start_and_end_and_stays_flat(soak):
    start, end = soak["rss_mib_start"], soak["rss_mib_end"]
    assert set(start) == set(end) == {"controller", "sim-0", "sim-1"}
    for name in ("sim-0", "sim-1"):
        assert start[name] > 0 and end[name] > 0
        assert end[name] <= 1.25 * start[name], f"{name} grew from {start[name]} to {end[name]} MiB"
