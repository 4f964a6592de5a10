"""RLinf's own LIBERO env against vecsim's RLinf env: env-steps/s of ``chunk_step`` side by side.

Contenders, on the same CPU cores, the same tasks and reset ids, the same scripted chunks:

- ``rlinf``: RLinf 0.3.0's ``LiberoEnv`` (its subprocess vector env, one LIBERO env a process,
  rendering both cameras after every action), its processes pinned to the sim cores;
- ``vecsim``: :class:`vecsim.trainers.rlinf.VecsimLiberoEnv` over standalone pods, one pod a sim
  core (pinned), slot ``i``'s task on the pod of core ``i % cores`` (one env each), the pods
  rendering once a chunk.

With ``--mjwarp``, ``vecsim`` is the same env over one ``mjwarp`` pod (MuJoCo Warp on the GPU,
one batch of worlds a task), started with ``--mjwarp-pythonpath`` (its stack pins mujoco 4; this
process runs the CPU stack, for RLinf's env), on the LIBERO-10 tasks whose exported scenes the
engine serves (``--task-ids``; default: every one found under ``$VECSIM_MJWARP_SCENES`` for the
pods' protocol), both envs restricted to them by RLinf's ``task_id_filter``. RLinf's env runs
only up to ``--rlinf-max-envs`` slots (a process and an EGL context a slot); larger slot counts
time the ``mjwarp`` pod alone, and the summary sets its best rate beside RLinf's best.

Slot ``i`` runs task ``i % n`` of the ``n`` tasks (reset id ``task * 50 + (i // n) % 50``), so
both see the same task mix. Each round (the order alternating) resets every slot (not timed) and
times ``--chunks`` calls of ``chunk_step`` with K actions a slot; env-steps/s = slots * K *
chunks / that time. Settle: RLinf's (15 steps, gripper open), the pods' ``settle_steps: 15``, and
``fixture_rule: first_reset`` (RLinf's placement).

Commands::

    source .device/setup.sh && MUJOCO_GL=egl python bench/bench_rlinf.py --gpu --copy-to "$OUT"
    python bench/bench_rlinf.py --mjwarp --mjwarp-pythonpath /tmp/site-mjw:/tmp/site --envs 24,512
    python bench/bench_rlinf.py --smoke     # here (CI): 2 slots of libero_spatial/0, 32x32, 1 round

Writes out/bench/bench_rlinf[_smoke|_mjwarp].json and prints one ``RESULT {json}`` line.
``--gpu``: LIBERO-10, two 256x256 cameras, K = 8, 12 and 24 slots on 12 sim cores, 2 rounds;
``--mjwarp``: the same cameras and K, 24 and 1,024 slots.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import shutil
import subprocess
import sys
import tempfile
import time
import urllib.request
from collections import Counter
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

# One BLAS/OpenMP thread a process, for RLinf's env processes (spawned: they read this
# environment) and for the pods alike. Left at the libraries' defaults (a thread per core each),
# RLinf's LiberoEnv measured 7.4-7.7 env-steps/s on the H100 node, and ~180 with these
# (docs/benchmarks.md, "Trainers"); vecsim's pods measured the same either way.
for _threads in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_threads, "1")

import numpy as np  # after the thread settings, which BLAS reads as it loads
from lib.pods import paired_ratio, rate_spread, setup_logging
from lib.machine import cores_first, cpu_topology, gl_probe, split_cores
from lib.jobs import RLINF_PROTOCOL
from lib.records import write_result

from vecsim.config import Assignment, TaskBlock
from vecsim.suites import LIBERO_SUITES

log = logging.getLogger("bench.rlinf")


def stand_in_for_rlinf_scheduler() -> None:
    """Without Ray (the GPU machine's bundle cannot carry its 79 MB), give ``rlinf.scheduler`` the
    one thing RLinf's LIBERO env path uses of it: ``rlinf.utils.logging.get_logger`` returns
    ``rlinf.scheduler.worker.Worker.logger``. At module level, so spawned env processes (which
    import this script as ``__mp_main__``) get it too."""
    import importlib.util
    import types

    if importlib.util.find_spec("ray") is not None or "rlinf.scheduler" in sys.modules:
        return
    worker = types.ModuleType("rlinf.scheduler.worker")
    worker.Worker = type("Worker", (), {"logger": logging.getLogger("RLinf")})
    scheduler = types.ModuleType("rlinf.scheduler")
    scheduler.__path__ = []
    scheduler.worker = worker
    sys.modules["rlinf.scheduler"], sys.modules["rlinf.scheduler.worker"] = scheduler, worker


stand_in_for_rlinf_scheduler()

CAMERAS = ("agentview", "robot0_eye_in_hand")
STATES_PER_TASK = 50
# The pods' LIBERO protocol: RLinf's (lib.jobs.RLINF_PROTOCOL).
PROTOCOL = RLINF_PROTOCOL
READY_TIMEOUT_S = 900.0
TARGET = 4.0  # issue 26: vecsim's RLinf env at least 4x RLinf's own (the largest slot count's paired median)


def slot_tasks(num_envs: int, tasks: Sequence[int]) -> list[int]:
    return [tasks[i % len(tasks)] for i in range(num_envs)]


def reset_ids(num_envs: int, tasks: Sequence[int]) -> np.ndarray:
    n = len(tasks)
    return np.array([tasks[i % n] * STATES_PER_TASK + (i // n) % STATES_PER_TASK for i in range(num_envs)])


def _blocks(suite: str, tasks: Sequence[int]) -> list[TaskBlock]:
    """A block a task, tasks in order, as many envs as ``tasks`` names it."""
    counts, blocks, start = Counter(tasks), [], 0
    for task in sorted(counts):
        blocks.append(TaskBlock(task_id=f"{suite}/{task}", env_start=start, num_envs=counts[task]))
        start += counts[task]
    return blocks


def _assignment(pod: str, blocks: list[TaskBlock], size: int, render: str | None, engine: str) -> Assignment:
    return Assignment.model_validate(
        {
            "generation": 0,
            "job_id": "bench-rlinf",
            "pod": pod,
            "stage_id": 0,
            "engine": engine,
            "tasks": blocks,
            "camera": {"names": list(CAMERAS), "height": size, "width": size},
            "render": render,
            "max_episode_steps": 10_000,
            "envs_per_worker": 0,
            "libero": PROTOCOL.model_dump(),
        }
    )


def pod_assignments(suite: str, tasks: Sequence[int], cores: int, size: int, render: str | None) -> list[Assignment]:
    """One pod a core; pod ``c`` holds one env for each slot ``i`` with ``i % cores == c``."""
    return [
        _assignment(f"rlinf-sim-{c}", _blocks(suite, tasks[c::cores]), size, render, "cpu")
        for c in range(min(cores, len(tasks)))
    ]


def mjwarp_assignment(suite: str, tasks: Sequence[int], size: int) -> Assignment:
    """One ``mjwarp`` pod holding every slot's env: one block (a batch of worlds) a task."""
    return _assignment("rlinf-mjwarp-0", _blocks(suite, tasks), size, None, "mjwarp")


def served_tasks(suite: str, num_tasks: int, root: Path | None = None) -> list[int]:
    """The suite's tasks whose scene, exported under :data:`PROTOCOL`, the ``mjwarp`` engine
    serves (read from the scenes' manifests, as the engine reads them)."""
    from vecsim.engine.mjwarp.scene import load_scene, refusal, scene_dir

    served = []
    for task in range(num_tasks):
        try:
            scene = load_scene(scene_dir(f"{suite}/{task}", PROTOCOL, root))
        except (FileNotFoundError, ValueError):
            continue
        if refusal(scene.manifest) is None:
            served.append(task)
    return served


def mjwarp_pod_env(pythonpath: str | None) -> dict[str, str]:
    """The ``mjwarp`` pod's environment: this checkout, then its own stack's ``pythonpath``."""
    code = str(Path(__file__).resolve().parents[1])
    return {"PYTHONPATH": ":".join(p for p in (code, pythonpath or os.environ.get("PYTHONPATH")) if p)}


def _free_port() -> int:
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _ready(url: str) -> bool:
    try:
        with urllib.request.urlopen(f"{url}/readyz", timeout=5) as answer:
            return answer.status == 200
    except OSError:
        return False


@contextlib.contextmanager
def standalone_pods(
    assignments: Sequence[Assignment],
    pins: Sequence[str | None],
    workdir: Path,
    env: Mapping[str, str] | None = None,
    ready_timeout_s: float = READY_TIMEOUT_S,
) -> Iterator[list[str]]:
    """Start ``vecsim pod`` processes (pod ``i`` pinned to ``pins[i]``, unpinned where None; ``env``
    over this process's environment), wait until ready, yield their URLs."""
    procs, urls = [], []
    try:
        for assignment, pin in zip(assignments, pins):
            path = workdir / f"{assignment.pod}.json"
            path.write_text(assignment.model_dump_json())
            port = _free_port()
            argv = [
                *(["taskset", "-c", pin] if pin is not None else []),
                sys.executable,
                "-m",
                "service.cli",
                "pod",
                "--host",
                "127.0.0.1",
                "--port",
                str(port),
                "--log-level",
                "warning",
                "--assignment",
                str(path),
                "--name",
                assignment.pod,
            ]
            log_file = (workdir / f"{assignment.pod}.log").open("ab")
            procs.append(
                subprocess.Popen(
                    argv,
                    stdout=log_file,
                    stderr=subprocess.STDOUT,
                    start_new_session=True,
                    env={
                        **os.environ,
                        **(env or {}),
                        "POD_NAME": assignment.pod,
                        "VECSIM_MAX_ENVS": str(assignment.num_envs),
                    },
                )
            )
            urls.append(f"http://127.0.0.1:{port}")
        end = time.monotonic() + ready_timeout_s
        for url, proc in zip(urls, procs):
            while not _ready(url):
                if proc.poll() is not None or time.monotonic() > end:
                    raise RuntimeError(f"pod {url} did not get ready (logs in {workdir})")
                time.sleep(1.0)
        yield urls
    finally:
        for proc in procs:
            proc.terminate()
        for proc in procs:
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                proc.kill()


def rlinf_config(
    suite: str, num_envs: int, size: int, pod_urls: Sequence[str] | None, task_ids: Sequence[int] | None = None
) -> Any:
    from omegaconf import OmegaConf

    cfg = {
        "env_type": "libero",
        "task_suite_name": suite,
        "seed": 0,
        "group_size": 1,
        "use_fixed_reset_state_ids": True,
        "use_ordered_reset_state_ids": False,
        "ignore_terminations": False,
        "auto_reset": False,
        "use_rel_reward": True,
        "reward_coef": 5.0,
        "max_episode_steps": 10_000,
        "reset_gripper_open": True,
        "video_cfg": {"save_video": False},
        "init_params": {"camera_heights": size, "camera_widths": size},
    }
    if task_ids is not None:
        cfg["task_id_filter"] = list(task_ids)
    if pod_urls is not None:
        cfg["vecsim"] = {"pod_urls": list(pod_urls)}
    return OmegaConf.create(cfg)


def build_rlinf(cfg: Any, num_envs: int, sim_cores: set[int], driver_cores: set[int]) -> Any:
    """RLinf's own LiberoEnv, its env processes started while this process runs on the sim cores."""
    from vecsim.engine.tasks import ensure_config

    ensure_config()
    from rlinf.envs.libero.libero_env import LiberoEnv

    os.sched_setaffinity(0, sim_cores)
    try:
        return LiberoEnv(cfg, num_envs, 0, 1, None)
    finally:
        os.sched_setaffinity(0, driver_cores)


def build_vecsim(cfg: Any, num_envs: int) -> Any:
    from vecsim.trainers.rlinf import VecsimLiberoEnv

    return VecsimLiberoEnv(cfg, num_envs, 0, 1, None)


def measure(env: Any, ids: np.ndarray, chunks: Sequence[Any]) -> float:
    """Reset every slot to ``ids`` (not timed), then env-steps/s over ``chunk_step`` of ``chunks``."""
    env.is_start = False
    env.reset(reset_state_ids=ids)
    started = time.perf_counter()
    for chunk in chunks:
        env.chunk_step(chunk)
    elapsed = time.perf_counter() - started
    return sum(int(np.prod(c.shape[:2])) for c in chunks) / elapsed


def scripted_chunks(num_envs: int, k: int, count: int) -> list[Any]:
    import torch

    rng = np.random.default_rng(0)
    return [torch.tensor(rng.uniform(-0.5, 0.5, (num_envs, k, 7)), dtype=torch.float32) for _ in range(count)]


def run_size(
    args: argparse.Namespace, num_envs: int, pins: list[str], driver: list[int], workdir: Path
) -> dict[str, Any]:
    """Both envs on ``num_envs`` slots (RLinf's only up to ``--rlinf-max-envs`` with ``--mjwarp``)."""
    tasks = slot_tasks(num_envs, args.task_ids)
    ids = reset_ids(num_envs, args.task_ids)
    chunks = scripted_chunks(num_envs, args.k, args.chunks)
    sim_cores = {int(c) for pin in pins for c in pin.split(",")}
    if args.mjwarp:
        pods = standalone_pods(
            [mjwarp_assignment(args.suite, tasks, args.size)],
            [None],
            workdir,
            mjwarp_pod_env(args.mjwarp_pythonpath),
            args.ready_timeout_s,
        )
        filtered = args.task_ids
    else:
        pods = standalone_pods(pod_assignments(args.suite, tasks, len(pins), args.size, args.render), pins, workdir)
        filtered = None
    with_rlinf = not args.mjwarp or num_envs <= args.rlinf_max_envs
    rates: dict[str, list[float]] = {"rlinf": [], "vecsim": []} if with_rlinf else {"vecsim": []}
    with pods as urls, contextlib.ExitStack() as closing:
        contenders = []
        if with_rlinf:
            cfg = rlinf_config(args.suite, num_envs, args.size, None, filtered)
            theirs = build_rlinf(cfg, num_envs, sim_cores, set(driver))
            closing.callback(theirs.env.close)
            contenders.append(("rlinf", theirs))
        ours = build_vecsim(rlinf_config(args.suite, num_envs, args.size, urls, filtered), num_envs)
        closing.callback(ours.close)
        contenders.append(("vecsim", ours))
        for r in range(args.rounds):
            for name, env in contenders[:: 1 if r % 2 == 0 else -1]:
                rates[name].append(measure(env, ids, chunks))
                log.info("%d slots, round %d, %s: %.1f env-steps/s", num_envs, r, name, rates[name][-1])
    row = {
        "slots": num_envs,
        "pods": len(urls),
        "env_steps_per_s": {name: rate_spread(values) for name, values in rates.items()},
        "per_round": rates,
    }
    if with_rlinf:
        row["vecsim_over_rlinf"] = paired_ratio(rates["vecsim"], rates["rlinf"])
    return row


def best_over_best(sizes: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """vecsim's best median rate over RLinf's best median rate, each at its own slot count."""
    best = {
        name: max(
            (s for s in sizes if name in s["env_steps_per_s"]), key=lambda s: s["env_steps_per_s"][name]["median"]
        )
        for name in ("vecsim", "rlinf")
    }
    rate = {name: row["env_steps_per_s"][name]["median"] for name, row in best.items()}
    return {
        "ratio": rate["vecsim"] / rate["rlinf"],
        "vecsim": {"slots": best["vecsim"]["slots"], "median": rate["vecsim"]},
        "rlinf": {"slots": best["rlinf"]["slots"], "median": rate["rlinf"]},
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    mode = parser.add_mutually_exclusive_group(required=True)
    mode.add_argument("--gpu", action="store_true", help="LIBERO-10, 256x256 x 2, K = 8, 12 and 24 slots, 12 sim cores")
    mode.add_argument("--smoke", action="store_true", help="2 slots of libero_spatial/0, 32x32, 2 chunks, 1 round")
    mode.add_argument("--mjwarp", action="store_true", help="as --gpu, vecsim's env over one mjwarp pod")
    parser.add_argument("--rounds", type=int, help="interleaved rounds (default 2; --smoke 1)")
    parser.add_argument("--envs", help="comma-separated slot counts (default 12,24; --smoke 2; --mjwarp 24,1024)")
    parser.add_argument(
        "--task-ids",
        dest="task_ids_text",
        help="--mjwarp: comma-separated LIBERO-10 task indices (default: those served)",
    )
    parser.add_argument("--rlinf-max-envs", type=int, default=24, help="--mjwarp: RLinf's env up to this many slots")
    parser.add_argument("--mjwarp-pythonpath", help="--mjwarp: the mjwarp pod's stack (mujoco 4, mujoco_warp)")
    parser.add_argument("--ready-timeout-s", type=float, default=READY_TIMEOUT_S, help="--mjwarp: wait for the pod")
    parser.add_argument("--sim-cores", type=int, help="cores for the sims (default 12; --smoke 1)")
    parser.add_argument("--chunks", type=int, help="timed chunk_step calls a round (default 8; --smoke 2)")
    parser.add_argument("--copy-to", type=Path, help="also copy the JSON here")
    args = parser.parse_args()
    setup_logging()
    args.k = 8
    args.render = None  # LIBERO's own pixels ("full"), as RLinf renders them
    if args.gpu or args.mjwarp:
        args.suite, args.task_ids, args.size = "libero_10", list(range(10)), 256
        defaults = {"rounds": 2, "envs": "24,1024" if args.mjwarp else "12,24", "sim_cores": 12, "chunks": 8}
    else:
        args.suite, args.task_ids, args.size = "libero_spatial", [0], 32
        defaults = {"rounds": 1, "envs": "2", "sim_cores": 1, "chunks": 2}
    for key, value in defaults.items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    if args.mjwarp:
        args.task_ids = task_ids(args.task_ids_text, args.suite)
        log.info("mjwarp: tasks %s of %s", args.task_ids, args.suite)
    gl = gl_probe()
    log.info("GL: %s", gl)
    if (args.gpu or args.mjwarp) and "NVIDIA" not in gl.get("renderer", "").upper():
        log.error("GL_RENDERER is %r, not NVIDIA's (set MUJOCO_GL=egl): not measuring", gl.get("renderer", gl))
        return 2
    pins, driver = split_cores(cores_first(cpu_topology()), args.sim_cores)
    os.sched_setaffinity(0, set(driver))
    workdir = Path(tempfile.mkdtemp(prefix="vecsim-bench-rlinf-"))
    sizes: list[dict[str, Any]] = []
    for n in str(args.envs).split(","):
        sizes.append(run_size(args, int(n), pins, driver, workdir))
        # Written after every slot count, so a run cut short still leaves a record.
        summary = summarise(args, sizes, pins, driver, gl)
        tag = "_smoke" if args.smoke else "_mjwarp" if args.mjwarp else ""
        path = write_result(f"bench_rlinf{tag}", summary, {"rounds": {s["slots"]: s["per_round"] for s in sizes}})
        if args.copy_to:
            args.copy_to.mkdir(parents=True, exist_ok=True)
            shutil.copy(path, args.copy_to)
    log.info("record: %s", json.dumps(summary["results"]))
    return 0


def summarise(
    args: argparse.Namespace, sizes: list[dict[str, Any]], pins: list[str], driver: list[int], gl: dict[str, Any]
) -> dict[str, Any]:
    summary: dict[str, Any] = {
        "what": "env-steps/s of chunk_step, RLinf's LiberoEnv vs vecsim's RLinf env, same tasks/ids/chunks",
        "baseline": "RLinf 0.3.0 LiberoEnv (subprocess vector env, renders every action), same round (paired)",
        "suite": args.suite,
        "camera": f"{len(CAMERAS)} x {args.size}x{args.size}",
        "k": args.k,
        "sim_cores": pins,
        "driver_cores": driver,
        "results": [{k: v for k, v in size.items() if k != "per_round"} for size in sizes],
        "gl": gl,
    }
    if not args.mjwarp:
        ratio = sizes[-1]["vecsim_over_rlinf"]["median"]
        return {"ratio": ratio, "target": TARGET, "met": bool(ratio >= TARGET), **summary}
    best = best_over_best(sizes) if any("rlinf" in s["env_steps_per_s"] for s in sizes) else None
    return {
        "ratio": best["ratio"] if best else None,
        "best_over_best": best,
        "engine": "mjwarp (one pod, one GPU; RLinf's env on the sim cores)",
        "tasks": [f"{args.suite}/{t}" for t in args.task_ids],
        "libero": PROTOCOL.model_dump(),
        **summary,
    }


def task_ids(text: str | None, suite: str) -> list[int]:
    """``--task-ids`` (comma-separated), else every task of ``suite`` the mjwarp engine serves.

    Raises:
        SystemExit: none served (the message says how to export them).
    """
    tasks = [int(t) for t in text.split(",")] if text else served_tasks(suite, LIBERO_SUITES[suite].num_tasks)
    if not tasks:
        raise SystemExit(
            f"--mjwarp: no scene of {suite} that the mjwarp engine serves under {PROTOCOL.model_dump()}; export them: "
            f"python -m vecsim.engine.mjwarp.scene {suite}/0 ... --libero '{PROTOCOL.model_dump_json()}'"
        )
    return tasks


if __name__ == "__main__":
    sys.exit(main())
