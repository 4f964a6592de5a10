"""A LIBERO env-step: vecsim's step paths against LIBERO's own env and MuJoCo's floor, one core.

Per task, on one pinned core, no cameras, step by step:

- ``exact``: vecsim's env (``make_env``) on its default step path (``vecsim.engine.tasks._fast_step``);
- ``library``: the same env on the ``library`` path (robosuite's own ``step``, as before);
- with ``--changes``, the exact path's changes one at a time (each a subclass of ``ExactStep``
  that puts robosuite's own calls back for what is not yet changed);
- with ``--python-controller``, the exact path with its non-policy substeps' controller run from
  Python (robosuite's numpy and numba calls one by one), as it was before the compiled
  ``osc_substep`` (``vecsim.engine.tasks._osc_kernel``);
- with ``--second-pass``, the exact path without its second pass's changes (the non-policy
  substeps in one loop, the policy substep's controller compiled too), and with the first only;
- ``floor``: right before each of those steps, as many ``mj_step`` as the step holds (25 at
  LIBERO's 500 Hz physics and 20 Hz control) on a copy of the state the step starts from;
- ``libero``: after each of them, one step of LIBERO's own ``OffScreenRenderEnv``
  (``use_camera_obs=False``; it still makes its offscreen GL context, which a step does not use),
  reset LIBERO's way (``seed(0)``, ``reset()``, ``set_init_state`` of the same init state);
- physics only: each path's MuJoCo calls for one env-step without the controller around them,
  from the state the steps ended in (:func:`physics_only`);
- resets: vecsim's ``reset(options={"state_id": k})`` as it is and as it was (:func:`measure_resets`)
  against LIBERO's own reset, in turns.

The vecsim paths take turns on one env and one trajectory, each step's time set against the
floor taken just before it, so load that comes and goes on a shared machine moves both; the
figures are medians over the steps, and (``fastest_*``) the fastest step of each kind, what a
step costs when nothing else takes the core. ``--parity-episodes`` instead runs full-length episodes of every
task on the exact and the library path side by side and compares them bit for bit at every step
(MuJoCo state, every observable, reward, success); the first difference fails the run.

    python bench/bench_robot_step.py                                   # LIBERO-10, 160 steps each
    python bench/bench_robot_step.py --tasks libero_10/0,libero_10/5 --changes --steps 300
    python bench/bench_robot_step.py --tasks libero_10/0,libero_10/9 --python-controller --steps 100
    python bench/bench_robot_step.py --parity-episodes --episodes 1    # 520 steps per task
    python bench/bench_robot_step.py --resets-only --resets 5          # resets: vecsim now, before, LIBERO's

Writes out/bench/bench_robot_step[_parity_<path>|_resets][_<tag>].json and prints ``RESULT {json}``.
"""

from __future__ import annotations

import argparse
import logging
import os
import statistics
import time
from typing import Any

import mujoco
import numpy as np
from lib.records import spread, write_result

log = logging.getLogger("bench_robot_step")

PYTHON_CONTROLLER = "exact_python_controller"
# --second-pass: the exact path without the second pass's changes (ExactStep's flags), and with the first only.
SECOND_PASS = {"exact_before_second_pass": (False, False), "exact_one_substep_loop": (True, False)}

# The arrays of MuJoCo's state that an env-step carries forward, compared bit for bit.
STATE_FIELDS = (
    "time",
    "qpos",
    "qvel",
    "act",
    "ctrl",
    "qacc_warmstart",
    "qacc",
    "sensordata",
    "mocap_pos",
    "mocap_quat",
)


def action_table(steps: int, seed: int) -> np.ndarray:
    """Return ``steps`` random 7-dim actions whose gripper closes and opens every 20 steps."""
    rng = np.random.default_rng(seed)
    actions = rng.uniform(-0.5, 0.5, (steps, 7))
    actions[:, 6] = np.where((np.arange(steps) // 20) % 2 == 1, 1.0, -1.0)
    return actions


def change_variants() -> dict[str, Any]:
    """Return the exact path's changes as cumulative ``ExactStep`` subclasses, first to last."""
    from vecsim.engine.tasks import ExactStep

    class ControllerOnly(ExactStep):
        # robosuite's forwards (the substep's and the controller update's), mj_step and
        # per-substep observable updates; only the controller's Python is the fast one (from
        # Python: the compiled controller is the last change).
        def __init__(self, inner: Any) -> None:
            super().__init__(inner)
            self.fused = False

        def _forward(self, policy_step: bool) -> None:
            mujoco.mj_forward(self.model, self.data)

        def _update(self, arm: Any, controller: Any) -> None:
            mujoco.mj_forward(self.model, self.data)
            super()._update(arm, controller)

        def _integrate(self) -> None:
            mujoco.mj_step(self.model, self.data)

        def _observable_plan(self, substeps: int) -> None:
            return None

    class PlusObservables(ControllerOnly):
        def _observable_plan(self, substeps: int) -> Any:
            return ExactStep._observable_plan(self, substeps)

    class PlusOneForward(PlusObservables):
        _forward = ExactStep._forward
        _update = ExactStep._update
        _integrate = ExactStep._integrate

    return {
        "controller": ControllerOnly,
        "+observables": PlusObservables,
        "+one forward": PlusOneForward,
        "+compiled controller (exact)": ExactStep,
    }


def python_controller(inner: Any) -> Any:
    """Return the exact path's step for ``inner`` with its controller run from Python throughout."""
    from vecsim.engine.tasks import ExactStep

    step = ExactStep(inner)
    step.fused = False
    return step


def second_pass_variant(substep_loop: bool, fused_policy: bool) -> Any:
    """Return a maker of the exact path's step with its second pass's changes on or off."""
    from vecsim.engine.tasks import ExactStep

    def make(inner: Any) -> Any:
        step = ExactStep(inner)
        step.substep_loop, step.fused_policy = substep_loop, fused_policy
        return step

    return make


class LiberoOwn:
    """LIBERO's own ``OffScreenRenderEnv`` of one task, reset LIBERO's way."""

    def __init__(self, task_id: str) -> None:
        from vecsim.engine.tasks import init_states, libero_benchmark, stdout_to_log
        from vecsim.engine.tasks import get_task

        suite, index = task_id.split("/", 1)
        # libero_benchmark writes LIBERO's config first: importing LIBERO without it asks on stdin.
        bddl_file = libero_benchmark(suite).get_task_bddl_file_path(int(index))
        with stdout_to_log():
            from libero.libero.envs import OffScreenRenderEnv

            self.env = OffScreenRenderEnv(
                bddl_file_name=bddl_file,
                use_camera_obs=False,
                camera_heights=16,
                camera_widths=16,
            )
        self.states = init_states(get_task(task_id))

    def reset(self, state_id: int) -> None:
        """LIBERO's evaluation reset: ``seed(0)``, ``reset()``, ``set_init_state``."""
        self.env.seed(0)
        self.env.reset()
        self.env.set_init_state(self.states[state_id])

    def close(self) -> None:
        self.env.close()


def physics_only(model: Any, data: Any, scratch: Any, substeps: int, reps: int) -> dict[str, list[float]]:
    """Time each path's MuJoCo calls alone (no controller, no Python around them) for one env-step.

    From the state ``data`` is in, on ``scratch``, in turns: the floor (``mj_step``), the library
    path's (``mj_forward`` twice, ``mj_step``), the exact path's on a non-policy substep (the
    position and velocity stages with their sensors, the checks, ``mj_step2``).
    """
    calls = {
        "floor": lambda: mujoco.mj_step(model, scratch),
        "library": lambda: (
            mujoco.mj_forward(model, scratch),
            mujoco.mj_forward(model, scratch),
            mujoco.mj_step(model, scratch),
        ),
        "exact": lambda: (
            mujoco.mj_fwdPosition(model, scratch),
            mujoco.mj_sensorPos(model, scratch),
            mujoco.mj_fwdVelocity(model, scratch),
            mujoco.mj_sensorVel(model, scratch),
            mujoco.mj_checkPos(model, scratch),
            mujoco.mj_checkVel(model, scratch),
            mujoco.mj_step2(model, scratch),
        ),
    }
    spec = int(mujoco.mjtState.mjSTATE_INTEGRATION)
    state = np.empty(mujoco.mj_stateSize(model, spec))
    mujoco.mj_getState(model, data, state, spec)
    times: dict[str, list[float]] = {name: [] for name in calls}
    for _ in range(reps):
        for name, call in calls.items():
            mujoco.mj_setState(model, scratch, state, spec)
            started = time.perf_counter()
            for _ in range(substeps):
                call()
            times[name].append(time.perf_counter() - started)
    return times


def measure_task(task_id: str, args: argparse.Namespace) -> dict[str, Any]:
    """Measure one task's step paths against the floor, step by step, and its resets.

    One vecsim env runs one trajectory; each of its steps takes the next path in turn (every
    path leaves the same state, so it is the library's trajectory). Right before each step, the floor runs the same number of
    ``mj_step`` on a copy of the state that step starts from; a step's ratio is against that
    floor, so load that comes and goes moves both. LIBERO's own env takes one step of its own
    trajectory after each vecsim step. Figures are medians over the steps.
    """
    from vecsim.config import CameraConfig
    from vecsim.engine.tasks import make_env

    env = make_env(task_id, CameraConfig(names=()), "lean")
    own = LiberoOwn(task_id) if task_id.startswith("libero") else None
    paths: dict[str, Any] = {"exact": "exact", "library": "library"}
    if args.python_controller:
        paths[PYTHON_CONTROLLER] = python_controller
    if args.changes:
        paths.update(change_variants())
    if args.second_pass:
        paths.update({name: second_pass_variant(*flags) for name, flags in SECOND_PASS.items()})
    steppers = {}
    for name, path in paths.items():
        if isinstance(path, str):
            env.set_step_path(path)
            steppers[name] = env._step_fn
        else:
            steppers[name] = path(env.inner)
    model, data = env.inner.sim.model._model, env.inner.sim.data._data
    substeps = int(env.inner.control_timestep / env.inner.model_timestep)
    # The floor's copy takes the integration state only: a LIBERO scene's MjData is hundreds of
    # megabytes (robosuite's memory size), and copying all of it would flush the caches.
    spec = int(mujoco.mjtState.mjSTATE_INTEGRATION)
    state = np.empty(mujoco.mj_stateSize(model, spec))
    scratch = mujoco.MjData(model)
    samples: dict[str, list[float]] = {name: [] for name in [*steppers, "floor", "libero"]}
    over_floor: dict[str, list[float]] = {name: [] for name in [*steppers, "libero"]}
    actions = action_table(args.steps, seed=1)
    names = list(steppers)
    env.reset(options={"state_id": 0})
    if own is not None:
        own.reset(0)
    for index, action in enumerate(actions):
        name = names[index % len(names)]
        mujoco.mj_getState(model, data, state, spec)
        mujoco.mj_setState(model, scratch, state, spec)
        started = time.perf_counter()
        for _ in range(substeps):
            mujoco.mj_step(model, scratch)
        floor = time.perf_counter() - started
        env._step_fn = steppers[name]
        started = time.perf_counter()
        env.step(action)
        took = time.perf_counter() - started
        if index >= len(names):  # the first step of each path warms it up
            samples["floor"].append(floor)
            samples[name].append(took)
            over_floor[name].append(took / floor)
        if own is not None:
            started = time.perf_counter()
            own.env.step(action)
            took = time.perf_counter() - started
            if index >= len(names):
                samples["libero"].append(took)
                over_floor["libero"].append(took / floor)
    physics = physics_only(model, data, scratch, substeps, args.physics_reps)
    resets = measure_resets(env, own, args.resets)
    env.close()
    if own is not None:
        own.close()
    ms = {name: round(statistics.median(values) * 1e3, 3) for name, values in samples.items() if values}
    fastest = {name: min(values) for name, values in samples.items() if values}
    row: dict[str, Any] = {
        "ms": ms,
        "over_floor": {name: round(statistics.median(v), 3) for name, v in over_floor.items() if v},
        # The fastest step of each kind: what it costs when no other process takes the core.
        "fastest_ms": {name: round(value * 1e3, 3) for name, value in fastest.items()},
        "fastest_over_floor": {name: round(value / fastest["floor"], 3) for name, value in fastest.items()},
        "samples_per_path": len(samples["exact"]),
        **reset_figures(resets),
    }
    row["physics_fastest_over_floor"] = {
        name: round(min(values) / min(physics["floor"]), 3) for name, values in physics.items()
    }
    row["library_over_exact"] = round(ms["library"] / ms["exact"], 3)
    row["fastest_library_over_exact"] = round(fastest["library"] / fastest["exact"], 3)
    if PYTHON_CONTROLLER in ms:
        row["python_controller_over_exact"] = round(ms[PYTHON_CONTROLLER] / ms["exact"], 3)
        row["fastest_python_controller_over_exact"] = round(fastest[PYTHON_CONTROLLER] / fastest["exact"], 3)
    for name in SECOND_PASS:
        if name in ms:
            row[f"{name}_over_exact"] = round(ms[name] / ms["exact"], 3)
            row[f"fastest_{name}_over_exact"] = round(fastest[name] / fastest["exact"], 3)
    if own is not None:
        row["libero_over_exact"] = round(ms["libero"] / ms["exact"], 3)
        row["fastest_libero_over_exact"] = round(fastest["libero"] / fastest["exact"], 3)
    log.info("%s: %s", task_id, row)
    return row


def reset_figures(resets: dict[str, list[float]]) -> dict[str, Any]:
    """Return medians and fastest of each kind of reset, and each kind's over vecsim's."""
    median = {name: statistics.median(v) for name, v in resets.items() if v}
    fastest = {name: min(v) for name, v in resets.items() if v}
    figures: dict[str, Any] = {
        "reset_ms": {name: round(v * 1e3, 1) for name, v in median.items()},
        "fastest_reset_ms": {name: round(v * 1e3, 1) for name, v in fastest.items()},
    }
    for name in ("libero", "before", "forwards_cut"):
        if name in median:
            figures[f"reset_{name}_over_vecsim"] = round(median[name] / median["vecsim"], 2)
            figures[f"fastest_reset_{name}_over_vecsim"] = round(fastest[name] / fastest["vecsim"], 2)
    return figures


def measure_task_resets(task_id: str, args: argparse.Namespace) -> dict[str, Any]:
    """Measure one task's resets only (:func:`measure_resets`)."""
    from vecsim.config import CameraConfig
    from vecsim.engine.tasks import make_env

    env = make_env(task_id, CameraConfig(names=()), "lean")
    own = LiberoOwn(task_id) if task_id.startswith("libero") else None
    try:
        env.reset(options={"state_id": 0})  # the first reset of each kind warms up
        if own is not None:
            own.reset(0)
        row = reset_figures(measure_resets(env, own, args.resets))
    finally:
        env.close()
        if own is not None:
            own.close()
    log.info("%s: %s", task_id, row)
    return row


def measure_resets(env: Any, own: LiberoOwn | None, count: int) -> dict[str, list[float]]:
    """Time vecsim's reset as it is and as it was, and LIBERO's own reset, in turns, per state id.

    ``vecsim``: the env's reset on the exact step path (robosuite's reset forwards without their
    acceleration stage, settle steps on the exact path). For a LIBERO task also ``before`` (the
    library path: robosuite's reset with full forwards, settle steps on LIBERO's own step, as
    vecsim reset before) and ``forwards_cut`` (the forwards cut, settle steps still on LIBERO's
    own step): the two changes one at a time. All three leave the env bit-identical.
    """
    from vecsim.engine.tasks import library_step

    def on_path(path: str, settle_on_library: bool = False) -> Any:
        def reset(state_id: int) -> float:
            env.set_step_path(path)
            if settle_on_library:
                env._step_fn = library_step(env.inner)
            started = time.perf_counter()
            env.reset(options={"state_id": state_id})
            return time.perf_counter() - started

        return reset

    kinds: dict[str, Any] = {"vecsim": on_path("exact")}
    if own is not None:
        kinds = {"before": on_path("library"), "forwards_cut": on_path("exact", True), **kinds}
    resets: dict[str, list[float]] = {name: [] for name in kinds}
    for state_id in range(count):
        for name, reset in kinds.items():
            resets[name].append(reset(state_id))
        if own is not None:
            started = time.perf_counter()
            own.reset(state_id)
            resets.setdefault("libero", []).append(time.perf_counter() - started)
    env.set_step_path("exact")
    return resets


def snapshot(env: Any) -> dict[str, Any]:
    """Return what one env-step leaves behind: MuJoCo's state arrays and every observable's value."""
    data = env.inner.sim.data._data
    state = {f"data.{field}": np.array(getattr(data, field)) for field in STATE_FIELDS}
    for name, obs in env.inner._observables.items():
        state[f"observable {name}"] = np.array(obs.obs)
    return state


def parity_episode(task_id: str, episode: int, steps: int, path: str) -> dict[str, Any]:
    """Run one episode on ``path`` and on the library path side by side; return how they compare.

    It stops at the first difference.
    """
    from vecsim.config import CameraConfig
    from vecsim.engine.tasks import make_env

    envs = {p: make_env(task_id, CameraConfig(names=()), "lean", max_episode_steps=steps) for p in (path, "library")}
    try:
        for wanted, env in envs.items():
            env.set_step_path(wanted)
            if env.step_path != wanted:
                return {"task": task_id, "episode": episode, "error": f"no {wanted} path: {env.step_path}"}
            env.reset(options={"state_id": episode % env.task.num_states})
        first: dict[str, Any] | None = None
        drift = 0.0
        successes = {p: 0 for p in envs}
        disagreements = 0
        for index, action in enumerate(action_table(steps, seed=1000 + episode)):
            results = {p: env.step(action) for p, env in envs.items()}
            if first is None:
                a, b = (snapshot(envs[p]) for p in envs)
                a["proprio"], b["proprio"] = (results[p][0]["proprio"] for p in envs)
                a["reward, terminated, truncated, success"], b["reward, terminated, truncated, success"] = (
                    np.array([r[1], r[2], r[3], r[4]["success"]], dtype=np.float64) for r in results.values()
                )
                for key in a:
                    if a[key].shape != b[key].shape or a[key].tobytes() != b[key].tobytes():
                        first = {"step": index, "differs": key}
                        break
                if first is not None and path == "exact":
                    break
            qpos = [env.inner.sim.data._data.qpos for env in envs.values()]
            drift = max(drift, float(np.max(np.abs(qpos[0] - qpos[1]))))
            flags = [results[p][4]["success"] for p in envs]
            disagreements += int(flags[0] != flags[1])
            for p, flag in zip(envs, flags):
                successes[p] += int(flag)
        return {
            "task": task_id,
            "episode": episode,
            "path": path,
            "steps": index + 1,
            "identical": first is None,
            "first_difference": first,
            "max_abs_qpos_difference": drift,
            "success_steps": successes,
            "success_disagreements": disagreements,
        }
    finally:
        for env in envs.values():
            env.close()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tasks", help="comma-separated task ids (default: LIBERO-10's ten)")
    parser.add_argument("--steps", type=int, default=160, help="env-steps per task, the paths taking turns")
    parser.add_argument("--resets", type=int, default=3, help="resets per task, of each kind (one state id each)")
    parser.add_argument("--resets-only", action="store_true", help="measure resets only (--steps ignored)")
    parser.add_argument("--physics-reps", type=int, default=30, help="turns of the physics-only timing per task")
    parser.add_argument("--changes", action="store_true", help="also measure the exact path's changes one at a time")
    parser.add_argument(
        "--python-controller",
        action="store_true",
        help="also measure the exact path with its controller run from Python (before the compiled kernel)",
    )
    parser.add_argument(
        "--second-pass",
        action="store_true",
        help="also measure the exact path without its second pass's changes, and with the first only",
    )
    parser.add_argument("--cpu", type=int, help="the core to pin to (default: the last one allowed)")
    parser.add_argument("--parity-episodes", action="store_true", help="compare full episodes bit for bit instead")
    parser.add_argument("--episodes", type=int, default=1, help="episodes per task with --parity-episodes")
    parser.add_argument("--episode-steps", type=int, default=520, help="steps per episode with --parity-episodes")
    parser.add_argument("--tag", help="suffix of the output file's name")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    cpu = args.cpu if args.cpu is not None else max(os.sched_getaffinity(0))
    os.sched_setaffinity(0, {cpu})
    if args.tasks:
        tasks = [t for t in args.tasks.split(",") if t]
    else:
        from vecsim.engine.tasks import suite_tasks

        tasks = [t.task_id for t in suite_tasks("libero_10")]
    started = time.monotonic()
    load_at_start = os.getloadavg()
    suffix = f"_{args.tag}" if args.tag else ""
    if args.parity_episodes:
        episodes = []
        for task_id in tasks:
            for episode in range(args.episodes):
                episodes.append(parity_episode(task_id, episode, args.episode_steps, "exact"))
                log.info("parity %s", episodes[-1])
        identical = all(e.get("identical") for e in episodes)
        summary = {
            "path": "exact",
            "baseline": "the library step path (robosuite's/LIBERO's own step) on an identically built and reset env",
            "identical": identical,
            "setup": {
                "tasks": tasks,
                "episodes_per_task": args.episodes,
                "steps_per_episode": args.episode_steps,
                "pinned_to": cpu,
            },
            "episodes": episodes,
            "seconds_total": round(time.monotonic() - started, 1),
        }
        write_result("bench_robot_step_parity_exact" + suffix, summary)
        return 0 if identical else 1
    if args.resets_only:
        rows = {task_id: measure_task_resets(task_id, args) for task_id in tasks}
        summary = {
            "baseline": "vecsim's reset as it was (the library path), beside LIBERO's own reset (hard, its default)",
            "across_tasks": {
                key: spread([row[key] for row in rows.values() if key in row])
                for key in next(iter(rows.values()))
                if key.endswith("_over_vecsim")
            },
            "setup": {
                "tasks": tasks,
                "resets": args.resets,
                "pinned_to": cpu,
                "cameras": "none",
                "load_average_at_start": load_at_start,
                "load_average_at_end": os.getloadavg(),
            },
            "rows": rows,
            "seconds_total": round(time.monotonic() - started, 1),
        }
        write_result("bench_robot_step_resets" + suffix, summary)
        return 0
    rows = {task_id: measure_task(task_id, args) for task_id in tasks}

    def across(pick: Any) -> dict[str, float] | None:
        values = [v for v in (pick(row) for row in rows.values()) if v is not None]
        return spread(values) if values else None

    step_paths = list(next(iter(rows.values()))["over_floor"])
    summary = {
        "baseline": "MuJoCo's floor: mj_step on a copy of the state each step starts from, timed right before it",
        "ratio": statistics.median(row["over_floor"]["exact"] for row in rows.values()),
        "target": "exact <= 2x floor; LIBERO's own step >= 2.5x exact",
        "across_tasks": {
            **{f"{name}_over_floor": across(lambda row, n=name: row["over_floor"].get(n)) for name in step_paths},
            **{
                f"fastest_{name}_over_floor": across(lambda row, n=name: row["fastest_over_floor"].get(n))
                for name in step_paths
            },
            **{
                f"physics_{name}_over_floor": across(lambda row, n=name: row["physics_fastest_over_floor"][n])
                for name in ("exact", "library")
            },
            "library_over_exact": across(lambda row: row["library_over_exact"]),
            "fastest_library_over_exact": across(lambda row: row["fastest_library_over_exact"]),
            "libero_over_exact": across(lambda row: row.get("libero_over_exact")),
            "fastest_libero_over_exact": across(lambda row: row.get("fastest_libero_over_exact")),
            "python_controller_over_exact": across(lambda row: row.get("python_controller_over_exact")),
            "fastest_python_controller_over_exact": across(lambda row: row.get("fastest_python_controller_over_exact")),
            **{
                f"{prefix}{name}_over_exact": across(lambda row, k=f"{prefix}{name}_over_exact": row.get(k))
                for name in SECOND_PASS
                for prefix in ("", "fastest_")
            },
            **{
                key: across(lambda row, k=key: row.get(k))
                for key in ("reset_libero_over_vecsim", "reset_before_over_vecsim", "fastest_reset_before_over_vecsim")
            },
        },
        "setup": {
            "tasks": tasks,
            "steps": args.steps,
            "resets": args.resets,
            "pinned_to": cpu,
            "cameras": "none",
            "changes": args.changes,
            "python_controller": args.python_controller,
            "second_pass": args.second_pass,
            "load_average_at_start": load_at_start,
            "load_average_at_end": os.getloadavg(),
        },
        "rows": rows,
        "seconds_total": round(time.monotonic() - started, 1),
    }
    write_result("bench_robot_step" + suffix, summary)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
