"""Workers that host envs of several tasks: a worker's run of env indices crosses task blocks.

Shown on two gymnasium tasks that share their spaces (HalfCheetah v4 and v5: cheap, no rendering)
and on the tiny suite with 8x8 cameras; every answer is compared with one env per worker.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from typing import Any

import mujoco
import numpy as np
import pytest
from support import ROOT
from support.sim_envs import (
    CAMERAS,
    NO_CAMERA,
    TINY_CAMERA,
    env_rows,
    kill_worker,
    sim_assignment,
)

from vecsim.engine.batch_render import shared_renderer
from vecsim.config import AUTO_ENVS_PER_WORKER
from vecsim.engine import (
    InvalidRequestError,
    SimCrashedError,
    TaskGroupedVectorEnv,
    UnknownEnvError,
    assignment_spaces,
    resolve_envs_per_worker,
)
from vecsim.engine.protocol import Order
from vecsim.engine.worker import Worker, WorkerSpec

CHEETAH_V5 = "gym/HalfCheetah-v5"
CHEETAH_V4 = "gym/HalfCheetah-v4"


def _actions(n: int, size: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-1.0, 1.0, (n, size)).astype(np.float32)


def _play(pod: TaskGroupedVectorEnv, size: int) -> list[tuple[list[bytes], np.ndarray]]:
    """Reset every env to its own state, then step all, then some on both sides of each boundary."""
    ids = np.arange(pod.num_envs)
    obs, _ = pod.reset_envs(ids[::-1], (ids * 3 + 1)[::-1])
    answers = [(env_rows(obs), np.zeros(0))]
    for seed, chosen in enumerate((ids, ids[1::2], ids[::-1])):
        out = pod.step_envs(chosen, _actions(len(chosen), size, seed=seed))
        answers.append((env_rows(out[0]), out[1]))
    return answers


# Cheetahs of two tasks: v5 envs 0-2, v4 envs 3-4; three per worker puts envs 2 | 3 in one worker.
CHEETAH_BLOCKS = [(CHEETAH_V5, 3), (CHEETAH_V4, 2)]


@pytest.fixture(scope="module")
def cheetah_pods() -> Iterator[tuple[TaskGroupedVectorEnv, TaskGroupedVectorEnv]]:
    """The same two-task cheetahs, three envs per worker (v5 v5 v5 | v4 v4 pad) and one per worker."""
    with TaskGroupedVectorEnv(sim_assignment(CHEETAH_BLOCKS, envs_per_worker=3, max_episode_steps=5)) as packed:
        with TaskGroupedVectorEnv(sim_assignment(CHEETAH_BLOCKS, envs_per_worker=1, max_episode_steps=5)) as single:
            yield packed, single


@pytest.fixture(scope="module")
def spanning_cheetahs() -> Iterator[TaskGroupedVectorEnv]:
    """v5 v5 | v5 v4 | v4: worker 1 hosts the last v5 env and the first v4 env."""
    with TaskGroupedVectorEnv(sim_assignment(CHEETAH_BLOCKS, envs_per_worker=2, max_episode_steps=5)) as pod:
        yield pod


def test_a_worker_hosts_consecutive_envs_across_task_blocks(spanning_cheetahs: TaskGroupedVectorEnv) -> None:
    pod = spanning_cheetahs
    assert pod.task_ids == [CHEETAH_V5] * 3 + [CHEETAH_V4] * 2
    assert (pod.num_envs, pod.num_workers, len(set(pod.worker_pids))) == (5, 3, 3)


def test_envs_packed_across_tasks_serve_what_one_env_per_worker_serves(
    cheetah_pods: tuple[TaskGroupedVectorEnv, ...], spanning_cheetahs: TaskGroupedVectorEnv
) -> None:
    packed, single = cheetah_pods
    expected = _play(single, 6)
    for pod in (packed, spanning_cheetahs):
        got = _play(pod, 6)
        assert [rows for rows, _ in got] == [rows for rows, _ in expected]
        assert all(np.array_equal(a, b) for (_, a), (_, b) in zip(got, expected))


def test_stepping_one_side_of_a_boundary_leaves_the_other_side_where_it_was(
    spanning_cheetahs: TaskGroupedVectorEnv,
) -> None:
    pod = spanning_cheetahs
    move = _actions(1, 6, seed=11)
    pod.reset_envs([2, 3], [4, 4])
    untouched = env_rows(pod.step_envs([3], move)[0])
    pod.reset_envs([2, 3], [4, 4])
    pod.step_envs([2], move)
    pod.step_envs([2], move)
    assert env_rows(pod.step_envs([3], move)[0]) == untouched


def test_resetting_one_side_of_a_boundary_leaves_the_other_side_where_it_was(
    spanning_cheetahs: TaskGroupedVectorEnv,
) -> None:
    pod = spanning_cheetahs
    moves = _actions(2, 6, seed=12)
    pod.reset_envs([2, 3], [6, 6])
    first = env_rows(pod.step_envs([2, 3], moves)[0])
    second = env_rows(pod.step_envs([2, 3], moves)[0])
    pod.reset_envs([2, 3], [6, 6])
    pod.step_envs([2, 3], moves)
    _, info = pod.reset_envs([3], [6])
    assert info["task_id"] == [CHEETAH_V4]
    assert env_rows(pod.step_envs([2, 3], moves)[0]) == [second[0], first[1]]


def test_an_env_of_either_task_ends_its_episode_on_its_own_count(spanning_cheetahs: TaskGroupedVectorEnv) -> None:
    pod = spanning_cheetahs
    pod.reset_envs([2, 3], [0, 0])
    for _ in range(4):
        pod.step_envs([2, 3], _actions(2, 6))
    pod.reset_envs([3], [0])
    _, _, _, truncated, _ = pod.step_envs([2, 3], _actions(2, 6))
    assert truncated.tolist() == [True, False]


def test_more_envs_per_worker_than_envs_makes_one_worker_hosting_fewer_than_it_could() -> None:
    with TaskGroupedVectorEnv(sim_assignment(CHEETAH_BLOCKS, envs_per_worker=8, max_episode_steps=5)) as wide:
        assert (wide.num_workers, wide.envs_per_worker, len(wide.worker_pids)) == (1, 8, 1)
        with TaskGroupedVectorEnv(sim_assignment(CHEETAH_BLOCKS, envs_per_worker=1, max_episode_steps=5)) as single:
            got, expected = _play(wide, 6), _play(single, 6)
    assert [rows for rows, _ in got] == [rows for rows, _ in expected]
    with pytest.raises(UnknownEnvError, match="env 5 does not exist"):
        wide.reset_envs([5], [0])


BAD_CALLS = [
    pytest.param(
        UnknownEnvError,
        "env 5 does not exist; this pod has envs 0..4",
        lambda p: p.step_envs([2, 5], _actions(2, 6)),
        id="unknown_env",
    ),
    pytest.param(
        InvalidRequestError,
        "state 50 for env 3 is out of range 0..49 of task 'gym/HalfCheetah-v4'",
        lambda p: p.reset_envs([2, 3], [0, 50]),
        id="state_of_the_second_task",
    ),
    pytest.param(
        InvalidRequestError,
        "env 3 is named more than once",
        lambda p: p.reset_envs([3, 2, 3], [0, 0, 0]),
        id="duplicate_env",
    ),
    pytest.param(
        InvalidRequestError,
        "the action for env 3 is not finite",
        lambda p: p.step_envs([2, 3], [[0.0] * 6, [np.nan] * 6]),
        id="nan_action",
    ),
]


@pytest.mark.parametrize(("error", "message", "call"), BAD_CALLS)
def test_bad_input_to_a_spanning_worker_raises_its_named_error_and_changes_nothing(
    spanning_cheetahs: TaskGroupedVectorEnv, error: type[Exception], message: str, call: Any
) -> None:
    pod = spanning_cheetahs
    moves = _actions(2, 6, seed=13)
    pod.reset_envs([2, 3], [1, 1])
    expected = env_rows(pod.step_envs([2, 3], moves)[0])
    pod.reset_envs([2, 3], [1, 1])
    with pytest.raises(error, match=message):
        call(pod)
    assert env_rows(pod.step_envs([2, 3], moves)[0]) == expected


def test_a_dead_worker_is_named_with_every_task_it_hosted() -> None:
    with TaskGroupedVectorEnv(sim_assignment(CHEETAH_BLOCKS, envs_per_worker=2)) as pod:
        kill_worker(pod.worker_pids[1])
        with pytest.raises(
            SimCrashedError,
            match=r"worker 1 hosting gym/HalfCheetah-v5 \(envs 2-2\), "
            r"gym/HalfCheetah-v4 \(envs 3-3\) died",
        ):
            pod.reset_envs([0], [0])


def test_a_spanning_worker_reports_its_physics_time() -> None:
    with TaskGroupedVectorEnv(sim_assignment(CHEETAH_BLOCKS, envs_per_worker=5)) as pod:
        pod.step_envs([2, 3], _actions(2, 6))
        assert pod.last_timing.physics_s > 0.0


# Robot scenes with cameras.

TINY_BLOCKS = [("tiny/lift", 1), ("tiny/door", 2)]


@pytest.mark.slow
def test_robot_envs_of_two_tasks_in_one_worker_match_one_env_per_worker() -> None:
    with TaskGroupedVectorEnv(sim_assignment(TINY_BLOCKS, TINY_CAMERA, envs_per_worker=3)) as packed:
        with TaskGroupedVectorEnv(sim_assignment(TINY_BLOCKS, TINY_CAMERA, envs_per_worker=1)) as single:
            assert (packed.num_workers, single.num_workers) == (1, 3)
            got, expected = _play(packed, 7), _play(single, 7)
            assert packed.last_timing.render_s > 0.0
    assert [rows for rows, _ in got] == [rows for rows, _ in expected]


def test_one_worker_renders_scenes_of_two_tasks_in_one_readback_per_scene() -> None:
    assignment = sim_assignment(TINY_BLOCKS, TINY_CAMERA, envs_per_worker=3)
    observation_space, action_space = assignment_spaces(assignment)
    tasks = ("tiny/lift", "tiny/door", "tiny/door")
    worker = Worker(WorkerSpec(tasks, (0, 1, 2), 3, TINY_CAMERA, "lean", 10, observation_space, action_space))
    try:
        worker.build()
        renderer = shared_renderer(TINY_CAMERA.height, TINY_CAMERA.width, "lean")
        views, readbacks = renderer.views_rendered, renderer.readbacks
        chunks = np.stack([[action_space.sample()] for _ in range(2)])  # a chunk of one action per env
        worker.run(Order(np.array([0, 2]), actions=chunks), Order(np.array([1]), state_ids=np.array([5])))
        assert renderer.views_rendered - views == 3 * len(CAMERAS)
        assert renderer.readbacks - readbacks == 2
        for slot, env in enumerate(worker._envs):
            own = env.render_images()
            assert all(np.array_equal(worker._out["obs"]["images"][name][slot], own[name]) for name in CAMERAS)
    finally:
        worker.close()


def test_a_built_worker_keeps_no_compiler_copy_of_its_scenes() -> None:
    assignment = sim_assignment([("tiny/lift", 1), ("tiny/stack", 1)])
    observation_space, action_space = assignment_spaces(assignment)
    spec = WorkerSpec(("tiny/lift", "tiny/stack"), (0, 1), 2, NO_CAMERA, "lean", 10, observation_space, action_space)
    worker = Worker(spec)
    try:
        assert worker.build()["envs"] == 2
        assert mujoco.mj_getCacheSize(mujoco.mj_getCache()) == 0
        model = worker._envs[0].inner.sim.model._model
        with tempfile.TemporaryDirectory() as folder, pytest.raises(mujoco.FatalError, match="No XML model"):
            mujoco.mj_saveLastXML(os.path.join(folder, "last.xml"), model)
    finally:
        worker.close()


# auto


def test_auto_packs_robot_scenes_with_cameras_over_the_cores_across_tasks() -> None:
    six = sim_assignment(
        [("tiny/lift", 2), ("tiny/stack", 2), ("tiny/door", 2)], TINY_CAMERA, envs_per_worker=AUTO_ENVS_PER_WORKER
    )
    assert resolve_envs_per_worker(six, cores=2) == 3
    assert resolve_envs_per_worker(six, cores=4) == 2
    assert resolve_envs_per_worker(six, cores=16) == 1


WARM_PROBE = """
import json, numpy as np
from support.sim_envs import TINY_CAMERA, sim_assignment
from vecsim.engine import assignment_spaces
from vecsim.engine.worker import Worker, WorkerSpec
from vecsim.engine.tasks import _fast_step
assignment = sim_assignment([("tiny/lift", 2)], TINY_CAMERA)
observation_space, action_space = assignment_spaces(assignment)
worker = Worker(WorkerSpec(("tiny/lift", "tiny/lift"), (0, 1), 2, TINY_CAMERA, "lean", 10, observation_space, action_space))
took = worker.build()
compiled = bool(_fast_step.osc_kernel().osc_substep.signatures)
env = worker._envs[0]
after_build = env.inner.sim.get_state().flatten().tolist()
worker._reset_env(0, 0)
again = env.inner.sim.get_state().flatten().tolist()
print(json.dumps({"took": took, "compiled": compiled, "same_state": after_build == again, "path": env.step_path}))
worker.close()
"""


@pytest.mark.slow
def test_the_build_warms_the_step_path_and_leaves_every_env_in_state_0() -> None:
    # A fresh interpreter: nothing compiled or loaded before the build. After it, the compiled
    # controller has run in this process (compiled, or loaded from numba's cache), and the env
    # it stepped is back in state 0 exactly as a reset to state 0 leaves it.
    tests = ROOT / "tests"
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(tests), str(tests.parent), os.environ.get("PYTHONPATH", "")]),
    }
    out = subprocess.run(
        [sys.executable, "-c", WARM_PROBE], env=env, capture_output=True, text=True, timeout=600, check=True
    )
    report = json.loads(out.stdout.strip().splitlines()[-1])
    assert report["path"] == "exact"
    assert report["compiled"] is True
    assert report["same_state"] is True
    assert set(report["took"]) == {"envs", "make", "reset", "warm", "render"} and report["took"]["envs"] == 2


FIRST_STEP_PROBE = """
import json, sys, numpy as np, numba
from support.sim_envs import TINY_CAMERA, sim_assignment
from vecsim.engine import assignment_spaces
from vecsim.engine.worker import Worker, WorkerSpec
from vecsim.engine.tasks import _fast_step

def compiled():
    # Every numba function loaded so far, with the signatures it has compiled or loaded.
    found = {"osc_substep": [str(s) for s in _fast_step.osc_kernel().osc_substep.signatures]}
    for name, module in list(sys.modules.items()):
        for attr, value in list(vars(module).items()) if module is not None else ():
            if isinstance(value, numba.core.dispatcher.Dispatcher):
                found[f"{name}.{attr}"] = [str(s) for s in value.signatures]
    return found

assignment = sim_assignment([("tiny/lift", 1)], TINY_CAMERA)
observation_space, action_space = assignment_spaces(assignment)
worker = Worker(WorkerSpec(("tiny/lift",), (0,), 1, TINY_CAMERA, "lean", 10, observation_space, action_space))
worker.build()
before = compiled()
worker._reset_env(0, 3)
action = np.random.default_rng(0).uniform(-1.0, 1.0, action_space.shape).astype(np.float32)
worker._envs[0].step(action)
after = compiled()
print(json.dumps({"new": {k: v for k, v in after.items() if before.get(k) != v}, "kernels": len(after)}))
worker.close()
"""


def test_after_the_build_a_first_step_with_a_turning_arm_compiles_or_loads_nothing() -> None:
    # A fresh interpreter: what the trainer's first step would compile or load from numba's
    # cache (robosuite's quat2mat runs only when the arm turns) the build has done already.
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(ROOT / "tests"), str(ROOT), os.environ.get("PYTHONPATH", "")]),
    }
    out = subprocess.run(
        [sys.executable, "-c", FIRST_STEP_PROBE], env=env, capture_output=True, text=True, timeout=600, check=True
    )
    report = json.loads(out.stdout.strip().splitlines()[-1])
    assert report["kernels"] > 1
    assert report["new"] == {}
