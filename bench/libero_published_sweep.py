"""LIBERO's published loop, episode by episode: vecsim's resets to state k against LIBERO's episode k.

The oracle is LIBERO run as OpenVLA-OFT's ``run_libero_eval.py`` and openpi's
``examples/libero/main.py`` run it: one ``OffScreenRenderEnv`` per task, ``env.seed(seed)`` once,
then for every episode ``k = 0, 1, ...`` ``env.reset()``, ``env.set_init_state(init_states[k])``
and 10 steps of ``[0, 0, 0, 0, 0, 0, -1]``. LIBERO's hard reset places the fixtures anew each
episode, so episode ``k``'s scene depends on ``k``. Every episode up to the largest asked for is
reset and settled; for the episodes asked for (default 0, 1, 17, 49) the first frame and the
frames after ``--steps`` fixed random actions (default 20) are kept.

vecsim is ``vecsim.engine.tasks.make_env`` in this process (the env class a pod runs), reset to state
``k``, twice: with the job config's defaults (``fixture_rule: published``) and with
``fixture_rule: first_reset`` (vecsim's rule before, a fresh env's first placement for every
``k``). Per (task, k, rule) it records the worst difference over the frames of each quantity
(pixels per camera, joints in mrad, eef in mm, the 8-float state, the full MuJoCo state) and, for
the cameras, the share of pixels that differ and their mean absolute difference, at the first
frame. It also times building each env: the published rule's build replays LIBERO's resets
(uncached: ``--cache-dir`` starts empty) or reads them from the cache (the second build).

    PYTHONPATH=$PWD MUJOCO_GL=egl python bench/libero_published_sweep.py [--tasks libero_10/9 ...]
        [--episodes 0,1,17,49] [--steps 20] [--size 128] [--seed 0] [--tag name]
"""

from __future__ import annotations

import argparse
import logging
import os
import tempfile
import time
from typing import Any

import mujoco
import numpy as np
from lib.records import write_result
from lib.parity import CAMERAS, NO_OP, SETTLE_STEPS, differences, exact, libero_frame, vecsim_frame, worst

from vecsim.config import CameraConfig, LiberoProtocol
from vecsim.engine.tasks import get_task, make_env
from vecsim.engine.tasks import ensure_config, fixtures_path, init_states, libero_benchmark, load_fixtures

log = logging.getLogger("bench.libero_published_sweep")


class ReplayTimes(logging.Handler):
    """Keeps the seconds of every replay vecsim logs ("replayed N LIBERO resets of T ... in S s")."""

    def __init__(self) -> None:
        super().__init__()
        self.seconds: list[float] = []

    def emit(self, record: logging.LogRecord) -> None:
        if isinstance(record.msg, str) and record.msg.startswith("replayed ") and record.args:
            self.seconds.append(float(record.args[3]))


RULES = ("published", "first_reset")


def libero_loop(task_id: str, episodes: list[int], size: int, seed: int, actions: np.ndarray) -> tuple[dict, dict]:
    """Run LIBERO's published loop up to the last episode asked for; return the kept frames per
    episode and the loop's timings."""
    from libero.libero.envs import OffScreenRenderEnv

    suite, index = task_id.split("/")
    states = init_states(get_task(task_id))
    started = time.perf_counter()
    env = OffScreenRenderEnv(
        bddl_file_name=libero_benchmark(suite).get_task_bddl_file_path(int(index)),
        camera_heights=size,
        camera_widths=size,
    )
    timings: dict[str, float] = {"build_s": time.perf_counter() - started, "resets_s": 0.0}
    frames: dict[int, list[dict[str, Any]]] = {}
    try:
        env.seed(seed)
        for k in range(max(episodes) + 1):
            started = time.perf_counter()
            env.reset()
            timings["resets_s"] += time.perf_counter() - started
            raw = env.set_init_state(states[k])
            for _ in range(SETTLE_STEPS):
                raw, _, _, _ = env.step(NO_OP)
            if k in episodes:
                kept = [libero_frame(env, raw)]
                for action in actions:
                    kept.append(libero_frame(env, env.step(action.tolist())[0]))
                frames[k] = kept
        timings["reset_mean_s"] = timings["resets_s"] / (max(episodes) + 1)
        return frames, {key: round(value, 3) for key, value in timings.items()}
    finally:
        env.close()
        mujoco.mj_clearCache(mujoco.mj_getCache())


def pixel_shares(theirs: dict[str, Any], ours: dict[str, Any]) -> dict[str, float]:
    """Per camera: the share of pixels that differ and the mean absolute difference of all values."""
    found = {}
    for name in CAMERAS:
        a, b = theirs["images"][name].astype(np.int16), ours["images"][name].astype(np.int16)
        found[f"{name}_differing"] = round(float((a != b).any(-1).mean()), 4)
        found[f"{name}_mean_abs"] = round(float(np.abs(a - b).mean()), 3)
    return found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--tasks", nargs="*", default=[f"libero_10/{i}" for i in range(10)])
    parser.add_argument("--episodes", default="0,1,17,49", help="episodes k compared, e.g. '0,1,17,49'")
    parser.add_argument("--steps", type=int, default=20, help="fixed random actions after settling")
    parser.add_argument("--size", type=int, default=128, help="camera height and width")
    parser.add_argument("--seed", type=int, default=0, help="env.seed of the loop (0 OpenVLA-OFT, 7 openpi)")
    parser.add_argument("--cache-dir", default=None, help="vecsim's cache (default: a new empty folder)")
    parser.add_argument("--tag", default="", help="suffix of the result's name")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    os.environ["VECSIM_CACHE_DIR"] = args.cache_dir or tempfile.mkdtemp(prefix="vecsim-published-")
    replays = ReplayTimes()
    logging.getLogger("vecsim").addHandler(replays)
    ensure_config()
    episodes = sorted({int(k) for k in args.episodes.split(",")})
    actions = np.random.default_rng(13).uniform(-1.0, 1.0, (args.steps, 7)).astype(np.float32)
    camera = CameraConfig(names=CAMERAS, height=args.size, width=args.size)
    cases: list[dict[str, Any]] = []
    builds: list[dict[str, Any]] = []
    started = time.perf_counter()
    for task_id in args.tasks:
        # LIBERO's frames first: its render contexts and vecsim's never share the process at once.
        theirs, loop_timings = libero_loop(task_id, episodes, args.size, args.seed, actions)
        build = {"task_id": task_id, "libero": loop_timings}
        for rule in RULES + ("published",):
            protocol = LiberoProtocol(fixture_seed=args.seed, fixture_rule=rule)
            began = time.perf_counter()
            env = make_env(task_id, camera, libero=protocol)
            seconds = round(time.perf_counter() - began, 2)
            key = f"{rule}_build_s" if f"{rule}_build_s" not in build else f"{rule}_cached_build_s"
            build[key] = seconds
            if rule == "published" and replays.seconds and "replay_s" not in build:
                build["replay_s"] = replays.seconds[-1]
            if key.endswith("cached_build_s"):
                began = time.perf_counter()
                path = fixtures_path(get_task(task_id), args.seed)
                loaded = load_fixtures(path, len(env._fixtures), env.inner.sim.model.nbody)
                build["cached_read_s"] = round(time.perf_counter() - began, 4)
                assert loaded is not None, "the published fixtures were not cached"
                env.close()  # built only to time the cached build
                continue
            try:
                for k in episodes:
                    obs, _ = env.reset(options={"state_id": k})
                    ours = [vecsim_frame(env, obs)]
                    for action in actions:
                        ours.append(vecsim_frame(env, env.step(action)[0]))
                    rows = [differences(t, o) for t, o in zip(theirs[k], ours)]
                    case = {"task_id": task_id, "k": k, "rule": rule, "worst": worst(rows)}
                    case["exact"] = exact(case["worst"])
                    case["first_frame"] = pixel_shares(theirs[k][0], ours[0])
                    cases.append(case)
                    log.info("%s k %d %s: exact %s %s", task_id, k, rule, case["exact"], case["first_frame"])
            finally:
                env.close()
        builds.append(build)
        log.info("%s timings %s", task_id, build)
    summary = {
        rule: {
            "cases": sum(case["rule"] == rule for case in cases),
            "exact": sum(case["exact"] for case in cases if case["rule"] == rule),
        }
        for rule in RULES
    }
    summary.update(
        tasks=args.tasks,
        episodes=episodes,
        steps=args.steps,
        size=args.size,
        seed=args.seed,
        seconds=round(time.perf_counter() - started, 1),
    )
    name = f"libero_published_sweep{'_' + args.tag if args.tag else ''}"
    write_result(name, summary, {"cases": cases, "builds": builds})


if __name__ == "__main__":
    main()
