"""The ``mjwarp`` engine on one GPU, against the CPU engine: rate, scaling, memory, fidelity.

Two steps, on two machines:

``reference`` (the CPU stack: robosuite, LIBERO, mujoco 3.3) records what the CPU engine does
for one LIBERO task: for each of ``--states`` init states, the 8-float state after every action
of a fixed action sequence (a smooth pseudo-random walk, seeded), and the two cameras' images
after the reset. It also times the CPU engine itself (``TaskGroupedVectorEnv``, one worker per
core, chunks of ``--chunk``, the same cameras), the baseline of the ratio::

    python bench/bench_mjwarp.py reference --task libero_10/0 --out out/bench/mjwarp_reference.npz

``pod`` times one real pod (``vecsim pod`` on loopback) on either engine through ``/v1/step``,
the whole serving path included::

    python bench/bench_mjwarp.py pod --engine mjwarp --envs 1024 --size 256 --out out/bench/pod_mjwarp.json

``run`` (the ``mjwarp`` extra, a GPU) builds the ``mjwarp`` engine (``vecsim.engine.base.engine_kind``)
for each camera setting and worlds-per-task count, resets every env and times chunk steps of
``--chunk`` actions: env-steps/s, the physics and render seconds of each call, GPU memory per
world (``torch.cuda.mem_get_info`` before and after the build). With ``--reference``, it replays
the recorded action sequences from the same init states and reports the divergence of the
8-float state over time and the images' mean absolute difference per camera; and a ratio to
the CPU engine's rate when the reference holds one measured on this machine (``--cpu-rate``
names a figure measured elsewhere only to print it beside, never as a ratio)::

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

from vecsim.config import Assignment, CameraConfig, TaskBlock

log = logging.getLogger("bench_mjwarp")

CAMERAS = ("agentview", "robot0_eye_in_hand")


def action_walk(num: int, steps: int, seed: int) -> np.ndarray:
    """``[num, steps, 7]`` smooth pseudo-random actions: arm deltas a slow random walk within
    +-0.5, the gripper opening then closing halfway through."""
    rng = np.random.default_rng(seed)
    arm = np.cumsum(rng.normal(0.0, 0.08, (num, steps, 6)), axis=1).clip(-0.5, 0.5)
    gripper = np.where(np.arange(steps) < steps // 2, -1.0, 1.0)[None, :, None].repeat(num, 0)
    return np.concatenate([arm, gripper], axis=2).astype(np.float32)


def assignment(task: str, envs: int, size: int, engine: str) -> Assignment:
    camera = CameraConfig(names=CAMERAS if size else (), height=size or 128, width=size or 128)
    return Assignment(
        generation=0, pod="sim-0", stage_id=0, engine=engine, camera=camera,
        tasks=(TaskBlock(task_id=task, env_start=0, num_envs=envs),),
    )


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
        "calls": done, "env_steps": int(steps), "seconds": elapsed, "env_steps_per_s": steps / elapsed,
        "physics_s_per_call": physics / done, "render_s_per_call": render / done,
        "other_s_per_call": (elapsed - physics - render) / done,
    }


def write(record: dict[str, Any], out: Path) -> None:
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(record, indent=1))


def reference(args: argparse.Namespace) -> None:
    """The CPU engine's trajectories, images and rate (the CPU stack)."""
    from vecsim.engine.base import engine_kind
    from vecsim.engine.tasks import make_env

    actions = action_walk(args.states, args.steps, args.seed)
    env = make_env(args.task, CameraConfig(names=CAMERAS, height=args.size, width=args.size))
    states = np.zeros((args.states, args.steps + 1, 8), dtype=np.float32)
    images = {name: np.zeros((args.states, args.size, args.size, 3), np.uint8) for name in CAMERAS}
    success = np.zeros((args.states, args.steps), dtype=bool)
    for k in range(args.states):
        obs, _ = env.reset(options={"state_id": k})
        states[k, 0] = obs["state"]
        for name in CAMERAS:
            images[name][k] = obs["images"][name]
        for t in range(args.steps):
            obs, _, _, _, info = env.step(actions[k, t])
            states[k, t + 1] = obs["state"]
            success[k, t] = bool(info["success"])
    env.close()
    record: dict[str, Any] = {"task": args.task, "machine": args.machine, "cores": os.cpu_count()}
    if args.cpu_envs:
        engine = engine_kind("cpu").build(assignment(args.task, args.cpu_envs, args.cpu_size, "cpu"))
        try:
            record["cpu_engine"] = time_chunks(engine, args.cpu_envs, args.chunk, args.calls, time.monotonic() + 600)
        finally:
            engine.close()
        record["cpu_engine"].update(envs=args.cpu_envs, size=args.cpu_size, chunk=args.chunk)
    np.savez_compressed(
        args.out, actions=actions, states=states, success=success, record=json.dumps(record),
        **{f"image.{name}": pixels for name, pixels in images.items()},
    )
    print("RESULT", json.dumps(record))


def gpu_free() -> int | None:
    try:
        import torch

        return int(torch.cuda.mem_get_info()[0]) if torch.cuda.is_available() else None
    except ImportError:
        return None


def fidelity(args: argparse.Namespace, ref: Any) -> dict[str, Any]:
    """Replay the reference's actions on the mjwarp engine from the same init states."""
    from vecsim.engine.base import engine_kind

    actions, want = ref["actions"], ref["states"]
    n, steps = actions.shape[:2]
    size = int(ref[f"image.{CAMERAS[0]}"].shape[1])
    engine = engine_kind("mjwarp").build(assignment(args.task, n, size, "mjwarp"))
    try:
        ids = np.arange(n)
        obs, _ = engine.reset_envs(ids, ids)
        mad = {name: float(np.abs(obs["images"][name].astype(np.int16) - ref[f"image.{name}"]).mean()) for name in CAMERAS}
        # The same with the image flipped each way: a layout mismatch shows as a large MAD that
        # one flip brings down.
        flips = {"rows": (slice(None), slice(None, None, -1)), "columns": (slice(None), slice(None), slice(None, None, -1))}
        mad_flipped = {
            f"{name}/{flip}": float(np.abs(obs["images"][name][index].astype(np.int16) - ref[f"image.{name}"]).mean())
            for name in CAMERAS for flip, index in flips.items()
        }
        have = np.zeros_like(want)
        have[:, 0] = obs["state"]
        won = np.zeros((n, steps), dtype=bool)
        for t in range(steps):
            result = engine.chunk_step_envs(ids, actions[:, t : t + 1], step_past_end=True)
            have[:, t + 1] = result.obs["state"]
            won[:, t] = result.success[:, 0]
        errors = [e.message for e in result.errors]
    finally:
        engine.close()
    eef = np.linalg.norm(have[..., :3] - want[..., :3], axis=-1)
    marks = [t for t in (0, 1, 5, 10, 20, 40, 80, 160) if t <= steps]
    return {
        "states": n, "actions": steps, "image_size": size, "image_mad": mad, "image_mad_flipped": mad_flipped,
        "eef_pos_divergence_m": {str(t): {"median": float(np.median(eef[:, t])), "max": float(eef[:, t].max())} for t in marks},
        "gripper_divergence_max": float(np.abs(have[..., 6:] - want[..., 6:]).max()),
        "success_agreement": float((won == ref["success"]).mean()), "errors": errors,
    }


def run(args: argparse.Namespace) -> None:
    """The mjwarp engine's rates, scaling and memory; fidelity against a reference."""
    from vecsim.engine.base import engine_kind

    deadline = time.monotonic() + args.budget_s
    record: dict[str, Any] = {"task": args.task, "chunk": args.chunk, "machine": args.machine, "runs": [], "complete": False}
    ref = np.load(args.reference) if args.reference else None
    if ref is not None:
        record["cpu_reference"] = json.loads(str(ref["record"]))
    if args.cpu_rate:
        record["cpu_rate_elsewhere"] = args.cpu_rate
    write(record, args.out)
    for index, (size, worlds) in enumerate(args.runs):
        if time.monotonic() > deadline:
            record["cut_short"] = f"budget of {args.budget_s} s spent"
            write(record, args.out)
            return
        free = gpu_free()
        started = time.monotonic()
        engine = engine_kind("mjwarp").build(assignment(args.task, worlds, size, "mjwarp"))
        built = time.monotonic() - started
        used = None if free is None else free - (gpu_free() or 0)
        try:
            measured = time_chunks(engine, worlds, args.chunk, args.calls, deadline)
        finally:
            engine.close()
        entry = {"size": size, "worlds": worlds, "build_s": built, "gpu_bytes_per_world": None if used is None else used / worlds, **measured}
        cpu = record.get("cpu_reference", {}).get("cpu_engine")
        if cpu and cpu["size"] == size and record["cpu_reference"]["machine"] == record["machine"]:
            entry["ratio_to_cpu_engine"] = measured["env_steps_per_s"] / cpu["env_steps_per_s"]
        record["runs"].append(entry)
        log.info("size %s, %d worlds: %.0f env-steps/s (built in %.0f s)", size, worlds, measured["env_steps_per_s"], built)
        write(record, args.out)
        if index == 0 and ref is not None:
            # Right after the first run, while the budget lasts: its kernels are compiled.
            record["fidelity"] = fidelity(args, ref)
            write(record, args.out)
    record["complete"] = True
    write(record, args.out)
    print("RESULT", json.dumps(record))


def run_spec(text: str) -> tuple[int, int]:
    size, _, worlds = text.partition(":")
    return int(size), int(worlds)


def through_pod(args: argparse.Namespace) -> None:
    """One real pod (``vecsim pod``, uvicorn, HTTP on loopback) on ``--engine``: reset every env,
    then time ``--calls`` chunk steps of random actions through ``/v1/step`` (wire format)."""
    import subprocess
    import sys
    import tempfile

    import httpx

    from vecsim import wire

    spec = assignment(args.task, args.envs, args.size, args.engine)
    record: dict[str, Any] = {"engine": args.engine, "envs": args.envs, "size": args.size, "chunk": args.chunk, "machine": args.machine}
    url = f"http://127.0.0.1:{args.port}"
    headers = {"Content-Type": wire.CONTENT_TYPE, "Accept": wire.CONTENT_TYPE}
    with tempfile.NamedTemporaryFile("w", suffix=".json", delete=False) as handle:
        handle.write(spec.model_dump_json())
    env = {**os.environ, "VECSIM_MAX_ENVS": str(args.envs), "VECSIM_BUILD_TIMEOUT_S": "900"}
    command = [sys.executable, "-m", "service.cli", "pod", "--assignment", handle.name, "--port", str(args.port)]
    pod = subprocess.Popen(command, env=env)
    try:
        started = time.monotonic()
        with httpx.Client(timeout=300) as client:
            while True:
                try:
                    if client.get(f"{url}/readyz").status_code == 200:
                        break
                except httpx.TransportError:
                    pass  # not listening yet
                if pod.poll() is not None or time.monotonic() - started > args.ready_timeout_s:
                    raise RuntimeError(f"pod not ready after {time.monotonic() - started:.0f} s")
                time.sleep(1.0)
            record["ready_s"] = time.monotonic() - started
            ids = np.arange(args.envs)

            def call(op: str, body: dict[str, Any]) -> dict[str, Any]:
                answer = client.post(f"{url}/v1/{op}", content=wire.encode(body), headers=headers)
                answer.raise_for_status()
                return wire.decode(answer.content)

            call("reset", {"generation": 0, "env_indices": ids, "state_ids": ids % 50})
            rng = np.random.default_rng(0)
            steps, begun = 0, time.perf_counter()
            for _ in range(args.calls):
                actions = rng.uniform(-0.3, 0.3, (args.envs, args.chunk, 7)).astype(np.float32)
                answer = call("step", {"generation": 0, "env_indices": ids, "actions": actions, "step_past_end": True})
                steps += int(np.asarray(answer["num_steps"]).sum())
            elapsed = time.perf_counter() - begun
        record.update(calls=args.calls, env_steps=steps, seconds=elapsed, env_steps_per_s=steps / elapsed)
    finally:
        pod.terminate()
        pod.wait(timeout=60)
    write(record, args.out)
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
        "--runs", type=run_spec, nargs="+", default=[run_spec(s) for s in ("256:256", "256:1024", "128:1024", "0:1024")],
        help="SIZE:WORLDS per measurement, in order (size 0: no camera); the fidelity replay follows the first",
    )
    go.add_argument("--chunk", type=int, default=8)
    go.add_argument("--calls", type=int, default=10)
    go.add_argument("--budget-s", type=float, default=480.0)
    go.add_argument("--reference", type=Path, default=None)
    go.add_argument("--cpu-rate", type=float, default=None, help="a CPU-pod rate measured elsewhere, printed beside only")
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
    for command in (ref, go, pod):
        command.add_argument(
            "--machine", default=platform.node(),
            help="names the machine; a ratio to the CPU engine is given only when both steps name the same one",
        )
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    logging.getLogger("httpx").setLevel(logging.WARNING)
    {"reference": reference, "run": run, "pod": through_pod}[args.command](args)


if __name__ == "__main__":
    main()
