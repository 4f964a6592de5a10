"""The README's first command: ``vecsim demo`` starts a job, rolls out, reports, and cleans up."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import psutil
import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
@pytest.mark.timeout(400)
def test_the_demo_rolls_out_on_a_local_job_writes_its_pictures_and_leaves_nothing_running(tmp_path: Path) -> None:
    out = tmp_path / "demo"
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    env.pop("VECSIM_TOKEN", None)
    started = psutil.Process().create_time()
    done = subprocess.run(
        [sys.executable, "-m", "vecsim.cli", "demo", "--out", str(out), "--batch", "6", "--horizon", "4",
         "--videos", "1", "--ready-timeout", "300"],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=380,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]

    assert "env-steps/s" in done.stdout and "policy time overlapped" in done.stdout
    summary = json.loads((out / "summary.json").read_text())
    assert summary["stats"]["num_trajectories"] == 6
    assert summary["stats"]["env_steps"] == 6 * 4
    routes = summary["routes"]
    assert {r["stage_id"] for r in routes.values()} == {0, 1}
    assert len({(r["pod"], r["env_index"]) for r in routes.values()}) == 6  # one env per trajectory
    assert (out / "timeline.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    (video,) = summary["videos"].values()
    assert Path(video).stat().st_size > 0
    assert _vecsim_processes_since(started) == [], "the demo left processes running"


def _vecsim_processes_since(started: float) -> list[str]:
    """Command lines of live vecsim processes (and their env workers) made after ``started``."""
    found = []
    for proc in psutil.process_iter(["cmdline", "create_time", "status"]):
        cmdline = " ".join(proc.info["cmdline"] or [])
        if proc.info["create_time"] >= started and proc.info["status"] != psutil.STATUS_ZOMBIE and (
            "vecsim.cli" in cmdline or "vecsim/cli" in cmdline or "bin/vecsim" in cmdline
        ):
            found.append(cmdline)
    return found
