"""The trainer's install is the client alone: ``pip install vecsim`` (no extras) brings no
simulator and no torch, and that is enough to open a job, reset, step and run ``HTTPVectorEnv``
and ``StageClient``. What the client needs from the tasks (spaces, instructions, numbers of
initial states) comes from the pods' ``/v1/info``.

``scripts/setup.sh`` builds that install in a venv of its own (``$VECSIM_VENV-client``); the
trainer's script runs there, against real pods started from the full install."""

from __future__ import annotations

import json
import os
import subprocess
from collections.abc import Callable
from pathlib import Path

import pytest
from support import ROOT
from support.service_procs import PodSpec, RunningPod

from vecsim.config import CameraConfig

VENV = Path(os.environ.get("VECSIM_VENV", Path.home() / ".cache" / "vecsim" / "venv"))
CLIENT_VENV = VENV.with_name(VENV.name + "-client")  # where scripts/setup.sh puts the client alone

TRAINER = r"""
import importlib.util, json, sys
import numpy as np

heavy = [m for m in ("torch", "mujoco", "robosuite", "libero", "fastapi", "uvicorn", "matplotlib") if importlib.util.find_spec(m)]
assert not heavy, f"the client's venv has {heavy}"

from vecsim.client import HTTPVectorEnv, StageClient

urls = sys.argv[1:]
with StageClient.from_pods(urls, timeout_s=120) as client:
    tasks = sorted(client.num_states)
    client.reset_trajectories([(t, 1) for t in tasks], [f"k{i}" for i in range(len(tasks))])
    stages = sorted({r.stage_id for r in client.routes.values()})
    batch = client.reset_stage(stages[0]).result(timeout=120)
    info = {"num_states": client.num_states, "instructions": client.instructions, "reset_keys": batch.traj_keys}

env = HTTPVectorEnv(pod_urls=urls, timeout_s=120)
try:
    obs, _ = env.reset(seed=0)
    actions = np.stack([env.single_action_space.sample() * 0 for _ in range(env.num_envs)])
    obs, reward, terminated, truncated, _ = env.step(actions)
    info["vector"] = {"num_envs": env.num_envs, "reward_shape": list(np.shape(reward))}
finally:
    env.close()
info["loaded"] = sorted(m for m in ("torch", "mujoco", "robosuite", "libero", "service") if m in sys.modules)
print(json.dumps(info))
"""


@pytest.mark.slow
def test_the_client_alone_opens_a_job_resets_and_steps_without_simulator_or_torch(
    tmp_path: Path, start_pods: Callable[..., list[RunningPod]]
) -> None:
    python = CLIENT_VENV / "bin" / "python"
    if not python.exists():
        pytest.fail(f"no client-only venv at {CLIENT_VENV}: scripts/setup.sh builds it (run scripts/test.sh)")
    specs = [
        PodSpec("sim-0", 0, [("tiny/lift", 1)], camera=CameraConfig(names=("agentview",), height=16, width=16)),
        PodSpec("sim-1", 0, [("tiny/door", 1)], camera=CameraConfig(names=("agentview",), height=16, width=16)),
    ]
    pods = start_pods(specs)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env["PYTHONPATH"] = str(ROOT)  # this checkout's vecsim, whatever the venv's editable install points at
    done = subprocess.run(
        [str(python), "-c", TRAINER, *(p.url for p in pods)],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-4000:]
    seen = json.loads(done.stdout.strip().splitlines()[-1])
    assert seen["loaded"] == []
    assert seen["num_states"] == {"tiny/door": 50, "tiny/lift": 50}
    assert set(seen["instructions"]) == {"tiny/door", "tiny/lift"}
    assert seen["vector"] == {"num_envs": 2, "reward_shape": [2]}
