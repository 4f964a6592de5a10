"""The exact step path (vecsim.engine.tasks._fast_step) gives robosuite's and LIBERO's own trajectories.

Each test builds the same task twice, one env on the ``exact`` path (vecsim's default) and one on
the ``library`` path (the env's own ``step``: robosuite's, or LIBERO's for a LIBERO scene), resets
both alike and steps both with one action sequence whose gripper closes and opens (grasps,
contacts), with a reset to another state partway. At every step MuJoCo's state, every observable,
vecsim's observation, reward, success and the arm controller's output must be bit-identical.
Full-length episodes of every LIBERO-10 task: ``bench/bench_robot_step.py --parity-episodes``.

A LIBERO reset on the exact path (robosuite's reset forwards without their acceleration stage,
settle steps on the exact path) leaves everything as the library path's reset (robosuite's reset
in full, settle steps on LIBERO's own step) leaves it: every array of MuJoCo's data and model,
the controller, the robot's buffers, every observable and its clock, right after each reset and
after the steps that follow.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

import mujoco
import numpy as np
import pytest

from vecsim.config import CameraConfig
from vecsim.engine.tasks import TaskEnv, make_env

STEPS = 60
RESET_AT = 35
STATE_FIELDS = ("time", "qpos", "qvel", "act", "ctrl", "qacc_warmstart", "qacc", "sensordata")
CONTROLLER_FIELDS = ("torques", "goal_pos", "goal_ori", "ee_pos", "ee_ori_mat", "ee_pos_vel", "mass_matrix", "J_full")


def actions(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    table = rng.uniform(-0.6, 0.6, (STEPS, 7))
    # Closed for steps 10-24 and 45-59: the fingers close on whatever is near and open again.
    table[:, 6] = np.where((np.arange(STEPS) // 10) % 3 == 1, 1.0, -1.0)
    table[(np.arange(STEPS) // 15) % 3 == 2, 6] = 1.0
    return table


@contextlib.contextmanager
def env_pair(task_id: str) -> Iterator[dict[str, TaskEnv]]:
    envs = {path: make_env(task_id, CameraConfig(names=()), "lean") for path in ("exact", "library")}
    try:
        envs["library"].set_step_path("library")
        yield envs
    finally:
        for env in envs.values():
            env.close()


def left_behind(env: Any) -> dict[str, np.ndarray]:
    """Return MuJoCo's state, every observable's value and the arm controller's outputs."""
    inner = env.inner
    data = inner.sim.data._data
    state = {f"data.{name}": np.array(getattr(data, name)) for name in STATE_FIELDS}
    state.update({f"observable {name}": np.array(obs.obs) for name, obs in inner._observables.items()})
    controller = inner.robots[0].controller
    state.update({f"controller.{name}": np.array(getattr(controller, name)) for name in CONTROLLER_FIELDS})
    state["gripper action"] = np.array(inner.robots[0].gripper.current_action)
    state["env timestep"] = np.array(inner.timestep)
    return state


def _same_bits(ours: np.ndarray, theirs: np.ndarray) -> bool:
    """Whether two arrays of one shape and dtype hold the same bytes, read in place (a copy only
    where one is not contiguous); arrays of objects by their bytes."""
    if ours.dtype.hasobject:
        return ours.tobytes() == theirs.tobytes()
    return np.array_equal(
        np.ascontiguousarray(ours).reshape(-1).view(np.uint8), np.ascontiguousarray(theirs).reshape(-1).view(np.uint8)
    )


def assert_identical(task_id: str, step: int, exact: dict[str, Any], library: dict[str, Any]) -> None:
    """Assert that every quantity is bit-identical: shape, dtype and bytes (so NaN equals NaN)."""
    assert exact.keys() == library.keys(), f"{task_id} step {step}: different quantities"
    for name, value in exact.items():
        other = library[name]
        same = value.shape == other.shape and value.dtype == other.dtype and _same_bits(value, other)
        assert same, f"{task_id} step {step}: {name} differs (exact {value!r} vs library {other!r})"


def run_side_by_side(task_id: str, envs: dict[str, TaskEnv], seed: int) -> int:
    """Step both envs through the action table; return how many steps compared identical."""
    for env in envs.values():
        env.reset(options={"state_id": 0})
    compared = 0
    for step, action in enumerate(actions(seed)):
        if step == RESET_AT:
            # A reset makes new controllers; their first substep has no update of its own.
            for env in envs.values():
                env.reset(options={"state_id": 1})
        results = {path: env.step(action.astype(np.float32)) for path, env in envs.items()}
        exact, library = (
            {
                **left_behind(envs[path]),
                "observation proprio": results[path][0]["proprio"],
                "reward": np.array(results[path][1]),
                "terminated": np.array(results[path][2]),
                "success": np.array(results[path][4]["success"]),
            }
            for path in ("exact", "library")
        )
        assert_identical(task_id, step, exact, library)
        compared += 1
    return compared


def test_robot_envs_take_the_exact_step_path_by_default() -> None:
    with env_pair("tiny/lift") as envs:
        assert envs["exact"].step_path == "exact"
        assert envs["library"].step_path == "library"


def test_an_unknown_step_path_is_refused_and_the_path_is_kept() -> None:
    with env_pair("tiny/lift") as envs:
        with pytest.raises(ValueError, match="'fastest'"):
            envs["exact"].set_step_path("fastest")
        assert envs["exact"].step_path == "exact"


def test_exact_path_gives_robosuite_own_trajectory() -> None:
    with env_pair("tiny/lift") as envs:
        assert run_side_by_side("tiny/lift", envs, seed=0) == STEPS


def test_exact_path_runs_the_controller_of_non_policy_substeps_as_one_compiled_call() -> None:
    # Where numpy's BLAS is the OpenBLAS its wheels bundle (as in this venv), the trajectory
    # tests here and below compare the compiled controller (osc_substep) with robosuite's.
    from vecsim.engine.tasks import _osc_kernel

    with env_pair("tiny/lift") as envs:
        envs["exact"].reset(options={"state_id": 0})
        envs["exact"].step(np.zeros(7, np.float32))
        assert envs["exact"]._step_fn.fused
        assert _osc_kernel.osc_substep.signatures


def test_exact_path_with_the_controller_from_python_gives_robosuite_own_trajectory() -> None:
    # What the exact path runs where the compiled controller is not available.
    with env_pair("tiny/lift") as envs:
        envs["exact"]._step_fn.fused = False
        assert run_side_by_side("tiny/lift", envs, seed=0) == STEPS


def test_a_compiled_controller_that_cannot_load_leaves_the_controller_from_python(monkeypatch, caplog) -> None:
    # E.g. numba finding no writable place for its cache: the exact path goes on, from Python.
    from vecsim.engine.tasks import _fast_step

    def unloadable() -> Any:
        raise RuntimeError("cannot cache function 'osc_substep': no locator available")

    monkeypatch.setattr(_fast_step, "osc_kernel", unloadable)
    _fast_step._fused_controller_available.cache_clear()
    try:
        with caplog.at_level("WARNING"), env_pair("tiny/lift") as envs:
            assert not envs["exact"]._step_fn.fused
            assert run_side_by_side("tiny/lift", envs, seed=0) == STEPS
        assert "runs from Python" in caplog.text
    finally:
        _fast_step._fused_controller_available.cache_clear()


def test_exact_path_steps_from_a_controller_left_without_an_update_as_robosuite_does() -> None:
    # A controller whose last update saw another pose, with new_update cleared (what a reset
    # leaves: the controller it builds updated itself at the reset's pose, before the init state
    # was set). robosuite's policy step then sets the goal and the torques from those stale
    # values; the exact path must too, even where the gripper could run the compiled controller.
    with env_pair("tiny/lift") as envs:
        for env in envs.values():
            env.reset(options={"state_id": 0})
        table = actions(2)
        for action in table[:5]:
            for env in envs.values():
                env.step(action.astype(np.float32))
        earlier = {path: env.inner.sim.get_state().flatten() for path, env in envs.items()}
        for action in table[5:10]:
            for env in envs.values():
                env.step(action.astype(np.float32))
        for path, env in envs.items():
            env.inner.sim.set_state_from_flattened(earlier[path])
            env.inner.sim.forward()
            assert env.inner.robots[0].controller.new_update  # left by the last step's control
            env.inner.robots[0].controller.new_update = False
        for step, action in enumerate(table[10:20], start=10):
            results = {path: env.step(action.astype(np.float32)) for path, env in envs.items()}
            exact, library = (
                {**left_behind(envs[path]), "observation proprio": results[path][0]["proprio"]}
                for path in ("exact", "library")
            )
            assert_identical("tiny/lift", step, exact, library)


def test_exact_path_with_delayed_observables_gives_robosuite_own_trajectory() -> None:
    from robosuite.utils.observables import create_deterministic_delayer

    with env_pair("tiny/lift") as envs:
        for env in envs.values():
            # A delayer moves each sample's time, so the exact path updates observables every substep.
            env.inner.modify_observable("robot0_eef_pos", "delayer", create_deterministic_delayer(0.01))
        assert run_side_by_side("tiny/lift", envs, seed=1) == STEPS


@pytest.mark.libero
@pytest.mark.parametrize("task_id", ["libero_10/0", "libero_10/5"])
def test_exact_path_gives_libero_own_trajectory(task_id: str) -> None:
    with env_pair(task_id) as envs:
        assert run_side_by_side(task_id, envs, seed=2) == STEPS


# Arrays of MjData that hold no state: the sparse layout of the constraint Jacobian (and of its
# inverse-inertia product) is neither written nor read for a dense-Jacobian model under the
# Newton solver without noslip, so they show whatever the arena held before.
SPARSE_LAYOUT = (
    "efc_J_rownnz",
    "efc_J_rowadr",
    "efc_J_rowsuper",
    "efc_J_colind",
    "efc_AR_rownnz",
    "efc_AR_rowadr",
    "efc_AR_colind",
)


def _arrays(obj: Any, prefix: str, skip: tuple[str, ...] = ()) -> dict[str, np.ndarray]:
    """Return ``obj``'s public arrays as live views (compared at once, never kept: a LIBERO model's
    textures and meshes are ~250 MB, copied twice a step they took most of this file's time) and
    its numbers as arrays."""
    found = {}
    for name in dir(obj):
        value = getattr(obj, name) if not name.startswith("_") and name not in skip else None
        if isinstance(value, np.ndarray):
            found[f"{prefix}.{name}"] = value
        elif isinstance(value, (int, float)) and not isinstance(value, bool):
            found[f"{prefix}.{name}"] = np.array(value)
    return found


def everything(env: Any) -> dict[str, np.ndarray]:
    """Return every array of MuJoCo's data and model and all robosuite keeps beside them."""
    inner = env.inner
    model = inner.sim.model._model
    dense_newton = (
        not mujoco.mj_isSparse(model)
        and model.opt.solver == int(mujoco.mjtSolver.mjSOL_NEWTON)
        and model.opt.noslip_iterations == 0
    )
    state = _arrays(inner.sim.data._data, "data", SPARSE_LAYOUT if dense_newton else ())
    state.update(_arrays(model, "model"))
    for index, robot in enumerate(inner.robots):
        controller = robot.controller
        for name, value in vars(controller).items():
            if isinstance(value, (np.ndarray, float, int)):
                state[f"robot{index}.controller.{name}"] = np.array(value)
        for name in ("base_pos", "base_ori", "torques"):
            state[f"robot{index}.{name}"] = np.array(getattr(robot, name))
        state[f"robot{index}.gripper.current_action"] = np.array(robot.gripper.current_action)
        for name in (
            "recent_qpos",
            "recent_actions",
            "recent_torques",
            "recent_ee_forcetorques",
            "recent_ee_pose",
            "recent_ee_vel",
            "recent_ee_acc",
        ):
            buffer = getattr(robot, name)
            state[f"robot{index}.{name}"] = np.array([buffer.last, buffer.current])
        ring = robot.recent_ee_vel_buffer
        state[f"robot{index}.recent_ee_vel_buffer"] = np.append(ring.buf.ravel(), ring.ptr)
    for name, obs in inner._observables.items():
        state[f"observable {name}"] = np.array(obs.obs)
        state[f"observable {name} clock"] = np.array([obs._time_since_last_sample, obs._sampled, obs._current_delay])
    state.update({f"observation cache {name}": np.array(value) for name, value in inner._obs_cache.items()})
    state["env counters"] = np.array([inner.timestep, inner.cur_time, inner.done], dtype=np.float64)
    return state


@pytest.mark.libero
@pytest.mark.parametrize(("task_id", "state_ids"), [("libero_10/0", (0, 17, 49, 17)), ("libero_10/9", (49, 3))])
def test_exact_path_resets_a_libero_env_as_the_library_path_does(task_id: str, state_ids: tuple[int, ...]) -> None:
    table = actions(seed=3)
    with env_pair(task_id) as envs:
        for state_id in state_ids:
            observations = {path: env.reset(options={"state_id": state_id})[0] for path, env in envs.items()}
            exact, library = (
                {
                    **everything(envs[path]),
                    "observation proprio": observations[path]["proprio"],
                    "observation state": observations[path]["state"],
                }
                for path in ("exact", "library")
            )
            assert_identical(task_id, -1, exact, library)
            for step, action in enumerate(table[:8]):
                results = {path: env.step(action.astype(np.float32)) for path, env in envs.items()}
                exact, library = (
                    {
                        **everything(envs[path]),
                        "observation proprio": results[path][0]["proprio"],
                        "reward": np.array(results[path][1]),
                        "success": np.array(results[path][4]["success"]),
                    }
                    for path in ("exact", "library")
                )
                assert_identical(f"{task_id} from state {state_id}", step, exact, library)
