"""The ``mjwarp`` engine in a real pod on warp's CPU device, against a CPU pod of the same job.

Both pods are real: ``vecsim pod`` under uvicorn on loopback, one run by the ``mjwarp`` extra's
venv (``$VECSIM_VENV-mjwarp``, scripts/setup.sh; ``VECSIM_MJWARP_ALLOW_CPU=1``), one by the CPU
stack's (engine ``cpu``, LIBERO itself, the reference). libero_10/0's scene is exported by the
CPU stack for the test. Both are driven through the pod's REST API in the wire format, as the
client drives them: the same resets to LIBERO state ids, the same fixed action chunks.

- Resets answer the CPU pod's observation exactly (it was recorded from one at export).
- Over :data:`ACTIONS` the 8-float ``state`` and ``proprio`` stay within :data:`ATOL` of the CPU
  pod's; rewards, terminations, truncations (``max_episode_steps`` 6 ends the episode inside the
  second chunk), success and the actions applied are equal.
- **Determinism on warp's CPU device: on one pod, the same inputs give bit-identical outputs**
  (the same sequence run twice from a reset, and again after refused and empty calls, compares
  equal to the bit), unlike on the GPU (docs/mjwarp.md, Determinism). The guarantees below lean
  on it: "changes nothing" is checked as "the next call answers, bit for bit, what it answered
  before". A pod of another batch (2 worlds, another ``njmax``) parts in the last bits (7e-8 m).
- Envs a step leaves out do not move (MuJoCo Warp steps every world; the engine puts them back),
  and a refill (resets riding in a step) answers what a reset then a step answer.
- Refused calls (wrong action shapes, NaN actions, unknown env ids, out-of-range state ids) get
  the CPU pod's 4xx, naming the field; empty steps and resets are no-ops.
- A world that runs out of constraint rows (``VECSIM_MJWARP_NJMAX`` below what init state 5's
  resting contacts need, above state 0's) is that env's ``SimStateError``; the other env of the
  call steps as it would have, and a reset brings the failed one back.

The warp kernels compile once per kernel cache (``WARP_CACHE_PATH``: ``$VECSIM_WARP_CPU_CACHE``,
default ``~/.cache/vecsim/warp-cpu``, outside the checkout so CI runs on one machine share it);
the first build on a machine compiles for minutes (docs/mjwarp.md, How it is built).
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from support.service_procs import RunningPod, assignment, post_wire, reset_body, step_body

from vecsim import wire
from vecsim.config import CameraConfig, LiberoProtocol
from vecsim.engine.mjwarp.scene import ROOT_ENV, export_scene

# A cold kernel cache compiles for minutes on a 2-core machine: the first test's fixtures wait for it.
COLD_BUILD_S = 1500
pytestmark = [pytest.mark.libero, pytest.mark.slow, pytest.mark.timeout(COLD_BUILD_S + 300)]

VENV = Path(os.environ.get("VECSIM_VENV", Path.home() / ".cache" / "vecsim" / "venv"))
MJWARP_PYTHON = VENV.with_name(VENV.name + "-mjwarp") / "bin" / "python"  # scripts/setup.sh puts it there
WARP_CACHE = Path(os.environ.get("VECSIM_WARP_CPU_CACHE") or Path.home() / ".cache" / "vecsim" / "warp-cpu")
TASK = "libero_10/0"
# Init states: 5 has objects resting on each other (111 constraint rows against 99 for state 0),
# 45 has the fewest (81).
STATES = [0, 5, 45]
MAX_EPISODE_STEPS = 6
# Chunks of K=4: the second one truncates every env at its second action.
CHUNK = 4


def _actions() -> np.ndarray:
    """A fixed smooth random walk per env, gripper open then closing: ``[envs, 2 * CHUNK, 7]``."""
    rng = np.random.default_rng(40)
    steps = rng.uniform(-0.3, 0.3, size=(len(STATES), 2 * CHUNK, 7))
    actions = np.clip(np.cumsum(steps, axis=1), -1.0, 1.0).astype(np.float32)
    actions[:, :CHUNK, 6], actions[:, CHUNK:, 6] = -1.0, 1.0
    return actions


ACTIONS = _actions()
# Positions in m, angles in rad, cos/sin and quaternions: 10 um / 10 urad. Measured here after 6
# actions: 2.7e-6 at most in ``state``, 1.2e-6 in ``proprio`` (on the GPU, docs/mjwarp.md: the end
# effector 0.2-0.9 um from the CPU engine's over the first 10 actions).
ATOL = 1e-5
# A refused call's body and the field its 4xx names.
REFUSED = {
    "a chunk of 6-float actions": ("step", lambda: step_body(0, [0, 1, 2], ACTIONS[:, :CHUNK, :6]), "actions"),
    "a NaN action": ("step", lambda: step_body(0, [0, 1, 2], _with_nan(ACTIONS[:, :CHUNK])), "actions"),
    "an unknown env id": ("step", lambda: step_body(0, [0, 1, 3], ACTIONS[:, :CHUNK]), "env_indices"),
    "an out-of-range state id": ("reset", lambda: reset_body(0, [0, 1, 2], [0, 5, 50]), "state_ids"),
}


def _with_nan(actions: np.ndarray) -> np.ndarray:
    out = actions.copy()
    out[1, 2, 3] = np.nan
    return out


def _job(pod: str, engine: str, num_envs: int = len(STATES)) -> Any:
    return assignment(
        pod,
        [(TASK, num_envs)],
        job_id="mjwarp-cpu",
        engine=engine,
        camera=CameraConfig(names=(), height=8, width=8),
        max_episode_steps=MAX_EPISODE_STEPS,
    )


def _call(pod: RunningPod, op: str, body: dict[str, Any]) -> dict[str, Any]:
    answer = post_wire(pod.url, op, body, None, timeout=600)
    assert answer.status_code == 200, f"{pod.name}: {op} -> {answer.status_code} {answer.text[:500]}"
    return wire.decode(answer.content)


def _run(pod: RunningPod, envs: list[int], states: list[int]) -> list[dict[str, Any]]:
    """Reset ``envs`` to ``states``, then step them through :data:`ACTIONS` in two chunks."""
    rows = [STATES.index(s) for s in states]
    answers = [_call(pod, "reset", reset_body(0, envs, states))]
    for k in (0, CHUNK):
        answers.append(_call(pod, "step", step_body(0, envs, ACTIONS[rows, k : k + CHUNK])))
    return answers


@pytest.fixture(scope="module")
def scenes(tmp_path_factory) -> Path:
    """libero_10/0 exported by the CPU stack (LIBERO's published protocol)."""
    root = tmp_path_factory.mktemp("mjwarp-scenes")
    export_scene(TASK, LiberoProtocol(), root=root)
    return root


def _mjwarp_pod(job: Any, workdir: Path, scenes: Path, **env: str) -> RunningPod:
    assert MJWARP_PYTHON.exists(), f"no mjwarp venv at {MJWARP_PYTHON}: run scripts/setup.sh (extras with test)"
    WARP_CACHE.mkdir(parents=True, exist_ok=True)
    variables = {"VECSIM_MJWARP_ALLOW_CPU": "1", ROOT_ENV: str(scenes), "WARP_CACHE_PATH": str(WARP_CACHE), **env}
    return RunningPod(job, workdir, program=(str(MJWARP_PYTHON), "-m", "service.cli"), env=variables)


@pytest.fixture(scope="module")
def pods(scenes, tmp_path_factory) -> Iterator[dict[str, RunningPod]]:
    """The CPU pod and the mjwarp pod of one job, both ready."""
    workdir = tmp_path_factory.mktemp("pods")
    started = [RunningPod(_job("cpu-0", "cpu"), workdir), _mjwarp_pod(_job("mjwarp-0", "mjwarp"), workdir, scenes)]
    try:
        for pod in started:
            pod.start()
        for pod in started:
            pod.wait_ready(COLD_BUILD_S)
        yield {"cpu": started[0], "mjwarp": started[1]}
    finally:
        for pod in started:
            pod.stop()


@pytest.fixture(scope="module")
def runs(pods) -> dict[str, list[dict[str, Any]]]:
    """:data:`ACTIONS` from :data:`STATES` on the CPU pod, and twice on the mjwarp pod."""
    envs = list(range(len(STATES)))
    return {
        "cpu": _run(pods["cpu"], envs, STATES),
        "mjwarp": _run(pods["mjwarp"], envs, STATES),
        "mjwarp again": _run(pods["mjwarp"], envs, STATES),
    }


def _assert_bit_equal(answers: list[dict[str, Any]], reference: list[dict[str, Any]]) -> None:
    for answer, expected in zip(answers, reference, strict=True):
        for key in ("state", "proprio"):
            np.testing.assert_array_equal(answer["obs"][key], expected["obs"][key], err_msg=key)
        for key in ("reward", "terminated", "truncated", "num_steps"):
            if key in expected:
                np.testing.assert_array_equal(answer[key], expected[key], err_msg=key)


def _assert_tracks(answer: dict[str, Any], cpu: dict[str, Any], rows: tuple[int, int] | None = None) -> None:
    """A chunk's ``answer`` within :data:`ATOL` of the CPU pod's ``cpu``, its flags equal: every
    row, or only ``rows`` = (row of ``answer``, row of ``cpu``)."""
    pick = (slice(None), slice(None)) if rows is None else ([rows[0]], [rows[1]])
    for key in ("state", "proprio"):
        ours, theirs = answer["obs"][key][pick[0]], cpu["obs"][key][pick[1]]
        np.testing.assert_allclose(ours, theirs, rtol=0, atol=ATOL, err_msg=key)
    for key in ("reward", "terminated", "truncated", "num_steps"):
        np.testing.assert_array_equal(answer[key][pick[0]], cpu[key][pick[1]], err_msg=key)
    np.testing.assert_array_equal(answer["info"]["success"][pick[0]], cpu["info"]["success"][pick[1]])


def test_a_reset_answers_the_cpu_pods_observation_exactly(runs):
    cpu, mjwarp = runs["cpu"][0], runs["mjwarp"][0]
    for key in ("state", "proprio"):
        np.testing.assert_array_equal(mjwarp["obs"][key], cpu["obs"][key], err_msg=key)
    np.testing.assert_array_equal(mjwarp["info"]["success"], cpu["info"]["success"])


def test_a_fixed_action_sequence_tracks_the_cpu_pod(runs):
    for mjwarp, cpu in zip(runs["mjwarp"][1:], runs["cpu"][1:], strict=True):
        assert not mjwarp.get("errors") and not cpu.get("errors"), (mjwarp.get("errors"), cpu.get("errors"))
        _assert_tracks(mjwarp, cpu)
    last = runs["cpu"][-1]
    # The second chunk ends every episode at the limit: truncated at its second action.
    assert last["num_steps"].tolist() == [MAX_EPISODE_STEPS - CHUNK] * len(STATES)
    assert last["truncated"][:, MAX_EPISODE_STEPS - CHUNK - 1].all()


def test_the_same_inputs_give_bit_identical_outputs_on_warps_cpu_device(runs):
    _assert_bit_equal(runs["mjwarp again"], runs["mjwarp"])


@pytest.mark.parametrize("engine", ["mjwarp", "cpu"])
def test_refused_calls_name_the_field_and_change_nothing(pods, runs, engine):
    pod, envs = pods[engine], list(range(len(STATES)))
    reset = _call(pod, "reset", reset_body(0, envs, STATES))
    for what, (op, body, field) in REFUSED.items():
        answer = post_wire(pod.url, op, body(), None)
        assert 400 <= answer.status_code < 500, f"{what}: {answer.status_code}"
        assert answer.json()["detail"].startswith(f"pod {pod.name}: {field}:"), f"{what}: {answer.json()['detail']}"
    after = [reset, *(_call(pod, "step", step_body(0, envs, ACTIONS[:, k : k + CHUNK])) for k in (0, CHUNK))]
    if engine == "mjwarp":
        _assert_bit_equal(after, runs["mjwarp"])
    else:
        _assert_bit_equal(after, runs["cpu"])


def test_the_refusals_are_the_cpu_pods(pods):
    statuses = {}
    for engine, pod in pods.items():
        statuses[engine] = {
            what: post_wire(pod.url, op, body(), None).status_code for what, (op, body, _) in REFUSED.items()
        }
    assert statuses["mjwarp"] == statuses["cpu"]


def test_an_empty_step_and_an_empty_reset_are_no_ops(pods, runs):
    pod, envs = pods["mjwarp"], list(range(len(STATES)))
    reset = _call(pod, "reset", reset_body(0, envs, STATES))
    empty_reset = _call(pod, "reset", reset_body(0, [], []))
    empty_step = _call(pod, "step", step_body(0, [], np.zeros((0, CHUNK, 7), np.float32)))
    assert empty_reset["env_indices"].size == 0 and empty_reset["obs"]["state"].shape == (0, 8)
    assert empty_step["num_steps"].size == 0 and empty_step["reward"].shape == (0, CHUNK)
    after = [reset, *(_call(pod, "step", step_body(0, envs, ACTIONS[:, k : k + CHUNK])) for k in (0, CHUNK))]
    _assert_bit_equal(after, runs["mjwarp"])


def test_envs_left_out_of_a_step_do_not_move(pods):
    """MuJoCo Warp steps every world of a batch; the engine puts back the ones a call does not
    name. Env 1, left out of a step of envs 0 and 2, answers its next chunk as it does right
    after its reset, bit for bit."""
    pod = pods["mjwarp"]
    _call(pod, "reset", reset_body(0, [0, 1, 2], STATES))
    _call(pod, "step", step_body(0, [0, 2], ACTIONS[[0, 2], :CHUNK]))
    after_others = _call(pod, "step", step_body(0, [1], ACTIONS[[1], :CHUNK]))
    _call(pod, "reset", reset_body(0, [0, 1, 2], STATES))
    alone = _call(pod, "step", step_body(0, [1], ACTIONS[[1], :CHUNK]))
    _assert_bit_equal([after_others], [alone])


@pytest.mark.parametrize("chunked", [True, False])
def test_a_refill_answers_what_a_reset_then_a_step_answer(pods, chunked):
    """A refill (resets riding in a step's request) runs both in one turn and draws once; it
    answers, bit for bit, what the reset and the step answer one after the other, on one
    action per env as on chunks."""
    pod = pods["mjwarp"]
    actions = ACTIONS[[0, 2], :CHUNK] if chunked else ACTIONS[[0, 2], 0]

    def start() -> None:
        _call(pod, "reset", reset_body(0, [0, 1, 2], STATES))

    start()
    apart = [_call(pod, "reset", reset_body(0, [1], [45])), _call(pod, "step", step_body(0, [0, 2], actions))]
    start()
    refill = _call(
        pod,
        "step",
        {**step_body(0, [0, 2], actions), "reset_env_indices": np.array([1]), "reset_state_ids": np.array([45])},
    )
    _assert_bit_equal([refill["reset"], refill], apart)
    np.testing.assert_array_equal(refill["reset"]["env_indices"], [1])
    np.testing.assert_array_equal(refill["reset"]["info"]["success"], apart[0]["info"]["success"])
    # Every env is where the separate calls left it: the next chunk answers the same.
    again = _call(pod, "step", step_body(0, [0, 1, 2], ACTIONS[:, CHUNK:]))
    start()
    _call(pod, "reset", reset_body(0, [1], [45]))
    _call(pod, "step", step_body(0, [0, 2], actions))
    _assert_bit_equal([again], [_call(pod, "step", step_body(0, [0, 1, 2], ACTIONS[:, CHUNK:]))])


def test_a_world_out_of_constraint_rows_fails_alone(scenes, runs, tmp_path):
    """njmax 104 per world: init state 0 needs 99 rows at rest, state 5 111 (two objects touch)."""
    pod = _mjwarp_pod(_job("mjwarp-njmax", "mjwarp", 2), tmp_path, scenes, VECSIM_MJWARP_NJMAX="104")
    try:
        pod.start()
        pod.wait_ready(COLD_BUILD_S)
        _call(pod, "reset", reset_body(0, [0, 1], [0, 5]))
        chunk = _call(pod, "step", step_body(0, [0, 1], ACTIONS[[0, 1], :CHUNK]))
        errors = chunk["errors"]
        assert errors["env_indices"].tolist() == [1] and errors["type"] == ["SimStateError"], errors
        assert "njmax" in errors["message"][0], errors["message"]
        assert chunk["num_steps"].tolist() == [CHUNK, 0]
        # Env 0 stepped as it does beside envs that do not fail (as the CPU pod's env 0 did: this
        # pod's batch of 2 worlds and its njmax part it from the other mjwarp pod's in the last bits).
        _assert_tracks(chunk, runs["cpu"][1], rows=(0, 0))
        # The failed env stays failed until it is reset; the reset brings it back.
        again = _call(pod, "step", step_body(0, [1], ACTIONS[[1], :CHUNK]))
        assert again["errors"]["env_indices"].tolist() == [1] and "reset it" in again["errors"]["message"][0]
        reset = _call(pod, "reset", reset_body(0, [1], [0]))
        np.testing.assert_array_equal(reset["obs"]["state"][0], runs["cpu"][0]["obs"]["state"][0])
        stepped = _call(pod, "step", step_body(0, [1], ACTIONS[[0], :CHUNK]))
        assert not stepped.get("errors")
        _assert_tracks(stepped, runs["cpu"][1], rows=(0, 0))
    finally:
        pod.stop()
