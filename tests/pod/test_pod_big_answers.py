"""A pod's answers larger than one slice (``service.pod.bodies.SLICE_BYTES``): sent from their
parts in slices, never joined. A real `vecsim pod` on loopback (gymnasium HalfCheetah, 4 envs, one
384x384 camera: a step of 3 envs answers 1.3 MB), read by the trainer's transport and by httpx.
"""

from __future__ import annotations

import asyncio
import io
import json
import socket
import uuid
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from PIL import Image
from support.service_procs import PodSpec, RunningPod, running

from service.pod.bodies import SLICE_BYTES, slices
from vecsim import wire
from vecsim.config import CameraConfig
from vecsim.transport import make_transport
from vecsim.transport.httptools_impl import IDEMPOTENCY_KEY

CAMERA = CameraConfig(names=("render",), height=384, width=384)
NUM_ENVS = 4
ACTION_DIM = 6
WIRE = {"Content-Type": wire.CONTENT_TYPE, "Accept": wire.CONTENT_TYPE}
MAX_ANSWER = 64 << 20


@pytest.fixture(scope="module")
def pod(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RunningPod]:
    spec = PodSpec("sim-big", 0, [("gym/HalfCheetah-v5", NUM_ENVS)], camera=CAMERA, envs_per_worker=NUM_ENVS)
    with running(RunningPod(spec, tmp_path_factory.mktemp("big_answers")), ready=True) as server:
        yield server


def fetch(pod: RunningPod, op: str, body: dict[str, Any], headers: dict[str, str] = WIRE) -> bytes:
    """POST ``body`` (wire) to ``op`` through the trainer's transport; the answer's bytes (200)."""

    async def go() -> tuple[int, bytes]:
        async with make_transport() as transport:
            return await transport.fetch(
                "POST", f"{pod.url}/v1/{op}", tuple(headers.items()), wire.encode(body), MAX_ANSWER
            )

    status, content = asyncio.run(go())
    assert status == 200, content[:300]
    return content


def reset_body(env_indices: list[int]) -> dict[str, Any]:
    ids = np.asarray(env_indices, np.int64)
    return {"generation": 0, "env_indices": ids, "state_ids": ids + 7}


def step_body(env_indices: list[int], seed: int) -> dict[str, Any]:
    actions = np.random.default_rng(seed).uniform(-1, 1, (len(env_indices), ACTION_DIM)).astype(np.float32)
    return {"generation": 0, "env_indices": np.asarray(env_indices, np.int64), "actions": actions}


def test_slices_of_parts_concatenate_to_the_joined_message() -> None:
    rng = np.random.default_rng(0)
    parts = [b"head", memoryview(rng.bytes(5 * 1024 + 3)), b"", memoryview(rng.bytes(700)), b"x" * 1500, b"tail"]
    pieces = list(slices(parts, 1024))
    assert b"".join(pieces) == b"".join(parts)
    assert all(0 < len(piece) < 2 * 1024 for piece in pieces)


def test_a_big_answer_arrives_bit_equal_to_its_json_form_and_to_the_pods_frames(pod: RunningPod) -> None:
    ids = list(range(NUM_ENVS))
    content = fetch(pod, "reset", reset_body(ids))
    assert len(content) > SLICE_BYTES
    answer = wire.decode(content)
    # The same reset again, answered as JSON: one body, encoded by another path.
    as_json = json.loads(fetch(pod, "reset", reset_body(ids), {**WIRE, "Accept": "application/json"}))
    images = answer["obs"]["images"]["render"]
    assert images.shape == (NUM_ENVS, 384, 384, 3)
    np.testing.assert_array_equal(wire.from_jsonable(as_json["obs"]["images"]["render"], like=images), images)
    for env in ids:
        png = pod_frame(pod, env)
        np.testing.assert_array_equal(png, images[env])


def pod_frame(pod: RunningPod, env: int) -> np.ndarray:
    import httpx

    response = httpx.get(f"{pod.url}/v1/envs/{env}/frame.png", timeout=60)
    assert response.status_code == 200, response.text
    return np.asarray(Image.open(io.BytesIO(response.content)).convert("RGB"))


def test_a_repeated_key_is_answered_the_same_bytes_after_other_envs_moved(pod: RunningPod) -> None:
    fetch(pod, "reset", reset_body(list(range(NUM_ENVS))))
    key = {IDEMPOTENCY_KEY: uuid.uuid4().hex}
    first = fetch(pod, "step", step_body([0, 1, 2], seed=1), {**WIRE, **key})
    assert len(first) > SLICE_BYTES
    fetch(pod, "step", step_body([3], seed=2), {**WIRE, IDEMPOTENCY_KEY: uuid.uuid4().hex})
    again = fetch(pod, "step", step_body([0, 1, 2], seed=1), {**WIRE, **key})
    assert again == first


def test_a_client_leaving_mid_answer_leaves_the_pod_serving(pod: RunningPod) -> None:
    fetch(pod, "reset", reset_body(list(range(NUM_ENVS))))
    actions = np.random.default_rng(3).uniform(-1, 1, (NUM_ENVS, 8, ACTION_DIM)).astype(np.float32)
    # Every env's frame after each of 8 actions: 14 MB, more than the sockets' buffers hold.
    body = wire.encode(
        {
            "generation": 0,
            "env_indices": np.arange(NUM_ENVS),
            "actions": actions,
            "record_env_indices": np.arange(NUM_ENVS),
        }
    )
    head = (
        f"POST /v1/step HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: {wire.CONTENT_TYPE}\r\n"
        f"Accept: {wire.CONTENT_TYPE}\r\nContent-Length: {len(body)}\r\n\r\n"
    ).encode()
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        sock.settimeout(120)
        sock.connect(("127.0.0.1", pod.port))
        sock.sendall(head + body)
        received = b""
        while len(received) < 64 << 10:
            chunk = sock.recv(16 << 10)
            assert chunk, "the pod closed the connection before answering"
            received += chunk
        assert received.startswith(b"HTTP/1.1 200")
    # Gone after 64 KiB of a 14 MB answer: the pod answers the next calls whole.
    after = wire.decode(fetch(pod, "step", step_body(list(range(NUM_ENVS)), seed=4)))
    assert after["obs"]["images"]["render"].shape == (NUM_ENVS, 384, 384, 3)
    assert pod.answers("/readyz")
    assert "Traceback" not in pod.log_text()
