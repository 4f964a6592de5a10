"""Where a non-policy physics substep of the exact step path spends its time, part by part.

One vecsim env of one task (no cameras), pinned to one core, stepped a few times; then each part
of a non-policy substep (``vecsim.engine.tasks._fast_step``) is called on its own, over and over, from the
state the steps left: MuJoCo's position and velocity stages (``_forward``); the controller as it
runs from Python (``_update``, then its torques ``ArmStep.control``; robosuite's numba OSC kernel
``opspace_matrices`` inside it alone); the same controller work as the exact path now runs it,
one ``mj_jacSite`` and one compiled call (``ArmStep.fused_control``; the compiled
``vecsim.engine.tasks._osc_kernel.osc_substep`` alone); and one ``mj_step`` for scale. Each figure is the
fastest of ``--repeats`` rounds of ``--number`` calls, in microseconds: what the part costs when
nothing else takes the core.

    python bench/bench_controller_parts.py --task libero_10/0 --cpu 0

Writes out/bench/bench_controller_parts[_<tag>].json and prints ``RESULT {json}``.
"""

from __future__ import annotations

import argparse
import logging
import os
import timeit
from typing import Any

import mujoco
import numpy as np
from lib.records import write_result

log = logging.getLogger("bench_controller_parts")


def parts(task_id: str, number: int, repeats: int) -> dict[str, float]:
    """Return the fastest time, in microseconds, of each part of one non-policy substep."""
    import robosuite.utils.control_utils

    from vecsim.config import CameraConfig
    from vecsim.engine.tasks import ArmStep, ExactStep, make_env, osc_kernel

    env = make_env(task_id, CameraConfig(names=()), "lean")
    try:
        env.reset(options={"state_id": 0})
        for _ in range(5):
            env.step(np.zeros(7, np.float32))
        step = env._step_fn
        if not isinstance(step, ExactStep):
            raise SystemExit(f"{task_id} is not on the exact step path ({env.step_path})")
        model, data = step.model, step.data
        arm = step.arms[0]
        controller = arm.robot.controller
        arm_step = ArmStep(arm, np.zeros(arm.action_dim), model)
        if not step.fused or not arm_step.start_fused(controller, step.data_arrays):
            raise SystemExit(f"{task_id}: the compiled controller (osc_substep) is not available here")
        utils = robosuite.utils.control_utils
        kernel = osc_kernel().osc_substep

        def python_controller() -> None:
            step._update(arm, controller)
            arm_step.control(controller, data)

        calls: dict[str, Any] = {
            "forward (position + velocity stages)": lambda: step._forward(False),
            "_update": lambda: step._update(arm, controller),
            "control": lambda: arm_step.control(controller, data),
            "opspace_matrices (in control)": lambda: utils.opspace_matrices(
                controller.mass_matrix, controller.J_full, controller.J_pos, controller.J_ori
            ),
            "controller from Python (_update + control)": python_controller,
            "compiled controller (fused_control: mj_jacSite + osc_substep)": lambda: arm_step.fused_control(
                model, data
            ),
            "osc_substep (in fused_control)": lambda: kernel(*arm_step.kernel_args),
        }
        timings = {
            name: min(timeit.repeat(call, number=number, repeat=repeats)) / number * 1e6 for name, call in calls.items()
        }
        scratch = mujoco.MjData(model)
        spec = int(mujoco.mjtState.mjSTATE_INTEGRATION)
        state = np.empty(mujoco.mj_stateSize(model, spec))
        mujoco.mj_getState(model, data, state, spec)

        def mj_steps() -> None:
            mujoco.mj_setState(model, scratch, state, spec)
            for _ in range(25):
                mujoco.mj_step(model, scratch)

        timings["mj_step (floor, mean of 25 from the same state)"] = (
            min(timeit.repeat(mj_steps, number=max(1, number // 25), repeat=repeats))
            / (max(1, number // 25) * 25)
            * 1e6
        )
        return {name: round(value, 2) for name, value in timings.items()}
    finally:
        env.close()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--task", default="libero_10/0")
    parser.add_argument("--number", type=int, default=2000, help="calls per round")
    parser.add_argument("--repeats", type=int, default=15, help="rounds; the fastest counts")
    parser.add_argument("--cpu", type=int, help="the core to pin to (default: the last one allowed)")
    parser.add_argument("--tag", help="suffix of the output file's name")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    cpu = args.cpu if args.cpu is not None else max(os.sched_getaffinity(0))
    os.sched_setaffinity(0, {cpu})
    load_at_start = os.getloadavg()
    microseconds = parts(args.task, args.number, args.repeats)
    log.info("%s: %s", args.task, microseconds)
    summary = {
        "task": args.task,
        "fastest_us": microseconds,
        "setup": {
            "number": args.number,
            "repeats": args.repeats,
            "pinned_to": cpu,
            "load_average_at_start": load_at_start,
            "load_average_at_end": os.getloadavg(),
        },
    }
    suffix = f"_{args.tag}" if args.tag else ""
    write_result("bench_controller_parts" + suffix, summary)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
