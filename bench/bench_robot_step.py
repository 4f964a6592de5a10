"""A LIBERO env-step: vecsim's step paths against LIBERO's own env and MuJoCo's floor, one core.

Per task, side by side in interleaved rounds on one pinned core, no cameras:

- ``exact``: vecsim's env (``make_env``) on its default step path (``vecsim.tasks._fast_step``);
- ``library``: the same env on the ``library`` path (robosuite's own ``step``, as before);
- ``approx``: the same env on the opt-in ``approx`` path (not bit-identical);
- ``libero``: LIBERO's own ``OffScreenRenderEnv`` (``use_camera_obs=False``; it still makes its
  offscreen GL context, which a step does not use), after LIBERO's own ``seed(0)``, ``reset()``
  and ``set_init_state`` of the same init state;
- ``floor``: ``mj_step`` on a copy of the vecsim env's state, as many as the steps hold
  (25 per env-step at LIBERO's 500 Hz physics and 20 Hz control);
- with ``--changes``, the exact path's changes one at a time (each a subclass of ``ExactStep``
  that puts robosuite's own calls back for what is not yet changed);
- resets: vecsim's ``reset(options={"state_id": k})`` against LIBERO's
  ``seed(0)`` + ``reset()`` + ``set_init_state``.

Every vecsim measurement restarts from the same reset and steps the same actions, so all vecsim
paths run the same trajectory. ``--parity-episodes`` instead runs full-length episodes of every
task on the exact and the library path side by side and compares them bit for bit at every step
(MuJoCo state, every observable, reward, success); the first difference fails the run. With
``--parity-path approx`` it measures the opt-in ``approx`` path's drift from the library instead.

    python bench/bench_robot_step.py                                   # LIBERO-10, 3 rounds
    python bench/bench_robot_step.py --tasks libero_10/0 --rounds 2 --changes
    python bench/bench_robot_step.py --parity-episodes --episodes 1    # 520 steps per task
    python bench/bench_robot_step.py --parity-episodes --parity-path approx

Writes out/bench/bench_robot_step[_parity_<path>][_<tag>].json and prints ``RESULT {json}``.
"""

from __future__ import annotations

import argparse
import copy
import logging
import os
import statistics
import time
from typing import Any

import mujoco
import numpy as np
from common import spread, write_result

log = logging.getLogger("bench_robot_step")

# The arrays of MuJoCo's state that an env-step carries forward, compared bit for bit.
STATE_FIELDS = ("time", "qpos", "qvel", "act", "ctrl", "qacc_warmstart", "qacc", "sensordata", "mocap_pos", "mocap_quat")


def action_table(steps: int, seed: int) -> np.ndarray:
    """Return ``steps`` random 7-dim actions whose gripper closes and opens every 20 steps."""
    rng = np.random.default_rng(seed)
    actions = rng.uniform(-0.5, 0.5, (steps, 7))
    actions[:, 6] = np.where((np.arange(steps) // 20) % 2 == 1, 1.0, -1.0)
    return actions


def change_variants() -> dict[str, Any]:
    """Return the exact path's changes as cumulative ``ExactStep`` subclasses, first to last."""
    from vecsim.tasks._fast_step import ExactStep

    class ControllerOnly(ExactStep):
        # robosuite's forwards, mj_step and per-substep observable updates; only the
        # controller's Python is the fast one.
        def _forward(self, policy_step: bool) -> None:
            mujoco.mj_forward(self.model, self.data)

        def _controller_forward(self, policy_step: bool) -> None:
            mujoco.mj_forward(self.model, self.data)

        def _integrate(self) -> None:
            mujoco.mj_step(self.model, self.data)

        def _observable_plan(self, substeps: int) -> None:
            return None

    class PlusObservables(ControllerOnly):
        def _observable_plan(self, substeps: int) -> Any:
            return ExactStep._observable_plan(self, substeps)

    class PlusForwards(ExactStep):
        # One full forward per substep, but every forward still computes every sensor.
        def _forward(self, policy_step: bool) -> None:
            mujoco.mj_forward(self.model, self.data)

        def _controller_forward(self, policy_step: bool) -> None:
            mujoco.mj_forwardSkip(self.model, self.data, int(mujoco.mjtStage.mjSTAGE_VEL), 0)

    return {
        "controller": ControllerOnly,
        "+observables": PlusObservables,
        "+forwards": PlusForwards,
        "+sensors (exact)": ExactStep,
    }


class LiberoOwn:
    """LIBERO's own ``OffScreenRenderEnv`` of one task, reset LIBERO's way."""

    def __init__(self, task_id: str) -> None:
        from vecsim.tasks._base import stdout_to_log
        from vecsim.tasks._libero import _benchmark, init_states
        from vecsim.tasks import get_task

        suite, index = task_id.split("/", 1)
        # _benchmark writes LIBERO's config first: importing LIBERO without it asks on stdin.
        bddl_file = _benchmark(suite).get_task_bddl_file_path(int(index))
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


def time_steps(step: Any, actions: np.ndarray) -> float:
    """Return seconds per call of ``step`` over ``actions``."""
    started = time.perf_counter()
    for action in actions:
        step(action)
    return (time.perf_counter() - started) / len(actions)


def measure_task(task_id: str, args: argparse.Namespace) -> dict[str, Any]:
    """Measure one task's env-step paths, floor and resets in ``args.rounds`` interleaved rounds."""
    from vecsim.config import CameraConfig
    from vecsim.tasks import make_env

    env = make_env(task_id, CameraConfig(names=()), "lean")
    own = LiberoOwn(task_id) if task_id.startswith("libero") else None
    actions = action_table(args.steps, seed=1)
    variants = change_variants() if args.changes else {}
    model = env.inner.sim.model._model
    substeps = int(env.inner.control_timestep / env.inner.model_timestep)
    per: dict[str, list[float]] = {}

    def record(name: str, seconds: float) -> None:
        per.setdefault(name, []).append(seconds * 1e3)

    def vecsim_run(path: str, variant: Any = None) -> float:
        env.set_step_path(path)
        if variant is not None:
            env._step_fn = variant(env.inner)
        env.reset(options={"state_id": 0})
        return time_steps(env.step, actions)

    vecsim_run("exact")  # warm-up: numba kernels, caches
    for round_ in range(args.rounds):
        record("exact", vecsim_run("exact"))
        record("library", vecsim_run("library"))
        record("approx", vecsim_run("approx"))
        for name, variant in variants.items():
            record(name, vecsim_run("exact", variant))
        # The floor: the substeps those env-steps hold, on a copy of the state the exact path reached.
        env.set_step_path("exact")
        env.reset(options={"state_id": 0})
        for action in actions[: args.steps // 2]:
            env.step(action)
        data = copy.copy(env.inner.sim.data._data)
        started = time.perf_counter()
        for _ in range(args.steps * substeps):
            mujoco.mj_step(model, data)
        record("floor", (time.perf_counter() - started) / args.steps)
        started = time.perf_counter()
        for state_id in range(args.resets):
            env.reset(options={"state_id": state_id})
        record("reset_vecsim", (time.perf_counter() - started) / args.resets)
        if own is not None:
            own.reset(0)
            record("libero", time_steps(own.env.step, actions))
            started = time.perf_counter()
            for state_id in range(args.resets):
                own.reset(state_id)
            record("reset_libero", (time.perf_counter() - started) / args.resets)
        log.info("%s round %d: %s", task_id, round_ + 1, {k: round(v[-1], 2) for k, v in per.items()})
    env.close()
    if own is not None:
        own.close()
    med = {name: statistics.median(values) for name, values in per.items()}
    row: dict[str, Any] = {"ms": {name: round(value, 3) for name, value in med.items()}}
    row["exact_over_floor"] = round(med["exact"] / med["floor"], 3)
    row["library_over_floor"] = round(med["library"] / med["floor"], 3)
    row["library_over_exact"] = round(med["library"] / med["exact"], 3)
    row["approx_over_floor"] = round(med["approx"] / med["floor"], 3)
    if own is not None:
        row["libero_over_floor"] = round(med["libero"] / med["floor"], 3)
        row["libero_over_exact"] = round(med["libero"] / med["exact"], 3)
        row["reset_libero_over_vecsim"] = round(med["reset_libero"] / med["reset_vecsim"], 3)
    for name in variants:
        row.setdefault("changes_over_floor", {})[name] = round(med[name] / med["floor"], 3)
    row["rounds_ms"] = {name: [round(v, 3) for v in values] for name, values in per.items()}
    return row


def snapshot(env: Any) -> dict[str, Any]:
    """Return what one env-step leaves behind: MuJoCo's state arrays and every observable's value."""
    data = env.inner.sim.data._data
    state = {f"data.{field}": np.array(getattr(data, field)) for field in STATE_FIELDS}
    for name, obs in env.inner._observables.items():
        state[f"observable {name}"] = np.array(obs.obs)
    return state


def parity_episode(task_id: str, episode: int, steps: int, path: str) -> dict[str, Any]:
    """Run one episode on ``path`` and on the library path side by side; return how they compare.

    ``exact`` stops at the first difference; ``approx`` runs on and measures the drift.
    """
    from vecsim.config import CameraConfig
    from vecsim.tasks import make_env

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
            "task": task_id, "episode": episode, "path": path, "steps": index + 1, "identical": first is None,
            "first_difference": first, "max_abs_qpos_difference": drift, "success_steps": successes,
            "success_disagreements": disagreements,
        }  # fmt: skip
    finally:
        for env in envs.values():
            env.close()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tasks", help="comma-separated task ids (default: LIBERO-10's ten)")
    parser.add_argument("--steps", type=int, default=40, help="env-steps per measurement")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--resets", type=int, default=3, help="resets per measurement")
    parser.add_argument("--changes", action="store_true", help="also measure the exact path's changes one at a time")
    parser.add_argument("--cpu", type=int, help="the core to pin to (default: the last one allowed)")
    parser.add_argument("--parity-episodes", action="store_true", help="compare full episodes bit for bit instead")
    parser.add_argument("--episodes", type=int, default=1, help="episodes per task with --parity-episodes")
    parser.add_argument("--parity-path", default="exact", choices=("exact", "approx"),
                        help="the step path --parity-episodes compares with the library path")
    parser.add_argument("--episode-steps", type=int, default=520, help="steps per episode with --parity-episodes")
    parser.add_argument("--tag", help="suffix of the output file's name")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    cpu = args.cpu if args.cpu is not None else max(os.sched_getaffinity(0))
    os.sched_setaffinity(0, {cpu})
    if args.tasks:
        tasks = [t for t in args.tasks.split(",") if t]
    else:
        from vecsim.tasks import suite_tasks

        tasks = [t.task_id for t in suite_tasks("libero_10")]
    started = time.monotonic()
    suffix = f"_{args.tag}" if args.tag else ""
    if args.parity_episodes:
        episodes = []
        for task_id in tasks:
            for episode in range(args.episodes):
                episodes.append(parity_episode(task_id, episode, args.episode_steps, args.parity_path))
                log.info("parity %s", episodes[-1])
        identical = all(e.get("identical") for e in episodes)
        summary = {
            "path": args.parity_path,
            "baseline": "the library step path (robosuite's/LIBERO's own step) on an identically built and reset env",
            "identical": identical,
            "setup": {"tasks": tasks, "episodes_per_task": args.episodes, "steps_per_episode": args.episode_steps,
                      "pinned_to": cpu},
            "episodes": episodes,
            "seconds_total": round(time.monotonic() - started, 1),
        }  # fmt: skip
        write_result(f"bench_robot_step_parity_{args.parity_path}" + suffix, summary)
        return 0 if identical or args.parity_path != "exact" else 1
    rows = {task_id: measure_task(task_id, args) for task_id in tasks}

    def across(key: str) -> dict[str, float] | None:
        values = [row[key] for row in rows.values() if key in row]
        return spread(values) if values else None

    summary = {
        "baseline": "MuJoCo's floor (mj_step on a copy of the same state) and LIBERO's own OffScreenRenderEnv step, same core, same rounds",
        "ratio": statistics.median(row["exact_over_floor"] for row in rows.values()),
        "target": "exact <= 2x floor; LIBERO's step >= 2.5x exact",
        "across_tasks": {key: across(key) for key in (
            "exact_over_floor", "library_over_floor", "library_over_exact", "approx_over_floor", "libero_over_floor",
            "libero_over_exact",
            "reset_libero_over_vecsim")},
        "setup": {"tasks": tasks, "steps": args.steps, "rounds": args.rounds, "resets": args.resets, "pinned_to": cpu,
                  "cameras": "none", "changes": args.changes},
        "rows": {task: {k: v for k, v in row.items() if k != "rounds_ms"} for task, row in rows.items()},
        "seconds_total": round(time.monotonic() - started, 1),
    }  # fmt: skip
    write_result("bench_robot_step" + suffix, summary, {task: row["rounds_ms"] for task, row in rows.items()})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
