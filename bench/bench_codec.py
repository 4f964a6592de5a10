"""Codec benchmark: encode + decode of one realistic step answer, against memcpy and two peers.

The payload is what a pod answers to ``/v1/step`` for 16 envs with two 128x128 cameras: about
1.5 MiB of uint8 images, proprio float32[16, 39], rewards, flags, env ids, task ids. Each codec
does a full round trip (bytes out, arrays back); the baseline is one ``memcpy`` of the same
array bytes into a new ``bytes`` object, the least any codec that produces one buffer must do.
Peers: msgpack-numpy and pickle (protocol 5), pickle only here as a local yardstick: it never
touches the wire. Times are the thread's CPU time (page faults included), and rounds interleave
the codecs, so that other processes on the machine disturb the comparison as little as possible.

    python bench/bench_codec.py [--rounds 15] [--number 40]

Prints ``RESULT {json}`` and writes out/bench/bench_codec.json.
"""

from __future__ import annotations

import argparse
import pickle
import time
from collections.abc import Callable
from typing import Any

import msgpack
import msgpack_numpy
import numpy as np
from lib.records import spread, write_result

from vecsim import wire

NUM_ENVS = 16
CAMERAS = ("agentview", "robot0_eye_in_hand")
IMAGE_SHAPE = (128, 128, 3)
PROPRIO = 39


def step_payload() -> dict[str, Any]:
    """Return one step answer as a pod sends it (random pixels: nothing compresses)."""
    rng = np.random.default_rng(0)
    return {
        "env_indices": np.arange(NUM_ENVS, dtype=np.int32),
        "obs": {
            "images": {name: rng.integers(0, 256, (NUM_ENVS, *IMAGE_SHAPE), dtype=np.uint8) for name in CAMERAS},
            "proprio": rng.standard_normal((NUM_ENVS, PROPRIO)).astype(np.float32),
        },
        "reward": rng.random(NUM_ENVS, dtype=np.float32),
        "terminated": np.zeros(NUM_ENVS, bool),
        "truncated": np.zeros(NUM_ENVS, bool),
        "info": {"success": np.zeros(NUM_ENVS, bool), "task_id": [f"libero_10/{i % 10}" for i in range(NUM_ENVS)]},
    }


def array_bytes(obj: Any) -> int:
    if isinstance(obj, dict):
        return sum(array_bytes(v) for v in obj.values())
    return obj.nbytes if isinstance(obj, np.ndarray) else 0


def round_trips(payload: dict[str, Any]) -> dict[str, Callable[[], Any]]:
    """One callable per contender, each doing a whole encode + decode (or the copy)."""
    flat = np.concatenate([a.reshape(-1).view(np.uint8) for a in _arrays(payload)])

    def memcpy() -> bytes:
        return bytes(flat)

    def vecsim_wire() -> Any:
        return wire.decode(wire.encode(payload))

    def msgpack_numpy_trip() -> Any:
        packed = msgpack.packb(payload, default=msgpack_numpy.encode)
        return msgpack.unpackb(packed, object_hook=msgpack_numpy.decode, raw=False)

    def pickle_trip() -> Any:
        return pickle.loads(pickle.dumps(payload, protocol=5))

    return {"memcpy": memcpy, "vecsim.wire": vecsim_wire, "msgpack-numpy": msgpack_numpy_trip, "pickle": pickle_trip}


def _arrays(obj: Any) -> list[np.ndarray]:
    if isinstance(obj, dict):
        return [a for v in obj.values() for a in _arrays(v)]
    return [obj] if isinstance(obj, np.ndarray) else []


def check_round_trips(payload: dict[str, Any], contenders: dict[str, Callable[[], Any]]) -> None:
    """Fail loudly if a codec does not give the payload back (a fast wrong codec is no result)."""
    for name, trip in contenders.items():
        if name == "memcpy":
            continue
        back = trip()
        for key in ("agentview", "robot0_eye_in_hand"):
            if not np.array_equal(back["obs"]["images"][key], payload["obs"]["images"][key]):
                raise SystemExit(f"{name}: obs/images/{key} did not survive the round trip")
        if not np.array_equal(back["obs"]["proprio"], payload["obs"]["proprio"]):
            raise SystemExit(f"{name}: obs/proprio did not survive the round trip")


def time_per_call(fn: Callable[[], Any], number: int) -> float:
    # CPU time of this thread, not wall time: the codecs are single-threaded and CPU-bound, and
    # on a shared machine wall time mostly measures who else got the core.
    start = time.thread_time()
    for _ in range(number):
        fn()
    return (time.thread_time() - start) / number


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=15, help="interleaved rounds (default 15)")
    parser.add_argument("--number", type=int, default=40, help="round trips per contender per round (default 40)")
    args = parser.parse_args()

    payload = step_payload()
    nbytes = array_bytes(payload)
    contenders = round_trips(payload)
    check_round_trips(payload, contenders)

    times: dict[str, list[float]] = {name: [] for name in contenders}
    names = list(contenders)
    for r in range(args.rounds):
        # Rotate the order each round so that no contender always runs first after a pause.
        for name in names[r % len(names) :] + names[: r % len(names)]:
            times[name].append(time_per_call(contenders[name], args.number))

    # Also the two halves of the wire codec alone, for the record.
    encoded = wire.encode(payload)
    times_encode = [time_per_call(lambda: wire.encode(payload), args.number) for _ in range(args.rounds)]
    times_decode = [time_per_call(lambda: wire.decode(encoded), args.number) for _ in range(args.rounds)]

    median = {name: spread(values)["median"] for name, values in times.items()}
    # Ratios are taken within each round (contenders ran back to back) and then the median over
    # rounds, so that load from other processes, which drifts between rounds, cancels out.
    per_round_ratio = {name: [m / t for m, t in zip(times["memcpy"], values)] for name, values in times.items()}
    per_round_speedup = {
        peer: [p / w for p, w in zip(times[peer], times["vecsim.wire"])] for peer in ("msgpack-numpy", "pickle")
    }
    summary = {
        "payload": {
            "num_envs": NUM_ENVS,
            "cameras": list(CAMERAS),
            "image_shape": list(IMAGE_SHAPE),
            "proprio": PROPRIO,
            "array_bytes": nbytes,
            "wire_bytes": len(encoded),
        },
        "round_trip_us": {name: round(t * 1e6, 1) for name, t in median.items()},
        "round_trip_GBps": {name: round(nbytes / t / 1e9, 3) for name, t in median.items()},
        "wire_encode_us": round(spread(times_encode)["median"] * 1e6, 1),
        "wire_decode_us": round(spread(times_decode)["median"] * 1e6, 1),
        # Speed relative to memcpy: 1.0 would be a codec as fast as one copy of the data.
        "ratio_vs_memcpy": {name: round(spread(r)["median"], 3) for name, r in per_round_ratio.items()},
        "wire_speedup_vs": {peer: round(spread(r)["median"], 2) for peer, r in per_round_speedup.items()},
        "target": "vecsim.wire >= 0.5x memcpy and faster than msgpack-numpy and pickle",
    }
    summary["target_met"] = (
        summary["ratio_vs_memcpy"]["vecsim.wire"] >= 0.5 and min(summary["wire_speedup_vs"].values()) > 1.0
    )
    details = {
        "rounds": args.rounds,
        "number": args.number,
        "seconds_per_round_trip": {name: spread(values) for name, values in times.items()},
        "ratio_vs_memcpy_per_round": {name: spread(r) for name, r in per_round_ratio.items()},
        "wire_speedup_per_round": {peer: spread(r) for peer, r in per_round_speedup.items()},
        "wire_encode_s": spread(times_encode),
        "wire_decode_s": spread(times_decode),
    }
    write_result("bench_codec", summary, details)


if __name__ == "__main__":
    main()
