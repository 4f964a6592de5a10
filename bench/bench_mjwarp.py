"""The ``mjwarp`` engine on one GPU, against the CPU engine: rate, scaling, memory, fidelity.

Steps, each in the environment it needs:

``reference`` (the CPU stack: robosuite, LIBERO, mujoco 3.3) records what the CPU engine does
for one LIBERO task: for each of ``--states`` init states, the 8-float state and ``qpos`` after
every action of a fixed action sequence (a smooth pseudo-random walk, seeded), and the two
cameras' images after the reset and after actions ``IMAGE_MARKS``. With ``--cpu-envs`` it also
times the CPU engine itself (``TaskGroupedVectorEnv``, one worker per core, chunks of
``--chunk``, the same cameras)::

    python bench/bench_mjwarp.py reference --task libero_10/0 --out out/bench/mjwarp_reference.npz

``pod`` times one real pod (``vecsim pod`` on loopback) on either engine through ``/v1/step``,
the whole serving path included::

    python bench/bench_mjwarp.py pod --engine mjwarp --envs 1024 --size 256 --out out/bench/pod_mjwarp.json

``side`` measures the node's CPU pods and the ``mjwarp`` pods in one invocation, one layout
after the other on the same machine, and prints the ratio. Each layout is ``PODSxENVS``: CPU
pods pinned to an equal share of the cores (as the runner places them), ``mjwarp`` pods on the
one GPU (started one after the other, so later ones find the kernel cache warm). Every pod of a
layout is stepped by its own client thread, back to back; the pods' counters (``/metrics``) say
where the time goes. Each side runs with its own ``PYTHONPATH`` (the two stacks pin different
mujoco versions)::

    python bench/bench_mjwarp.py side --cpu-layouts 1x32 8x4 --mjwarp-layouts 1x1024 2x512 \\
        --cpu-pythonpath /tmp/site --mjwarp-pythonpath /tmp/site-mjw --out out/bench/side.json

``--rounds R`` runs the whole plan R times, each round's pods started afresh: a ratio per round
(``ratio_by_round``), and the record's ``ratio_best_mjwarp_to_best_cpu`` is the lowest of them.
``--cpu-calls`` times the CPU pods over more calls than the ``mjwarp`` ones (a CPU pod's call is
short).

``run`` (the ``mjwarp`` extra, a GPU) builds the ``mjwarp`` engine (``vecsim.engine.base.engine_kind``)
for each camera setting and worlds-per-task count, resets every env and times chunk steps of
``--chunk`` actions: env-steps/s, the physics and render seconds of each call, GPU memory per
world (``torch.cuda.mem_get_info`` before and after the build). With ``--reference``, it replays
the recorded action sequences from the same init states and reports the divergence over time
of the end effector and of every free object, and per camera the images' mean absolute
difference and SSIM; then it replays them again on the same worlds and reports whether the
outputs repeat bit for bit (``--deterministic`` adds the same with MuJoCo Warp's
``opt.deterministic`` on). A ratio to the CPU engine's rate is given when the reference holds
one measured on this machine (``--cpu-rate`` names a figure measured elsewhere only to print
it beside, never as a ratio)::

    python bench/bench_mjwarp.py run --task libero_10/0 --runs 256:256 256:1024 128:1024 0:1024 \\
        --reference out/bench/mjwarp_reference.npz --out out/bench/bench_mjwarp.json

The JSON record is written after every measurement, so a run cut short still leaves one.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np
from lib.images import ssim
from lib.jobs import one_task_assignment
from lib.records import write_record

from vecsim.config import CameraConfig

log = logging.getLogger("bench_mjwarp")

CAMERAS = ("agentview", "robot0_eye_in_hand")
# Actions after which the reference keeps both cameras' images (0: after the reset).
IMAGE_MARKS = (0, 1, 10, 40, 80)
# Actions at which divergence is reported.
MARKS = (0, 1, 5, 10, 20, 40, 80, 160)


def action_walk(num: int, steps: int, seed: int) -> np.ndarray:
    """``[num, steps, 7]`` smooth pseudo-random actions: arm deltas a slow random walk within
    +-0.5, the gripper opening then closing halfway through."""
    rng = np.random.default_rng(seed)
    arm = np.cumsum(rng.normal(0.0, 0.08, (num, steps, 6)), axis=1).clip(-0.5, 0.5)
    gripper = np.where(np.arange(steps) < steps // 2, -1.0, 1.0)[None, :, None].repeat(num, 0)
    return np.concatenate([arm, gripper], axis=2).astype(np.float32)


def time_chunks(engine: Any, envs: int, chunk: int, calls: int, deadline: float) -> dict[str, Any]:
    """Reset every env, then ``calls`` chunk steps of random actions; the rate and the split."""
    ids = np.arange(envs)
    engine.reset_envs(ids, ids % 50)
    rng = np.random.default_rng(0)
    steps = physics = render = 0.0
    started = time.perf_counter()
    done = 0
    for _ in range(calls):
        actions = rng.uniform(-0.3, 0.3, (envs, chunk, 7)).astype(np.float32)
        result = engine.chunk_step_envs(ids, actions, step_past_end=True)
        steps += int(result.num_steps.sum())
        physics += engine.last_timing.physics_s
        render += engine.last_timing.render_s
        done += 1
        if time.monotonic() > deadline:
            break
    elapsed = time.perf_counter() - started
    return {
        "calls": done,
        "env_steps": int(steps),
        "seconds": elapsed,
        "env_steps_per_s": steps / elapsed,
        "physics_s_per_call": physics / done,
        "render_s_per_call": render / done,
        "other_s_per_call": (elapsed - physics - render) / done,
    }


def reference(args: argparse.Namespace) -> None:
    """The CPU engine's trajectories, images and (with ``--cpu-envs``) rate (the CPU stack)."""
    from vecsim.engine.base import engine_kind
    from vecsim.engine.tasks import make_env

    actions = action_walk(args.states, args.steps, args.seed)
    marks = [t for t in IMAGE_MARKS if t <= args.steps]
    env = make_env(args.task, CameraConfig(names=CAMERAS, height=args.size, width=args.size))
    sim = env.inner.sim
    states = np.zeros((args.states, args.steps + 1, 8), dtype=np.float32)
    qpos = np.zeros((args.states, args.steps + 1, sim.model.nq), dtype=np.float64)
    images = {name: np.zeros((args.states, len(marks), args.size, args.size, 3), np.uint8) for name in CAMERAS}
    success = np.zeros((args.states, args.steps), dtype=bool)
    for k in range(args.states):
        obs, _ = env.reset(options={"state_id": k})
        for t in range(args.steps + 1):
            if t:
                obs, _, _, _, info = env.step(actions[k, t - 1])
                success[k, t - 1] = bool(info["success"])
            states[k, t] = obs["state"]
            qpos[k, t] = sim.data.qpos
            if t in marks:
                for name in CAMERAS:
                    images[name][k, marks.index(t)] = obs["images"][name]
    env.close()
    record: dict[str, Any] = {"task": args.task, "machine": args.machine, "cores": os.cpu_count()}
    if args.cpu_envs:
        engine = engine_kind("cpu").build(one_task_assignment(args.task, args.cpu_envs, args.cpu_size, "cpu"))
        try:
            record["cpu_engine"] = time_chunks(engine, args.cpu_envs, args.chunk, args.calls, time.monotonic() + 600)
        finally:
            engine.close()
        record["cpu_engine"].update(envs=args.cpu_envs, size=args.cpu_size, chunk=args.chunk)
    np.savez_compressed(
        args.out,
        actions=actions,
        states=states,
        qpos=qpos,
        success=success,
        image_marks=np.array(marks),
        record=json.dumps(record),
        **{f"image.{name}": pixels for name, pixels in images.items()},
    )
    print("RESULT", json.dumps(record))


def gpu_free() -> int | None:
    try:
        import torch

        return int(torch.cuda.mem_get_info()[0]) if torch.cuda.is_available() else None
    except ImportError:
        return None


def rotation_between(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """The angle (rad) of the rotation between two arrays of ``(w, x, y, z)`` unit quaternions,
    from the sine of its half angle (the cosine's ``arccos`` loses float32 inputs' precision)."""
    w1, v1, w2, v2 = first[..., :1], first[..., 1:], second[..., :1], second[..., 1:]
    # The vector part of conj(first) * second.
    vector = w1 * v2 - w2 * v1 - np.cross(v1, v2)
    return 2 * np.arctan2(np.linalg.norm(vector, axis=-1), np.abs((first * second).sum(-1)))


def spread(values: np.ndarray) -> dict[str, float]:
    return {"median": float(np.median(values)), "max": float(np.max(values))}


def replay(engine: Any, ref: Any) -> dict[str, np.ndarray]:
    """The reference's actions on ``engine`` from the same init states, one action a call: the
    8-float state and ``qpos`` after each, the images at the reference's marks, success."""
    actions = ref["actions"]
    n, steps = actions.shape[:2]
    marks = [int(t) for t in ref["image_marks"]]
    # The bench reads the worlds' joints, which no pod call answers.
    data = engine._batches[0].data
    ids = np.arange(n)
    out = {
        "state": np.zeros((n, steps + 1, 8), np.float32),
        "qpos": np.zeros((n, steps + 1, data.qpos.shape[1])),
        "success": np.zeros((n, steps), dtype=bool),
        "errors": [],
    }
    out.update(
        {f"image.{name}": np.zeros((n, len(marks), *ref[f"image.{name}"].shape[2:]), np.uint8) for name in CAMERAS}
    )
    obs, _ = engine.reset_envs(ids, ids)
    for t in range(steps + 1):
        if t:
            result = engine.chunk_step_envs(ids, actions[:, t - 1 : t], step_past_end=True)
            obs = result.obs
            out["success"][:, t - 1] = result.success[:, 0]
            out["errors"] += [e.message for e in result.errors]
        out["state"][:, t] = obs["state"]
        out["qpos"][:, t] = data.qpos.numpy()[:n]
        if t in marks:
            for name in CAMERAS:
                out[f"image.{name}"][:, marks.index(t)] = obs["images"][name]
    return out


def sameness(first: dict[str, Any], second: dict[str, Any]) -> dict[str, Any]:
    """How two replays of the same inputs differ: the largest difference of each output, the
    first action after which the state or joints differ (None: never), and how far apart the
    joints are after it."""
    largest = {
        key: float(np.abs(first[key].astype(np.float64) - second[key]).max()) for key in first if key != "errors"
    }
    steps = first["state"].shape[1]
    differs = [
        t
        for t in range(steps)
        if (first["state"][:, t] != second["state"][:, t]).any() or (first["qpos"][:, t] != second["qpos"][:, t]).any()
    ]
    t = differs[0] if differs else None
    return {
        "max_abs_diff": largest,
        "identical": all(v == 0.0 for v in largest.values()),
        "first_differing_action": t,
        "qpos_diff_there": None if t is None else float(np.abs(first["qpos"][:, t] - second["qpos"][:, t]).max()),
    }


def fidelity(args: argparse.Namespace, ref: Any, deterministic: bool = False) -> dict[str, Any]:
    """Replay the reference's actions on the mjwarp engine from the same init states: twice on
    one build (a reset between), once more on a second build."""
    from vecsim.engine.base import engine_kind

    n, steps = ref["actions"].shape[:2]
    size = int(ref[f"image.{CAMERAS[0]}"].shape[2])

    def build() -> Any:
        os.environ["VECSIM_MJWARP_DETERMINISTIC"] = "1" if deterministic else "0"
        try:
            return engine_kind("mjwarp").build(one_task_assignment(args.task, n, size, "mjwarp"))
        finally:
            del os.environ["VECSIM_MJWARP_DETERMINISTIC"]  # the mode is read at the build only

    started = time.monotonic()
    engine = build()
    built = time.monotonic() - started
    try:
        mjm = engine._batches[0].mjm
        have = replay(engine, ref)
        again = replay(engine, ref)
    finally:
        engine.close()
    engine = build()
    try:
        fresh = replay(engine, ref)
    finally:
        engine.close()
    marks = [t for t in MARKS if t <= steps]
    eef = np.linalg.norm(have["state"][..., :3] - ref["states"][..., :3], axis=-1)
    # Every free joint's body (the objects): position and rotation angle apart.
    free = [int(mjm.jnt_qposadr[j]) for j in range(mjm.njnt) if mjm.jnt_type[j] == 0]
    pos = np.stack(
        [np.linalg.norm(have["qpos"][..., a : a + 3] - ref["qpos"][..., a : a + 3], axis=-1) for a in free], -1
    )
    angle = np.stack(
        [rotation_between(have["qpos"][..., a + 3 : a + 7], ref["qpos"][..., a + 3 : a + 7]) for a in free], -1
    )
    images = {}
    for name in CAMERAS:
        want, got = ref[f"image.{name}"], have[f"image.{name}"]
        images[name] = {
            str(int(t)): {
                "mad": float(np.abs(got[:, i].astype(np.int16) - want[:, i]).mean()),
                "ssim": float(ssim(got[:, i], want[:, i]).mean()),
            }
            for i, t in enumerate(ref["image_marks"])
        }
    return {
        "states": n,
        "actions": steps,
        "image_size": size,
        "deterministic": deterministic,
        "build_s": built,
        "eef_pos_divergence_m": {str(t): spread(eef[:, t]) for t in marks},
        "objects": len(free),
        "object_pos_divergence_m": {str(t): spread(pos[:, t]) for t in marks},
        "object_angle_divergence_rad": {str(t): spread(angle[:, t]) for t in marks},
        "gripper_divergence_max": float(np.abs(have["state"][..., 6:] - ref["states"][..., 6:]).max()),
        "images": images,
        "success_agreement": float((have["success"] == ref["success"]).mean()),
        "success_reached": {"mjwarp": int(have["success"].any(1).sum()), "cpu": int(ref["success"].any(1).sum())},
        "repeat_after_reset": sameness(have, again),
        "repeat_on_new_build": sameness(have, fresh),
        "errors": have["errors"],
    }


def run(args: argparse.Namespace) -> None:
    """The mjwarp engine's rates, scaling and memory; fidelity against a reference."""
    from vecsim.engine.base import engine_kind

    deadline = time.monotonic() + args.budget_s
    record: dict[str, Any] = {
        "task": args.task,
        "chunk": args.chunk,
        "machine": args.machine,
        "runs": [],
        "complete": False,
    }
    ref = np.load(args.reference) if args.reference else None
    if ref is not None:
        record["cpu_reference"] = json.loads(str(ref["record"]))
    if args.cpu_rate:
        record["cpu_rate_elsewhere"] = args.cpu_rate
    write_record(record, args.out)
    for index, (size, worlds) in enumerate(args.runs):
        if time.monotonic() > deadline:
            record["cut_short"] = f"budget of {args.budget_s} s spent"
            write_record(record, args.out)
            return
        free = gpu_free()
        started = time.monotonic()
        engine = engine_kind("mjwarp").build(one_task_assignment(args.task, worlds, size, "mjwarp"))
        built = time.monotonic() - started
        used = None if free is None else free - (gpu_free() or 0)
        try:
            measured = time_chunks(engine, worlds, args.chunk, args.calls, deadline)
        finally:
            engine.close()
        entry = {
            "size": size,
            "worlds": worlds,
            "build_s": built,
            "gpu_bytes_per_world": None if used is None else used / worlds,
            **measured,
        }
        cpu = record.get("cpu_reference", {}).get("cpu_engine")
        if cpu and cpu["size"] == size and record["cpu_reference"]["machine"] == record["machine"]:
            entry["ratio_to_cpu_engine"] = measured["env_steps_per_s"] / cpu["env_steps_per_s"]
        record["runs"].append(entry)
        log.info(
            "size %s, %d worlds: %.0f env-steps/s (built in %.0f s)", size, worlds, measured["env_steps_per_s"], built
        )
        write_record(record, args.out)
        if index == 0 and ref is not None:
            # Right after the first run, while the budget lasts: its kernels are compiled.
            record["fidelity"] = fidelity(args, ref)
            write_record(record, args.out)
            if args.deterministic and time.monotonic() < deadline:
                record["fidelity_deterministic"] = fidelity(args, ref, deterministic=True)
                write_record(record, args.out)
    record["complete"] = True
    write_record(record, args.out)
    print("RESULT", json.dumps(record))


def run_spec(text: str) -> tuple[int, int]:
    size, _, worlds = text.partition(":")
    return int(size), int(worlds)


def gpu_memory_used_mib() -> int | None:
    """The GPU's used memory as ``nvidia-smi`` reads it (every process), or None without one."""
    import subprocess

    try:
        text = subprocess.run(
            ["nvidia-smi", "--query-gpu=memory.used", "--format=csv,noheader,nounits"],
            capture_output=True,
            text=True,
            timeout=30,
            check=True,
        ).stdout
    except (OSError, subprocess.SubprocessError):
        return None
    return int(text.split()[0])


def scrape(urls: list[str]) -> dict[str, float]:
    """The pods' step counters (``/metrics``), summed over ``urls``."""
    import re

    import httpx

    totals: dict[str, float] = dict.fromkeys(POD_COUNTERS, 0.0)
    for url in urls:
        for name, value in re.findall(
            r"^(vecsim_pod_[a-z_]+?)(?:\{[^}]*\})? (\S+)$", httpx.get(f"{url}/metrics", timeout=10).text, re.M
        ):
            if name in totals:
                totals[name] += float(value)
    return totals


POD_COUNTERS = (
    "vecsim_pod_step_seconds_sum",
    "vecsim_pod_physics_seconds_total",
    "vecsim_pod_render_seconds_total",
    "vecsim_pod_gpu_turn_wait_seconds_total",
)


def rounds_spec(text: str) -> int:
    """A number of rounds: a whole number, at least 1."""
    if not text.isdigit() or int(text) < 1:
        raise argparse.ArgumentTypeError(f"rounds must be a whole number of at least 1, got {text!r}")
    return int(text)


def layout_spec(text: str) -> tuple[int, int, int | None, bool]:
    """``PODSxENVS[@SIZE][/turns]``: SIZE the cameras' size for this layout (0: none); ``/turns``:
    the layout's ``mjwarp`` pods take turns at the GPU (``VECSIM_MJWARP_TURNS``, else off)."""
    text, slash, option = text.partition("/")
    if slash and option != "turns":
        raise argparse.ArgumentTypeError(f"{text}/{option}: the only option is /turns")
    layout, _, size = text.partition("@")
    pods, _, envs = layout.partition("x")
    return int(pods), int(envs), int(size) if size else None, bool(slash)


def drive(url: str, envs: int, chunk: int, calls: int, seed: int) -> dict[str, Any]:
    """Step every env of the pod at ``url`` ``calls`` times, back to back (in a process of its
    own, so that decoding one pod's answers does not wait on another's), through the trainer's
    transport (``vecsim.transport.make_transport``): env-steps, the span, and the seconds spent
    waiting for answers and decoding them."""
    import asyncio

    from vecsim import wire
    from vecsim.transport import make_transport

    headers = (("Content-Type", wire.CONTENT_TYPE), ("Accept", wire.CONTENT_TYPE))
    # Far above any answer here (1,024 worlds of two 256x256 cameras are 403 MB).
    cap = 1 << 32
    rng = np.random.default_rng(seed)
    ids = np.arange(envs)

    async def loop() -> dict[str, Any]:
        transport = make_transport()
        steps, waiting, decoding, size = 0, 0.0, 0.0, 0
        try:
            begun = time.perf_counter()
            for _ in range(calls):
                actions = rng.uniform(-0.3, 0.3, (envs, chunk, 7)).astype(np.float32)
                body = wire.encode({"generation": 0, "env_indices": ids, "actions": actions, "step_past_end": True})
                sent = time.perf_counter()
                async with asyncio.timeout(600):
                    status, answer = await transport.fetch("POST", f"{url}/v1/step", headers, body, cap)
                if status != 200:
                    raise RuntimeError(f"{url}/v1/step answered {status}: {bytes(answer[:300])!r}")
                received = time.perf_counter()
                steps += int(np.asarray(wire.decode(answer)["num_steps"]).sum())
                waiting += received - sent
                decoding += time.perf_counter() - received
                size = len(answer)
            ended = time.perf_counter()
        finally:
            await transport.aclose()
        return {"steps": steps, "begun": begun, "ended": ended, "waiting": waiting, "decoding": decoding, "bytes": size}

    return asyncio.run(loop())


def run_layout(
    args: argparse.Namespace,
    engine: str,
    pods: int,
    envs: int,
    size: int,
    pythonpath: str | None,
    port: int,
    turns: bool = False,
    calls: int | None = None,
) -> dict[str, Any]:
    """Start ``pods`` real pods (``vecsim pod``, uvicorn, loopback) of ``envs`` envs each on
    ``engine``; reset every env; step every pod ``--calls`` times with chunks of random actions
    through ``/v1/step`` (wire format), one client process a pod (:func:`drive`); stop them.
    CPU pods are pinned to equal shares of this process's cores; ``mjwarp`` pods start one
    after the other. ``calls`` (default ``--calls``) per pod."""
    import multiprocessing
    import subprocess
    import sys
    import tempfile
    from concurrent.futures import ProcessPoolExecutor

    import httpx

    from vecsim import wire

    calls = args.calls if calls is None else calls
    cores = sorted(os.sched_getaffinity(0))
    share = len(cores) // pods
    if engine == "cpu" and share < 1:
        raise ValueError(f"--cpu-layouts: {pods} pods on {len(cores)} cores")
    code = str(Path(__file__).resolve().parents[1])
    env = {**os.environ, "VECSIM_MAX_ENVS": str(envs), "VECSIM_BUILD_TIMEOUT_S": "900"}
    env["PYTHONPATH"] = ":".join(p for p in (code, pythonpath or env.get("PYTHONPATH")) if p)
    urls = [f"http://127.0.0.1:{port + i}" for i in range(pods)]
    headers = {"Content-Type": wire.CONTENT_TYPE, "Accept": wire.CONTENT_TYPE}
    record: dict[str, Any] = {
        "engine": engine,
        "pods": pods,
        "envs_per_pod": envs,
        "envs": pods * envs,
        "cores_per_pod": share if engine == "cpu" else len(cores),
        "size": size,
        "chunk": args.chunk,
        "turns": turns,
    }
    processes: list[subprocess.Popen] = []
    started = time.monotonic()

    def wait_ready(index: int) -> None:
        with httpx.Client(timeout=30) as client:
            while True:
                try:
                    if client.get(f"{urls[index]}/readyz").status_code == 200:
                        return
                except httpx.TransportError:
                    pass  # not listening yet
                if processes[index].poll() is not None or time.monotonic() - started > args.ready_timeout_s:
                    raise RuntimeError(f"{engine} pod {index} not ready after {time.monotonic() - started:.0f} s")
                time.sleep(1.0)

    try:
        with tempfile.TemporaryDirectory() as folder:
            env["VECSIM_MJWARP_TURNS"] = str(Path(folder) / "turns") if turns else "off"
            for i in range(pods):
                spec = one_task_assignment(args.task, envs, size, engine).model_copy(update={"pod": f"sim-{i}"})
                path = Path(folder) / f"pod{i}.json"
                path.write_text(spec.model_dump_json())
                pinned = set(cores[i * share : (i + 1) * share]) if engine == "cpu" else None
                command = [
                    sys.executable,
                    "-m",
                    "service.cli",
                    "pod",
                    "--assignment",
                    str(path),
                    "--name",
                    spec.pod,
                    "--port",
                    str(port + i),
                ]
                processes.append(
                    subprocess.Popen(
                        command,
                        env=env,
                        cwd=code,
                        preexec_fn=(lambda c=pinned: os.sched_setaffinity(0, c)) if pinned else None,
                    )
                )
                if engine == "mjwarp":
                    wait_ready(i)  # the next pod finds the kernel cache warm
            for i in range(pods):
                wait_ready(i)
        record["ready_s"] = time.monotonic() - started
        record["gpu_memory_used_mib"] = gpu_memory_used_mib()
        ids = np.arange(envs)
        with httpx.Client(timeout=600) as client:
            for i, url in enumerate(urls):
                body = wire.encode({"generation": 0, "env_indices": ids, "state_ids": (ids + i * envs) % 50})
                client.post(f"{url}/v1/reset", content=body, headers=headers).raise_for_status()
        before = scrape(urls)
        with ProcessPoolExecutor(pods, mp_context=multiprocessing.get_context("fork")) as pool:
            driven = list(pool.map(drive, urls, [envs] * pods, [args.chunk] * pods, [calls] * pods, range(pods)))
        after = scrape(urls)
        elapsed = max(d["ended"] for d in driven) - min(d["begun"] for d in driven)
        steps = sum(d["steps"] for d in driven)
        total = pods * calls
        counters = {name.removeprefix("vecsim_pod_"): after[name] - before[name] for name in after}
        record.update(
            calls_per_pod=calls,
            env_steps=steps,
            seconds=elapsed,
            env_steps_per_s=steps / elapsed,
            answer_bytes=driven[0]["bytes"],
            # Per call: the client's wall time, its wait for the answer and its decoding; the pod's
            # engine call, its physics and render (summed over a CPU pod's workers) and its wait
            # for the GPU's turn.
            per_call_s={
                "client": sum(d["ended"] - d["begun"] for d in driven) / total,
                "client_waiting": sum(d["waiting"] for d in driven) / total,
                "client_decoding": sum(d["decoding"] for d in driven) / total,
                "engine": counters["step_seconds_sum"] / total,
                "physics": counters["physics_seconds_total"] / total,
                "render": counters["render_seconds_total"] / total,
                "turn_wait": counters["gpu_turn_wait_seconds_total"] / total,
            },
        )
    finally:
        for process in processes:
            process.terminate()
        for process in processes:
            try:
                process.wait(timeout=60)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait(timeout=30)
    log.info("%s %dx%d at %d: %.0f env-steps/s", engine, pods, envs, size, record["env_steps_per_s"])
    return record


def round_ratio(layouts: list[dict[str, Any]], round_index: int, size: int) -> float | None:
    """The best ``mjwarp`` layout's env-steps/s over the best ``cpu`` layout's, among the layouts
    of one round measured at the issue's camera ``size`` (None unless both engines have one)."""
    best: dict[str, float] = {}
    for entry in layouts:
        if entry.get("round") == round_index and "env_steps_per_s" in entry and entry["size"] == size:
            best[entry["engine"]] = max(best.get(entry["engine"], 0.0), entry["env_steps_per_s"])
    return best["mjwarp"] / best["cpu"] if len(best) == 2 else None


def side(args: argparse.Namespace) -> None:
    """The node's CPU pods and the mjwarp pods, one layout after the other, in one invocation;
    with ``--rounds`` the whole plan again, so that each round's ratio compares rates measured
    minutes apart, and the record's ratio is the lowest round's."""
    import httpx

    deadline = time.monotonic() + args.budget_s
    record: dict[str, Any] = {
        "task": args.task,
        "size": args.size,
        "chunk": args.chunk,
        "machine": args.machine,
        "cores": len(os.sched_getaffinity(0)),
        "layouts": [],
        "complete": False,
    }
    write_record(record, args.out)
    plan = [("cpu", *layout, args.cpu_pythonpath) for layout in args.cpu_layouts]
    plan += [("mjwarp", *layout, args.mjwarp_pythonpath) for layout in args.mjwarp_layouts]
    record["rounds"] = args.rounds
    record["ratio_by_round"] = []
    for round_index in range(args.rounds):
        for index, (engine, pods, envs, size, turns, pythonpath) in enumerate(plan):
            size = args.size if size is None else size
            if time.monotonic() > deadline:
                record["cut_short"] = (
                    f"budget of {args.budget_s} s spent before {engine} {pods}x{envs}@{size}, round {round_index}"
                )
                break
            try:
                port = args.port + 32 * index
                calls = args.cpu_calls if engine == "cpu" and args.cpu_calls else args.calls
                entry = run_layout(args, engine, pods, envs, size, pythonpath, port, turns, calls)
            except (RuntimeError, OSError, ValueError, httpx.HTTPError) as exc:
                entry = {"engine": engine, "pods": pods, "envs_per_pod": envs, "size": size, "error": str(exc)}
                log.error("%s %dx%d@%d failed: %s", engine, pods, envs, size, exc)
            record["layouts"].append({**entry, "round": round_index})
            write_record(record, args.out)
        else:
            ratio = round_ratio(record["layouts"], round_index, args.size)
            if ratio is not None:
                record["ratio_by_round"].append(ratio)
                # The lowest round's: a claim that holds in every round.
                record["ratio_best_mjwarp_to_best_cpu"] = min(record["ratio_by_round"])
                log.info("round %d: best mjwarp / best cpu = %.2fx", round_index, ratio)
            continue
        break
    else:
        record["complete"] = True
    write_record(record, args.out)
    print("RESULT", json.dumps(record))


def through_pod(args: argparse.Namespace) -> None:
    """One real pod on ``--engine`` (a layout of one, see :func:`run_layout`)."""
    record = {"machine": args.machine, **run_layout(args, args.engine, 1, args.envs, args.size, None, args.port)}
    write_record(record, args.out)
    print("RESULT", json.dumps(record))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    ref = sub.add_parser("reference", help="the CPU engine's trajectories, images and rate")
    ref.add_argument("--task", default="libero_10/0")
    ref.add_argument("--states", type=int, default=8)
    ref.add_argument("--steps", type=int, default=80)
    ref.add_argument("--size", type=int, default=128)
    ref.add_argument("--seed", type=int, default=0)
    ref.add_argument("--chunk", type=int, default=8)
    ref.add_argument("--calls", type=int, default=10)
    ref.add_argument("--cpu-envs", type=int, default=0, help="time the CPU engine with this many envs (0: skip)")
    ref.add_argument("--cpu-size", type=int, default=256, help="the cameras' size when timing the CPU engine")
    ref.add_argument("--out", type=Path, default=Path("out/bench/mjwarp_reference.npz"))
    go = sub.add_parser("run", help="the mjwarp engine's rates, scaling, memory and fidelity")
    go.add_argument("--task", default="libero_10/0")
    go.add_argument(
        "--runs",
        type=run_spec,
        nargs="+",
        default=[run_spec(s) for s in ("256:256", "256:1024", "128:1024", "0:1024")],
        help="SIZE:WORLDS per measurement, in order (size 0: no camera); the fidelity replay follows the first",
    )
    go.add_argument("--chunk", type=int, default=8)
    go.add_argument("--calls", type=int, default=10)
    go.add_argument("--budget-s", type=float, default=480.0)
    go.add_argument("--reference", type=Path, default=None)
    go.add_argument("--deterministic", action="store_true", help="replay the reference again with opt.deterministic on")
    go.add_argument(
        "--cpu-rate", type=float, default=None, help="a CPU-pod rate measured elsewhere, printed beside only"
    )
    go.add_argument("--out", type=Path, default=Path("out/bench/bench_mjwarp.json"))
    pod = sub.add_parser("pod", help="one real pod on an engine, timed through HTTP")
    pod.add_argument("--engine", choices=["cpu", "mjwarp"], required=True)
    pod.add_argument("--task", default="libero_10/0")
    pod.add_argument("--envs", type=int, default=1024)
    pod.add_argument("--size", type=int, default=256)
    pod.add_argument("--chunk", type=int, default=8)
    pod.add_argument("--calls", type=int, default=10)
    pod.add_argument("--port", type=int, default=8100)
    pod.add_argument("--ready-timeout-s", type=float, default=500.0)
    pod.add_argument("--out", type=Path, default=Path("out/bench/bench_mjwarp_pod.json"))
    both = sub.add_parser("side", help="the node's CPU pods and the mjwarp pods in one invocation, with the ratio")
    both.add_argument("--task", default="libero_10/0")
    both.add_argument("--size", type=int, default=256)
    both.add_argument("--chunk", type=int, default=8)
    both.add_argument("--calls", type=int, default=10)
    both.add_argument(
        "--cpu-calls",
        type=int,
        default=None,
        help="calls per CPU pod (default --calls): a CPU pod's call is short, so its rate needs more",
    )
    both.add_argument(
        "--cpu-layouts",
        type=layout_spec,
        nargs="*",
        default=[layout_spec("1x32")],
        help="PODSxENVS[@SIZE], in order (SIZE: the cameras' size if not --size; 0: none)",
    )
    both.add_argument(
        "--mjwarp-layouts",
        type=layout_spec,
        nargs="*",
        default=[layout_spec("1x1024")],
        help="PODSxENVS[@SIZE][/turns], in order (/turns: the pods take turns at the GPU)",
    )
    both.add_argument("--cpu-pythonpath", default=None, help="the CPU stack's PYTHONPATH (default: this process's)")
    both.add_argument(
        "--mjwarp-pythonpath", default=None, help="the mjwarp stack's PYTHONPATH (default: this process's)"
    )
    both.add_argument(
        "--rounds", type=rounds_spec, default=1, help="run the whole plan this many times, a ratio for each round"
    )
    both.add_argument("--port", type=int, default=8100)
    both.add_argument("--ready-timeout-s", type=float, default=500.0)
    both.add_argument("--budget-s", type=float, default=540.0)
    both.add_argument("--out", type=Path, default=Path("out/bench/bench_mjwarp_side.json"))
    for command in (ref, go, pod, both):
        command.add_argument(
            "--machine",
            default=platform.node(),
            help="names the machine; a ratio to the CPU engine is given only when both steps name the same one",
        )
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    logging.getLogger("httpx").setLevel(logging.WARNING)
    {"reference": reference, "run": run, "pod": through_pod, "side": side}[args.command](args)


if __name__ == "__main__":
    main()
