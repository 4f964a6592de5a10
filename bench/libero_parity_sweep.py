"""LIBERO parity sweep: vecsim's LIBERO tasks against LIBERO itself after reset and settling.

For every (task, init state) asked for (default: every LIBERO-10 task, all 50 init states), the
oracle is what a published LIBERO evaluation shows its policy first: a freshly built
``OffScreenRenderEnv``, ``env.seed(0); env.reset(); env.set_init_state(init_states[k])``, 10
steps of ``[0, 0, 0, 0, 0, 0, -1]``, images turned ``raw[::-1, ::-1]``, the 8-float state
(eef position, robosuite's axis-angle of the eef quaternion, gripper joints). vecsim is one env
per task (``vecsim.engine.tasks.make_env`` with the defaults of the checkout it imports), reset to
state ``k``: what its first observation is. ``--steps N`` then applies N fixed random actions to
both and keeps the worst difference over them.

Per case it records the largest absolute difference of each camera's pixels, of the arm's
joint angles (mrad), of the end-effector position (mm), of the 8-float state (when vecsim gives
one) and of the full MuJoCo state; the summary counts the cases that are bit-identical. Run it
against another checkout (``PYTHONPATH=/path/to/checkout``) to measure that one: it only uses
what every vecsim version offers (``make_env``, ``reset``, ``step``, ``proprio``, ``images``).

Its oracle is a fresh LIBERO env per state: what ``fixture_rule: first_reset`` gives every state.
Under a checkout's default ``published`` rule, states ``k > 0`` of tasks whose fixtures LIBERO's
resets move are episode ``k`` of the published loop instead: ``bench/libero_published_sweep.py``
compares those.

``--client-settle N`` sends N no-op steps to vecsim after its reset, as a user of a checkout
without settle steps would; ``--render`` picks vecsim's render preset.

``--pictures DIR`` also writes, for the first case, vecsim's and LIBERO's agentview and wrist
frames side by side (PNG), as ``docs/libero.md`` shows them.

    PYTHONPATH=$PWD MUJOCO_GL=egl python bench/libero_parity_sweep.py [--tasks libero_10/0 ...]
        [--states 0-49 | 0,25,49] [--size 128] [--steps 0] [--pictures docs/img] [--render lean]
        [--client-settle 10] [--tag name]
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
from lib.parity import CAMERAS, NO_OP, SETTLE_STEPS, differences, exact, libero_frame, vecsim_frame, worst
from lib.records import write_result
from PIL import Image

from vecsim.config import CameraConfig
from vecsim.engine.tasks import get_task, make_env
from vecsim.engine.tasks import ensure_config, init_states, libero_benchmark

log = logging.getLogger("bench.libero_parity_sweep")


def libero_frames(task_id: str, state_id: int, size: int, actions: np.ndarray) -> list[dict[str, Any]]:
    """What LIBERO's evaluation sees after settling, then after each action."""
    from libero.libero.envs import OffScreenRenderEnv

    suite, index = task_id.split("/")
    env = OffScreenRenderEnv(
        bddl_file_name=libero_benchmark(suite).get_task_bddl_file_path(int(index)),
        camera_heights=size,
        camera_widths=size,
    )
    try:
        env.seed(0)
        env.reset()
        raw = env.set_init_state(init_states(get_task(task_id))[state_id])
        for _ in range(SETTLE_STEPS):
            raw, _, _, _ = env.step(NO_OP)
        frames = [libero_frame(env, raw)]
        for action in actions:
            raw, _, _, _ = env.step(action.tolist())
            frames.append(libero_frame(env, raw))
        return frames
    finally:
        env.close()
        # MuJoCo's compiler keeps each loaded scene's assets cached (hundreds of MB for LIBERO).
        mujoco.mj_clearCache(mujoco.mj_getCache())


def write_pictures(directory: Path, task_id: str, state_id: int, theirs: dict, ours: dict) -> list[str]:
    directory.mkdir(parents=True, exist_ok=True)
    written = []
    for name in CAMERAS:
        pair = np.concatenate([ours["images"][name], theirs["images"][name]], axis=1)
        path = directory / f"libero_parity_{task_id.replace('/', '_')}_state{state_id}_{name}.png"
        Image.fromarray(pair).save(path)
        written.append(str(path))
    return written


def parse_states(text: str) -> list[int]:
    """``"0-49"`` -> 0..49; ``"0,25,49"`` -> those three."""
    states: list[int] = []
    for part in text.split(","):
        first, _, last = part.partition("-")
        states += range(int(first), int(last or first) + 1)
    return states


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--tasks", nargs="*", default=[f"libero_10/{i}" for i in range(10)])
    parser.add_argument("--states", default="0-49", help="init states: '0-49', '0,25,49'")
    parser.add_argument("--size", type=int, default=128, help="camera height and width")
    parser.add_argument("--steps", type=int, default=0, help="fixed random actions after settling")
    parser.add_argument("--pictures", type=Path, default=None, help="write the first case's frames here")
    parser.add_argument(
        "--client-settle",
        type=int,
        default=0,
        help="no-op steps this script sends after vecsim's reset (to settle a checkout that does not)",
    )
    parser.add_argument("--render", default=None, help="vecsim's render preset (default: the checkout's)")
    parser.add_argument("--tag", default="", help="suffix of the result's name (e.g. 'main')")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    ensure_config()
    states = parse_states(args.states)
    actions = np.random.default_rng(13).uniform(-1.0, 1.0, (args.steps, 7))
    camera = CameraConfig(names=CAMERAS, height=args.size, width=args.size)
    cases: list[dict[str, Any]] = []
    pictures: list[str] = []
    started = time.perf_counter()
    for task_id in args.tasks:
        # LIBERO's frames first: its render contexts and vecsim's never share the process at once.
        theirs = {state_id: libero_frames(task_id, state_id, args.size, actions) for state_id in states}
        env = make_env(task_id, camera) if args.render is None else make_env(task_id, camera, args.render)
        try:
            for state_id in states:
                obs, _ = env.reset(options={"state_id": state_id})
                for _ in range(args.client_settle):
                    obs = env.step(np.array(NO_OP))[0]
                ours = [vecsim_frame(env, obs)]
                for action in actions:
                    ours.append(vecsim_frame(env, env.step(action)[0]))
                rows = [differences(t, o) for t, o in zip(theirs[state_id], ours)]
                case = {"task_id": task_id, "state_id": state_id, "reset": rows[0], "worst": worst(rows)}
                case["exact"] = exact(case["worst"])
                cases.append(case)
                log.info("%s state %d: %s", task_id, state_id, case["worst"])
                if args.pictures is not None and not pictures:
                    pictures = write_pictures(args.pictures, task_id, state_id, theirs[state_id][0], ours[0])
        finally:
            env.close()
    summary = {
        "cases": len(cases),
        "exact": sum(case["exact"] for case in cases),
        "size": args.size,
        "steps": args.steps,
        "render": args.render,
        "client_settle": args.client_settle,
        "worst": worst([case["worst"] for case in cases]) if cases else {},
        "seconds": round(time.perf_counter() - started, 1),
        "pictures": pictures,
    }
    write_result(f"libero_parity_sweep{'_' + args.tag if args.tag else ''}", summary, {"cases": cases})


if __name__ == "__main__":
    main()
