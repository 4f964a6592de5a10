"""The sim pod as a user meets it: real `vecsim pod` processes on loopback, real MuJoCo envs.

Two pods run the same cheap assignment (gymnasium HalfCheetah and Walker2d, whose spaces match,
two envs each, one 16x24 camera: not square, so a transposed image would show): pod A is the one under test, pod B is the reference it must agree
with bit for bit. Pod A is started from a job config, pod B from an assignment file, so both
standalone paths of `vecsim pod` are exercised.
"""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import psutil
import pytest
import yaml
from PIL import Image
from prometheus_client.parser import text_string_to_metric_families
from support.service_procs import Server, clean_env, free_port, running, wait_until

from service.pod.state import steps_on_event_loop
from vecsim import wire
from vecsim.config import Assignment, CameraConfig, TaskBlock

TASKS = ("gym/HalfCheetah-v5", "gym/Walker2d-v5")
GROUP_SIZE = 2
NUM_ENVS = len(TASKS) * GROUP_SIZE
ACTION_DIM = 6
CAMERA = CameraConfig(names=("render",), height=16, width=24)
# Without a camera the scenes are cheap: the pod steps them on its event loop, not its worker thread.
NO_CAMERA = CameraConfig(names=())
BODY_LIMIT = 64 * 1024
JSON_TYPE = "application/json"


class Pod(Server):
    """A `vecsim pod` process on loopback and the calls the tests make to it."""

    def __init__(self, name: str, args: list[str], log_path: Path) -> None:
        port = free_port()
        super().__init__(name, ["pod", "--port", str(port), *args], port, clean_env(POD_NAME=name), log_path)
        self.http = httpx.Client(base_url=self.url, timeout=60.0)

    def stop(self) -> None:
        self.http.close()
        super().stop()

    def info(self) -> dict[str, Any]:
        response = self.http.get("/v1/info")
        assert response.status_code == 200, response.text
        return response.json()

    @property
    def generation(self) -> int:
        return self.info()["generation"]

    def post(self, op: str, body: dict[str, Any], *, send: str = "wire", accept: str = "wire") -> httpx.Response:
        if send == "wire":
            content, content_type = wire.encode(body), wire.CONTENT_TYPE
        else:
            content, content_type = json.dumps(wire.to_jsonable(body)).encode(), JSON_TYPE
        headers = {"Content-Type": content_type, "Accept": JSON_TYPE if accept == "json" else wire.CONTENT_TYPE}
        return self.http.post(f"/v1/{op}", content=content, headers=headers)

    def call(self, op: str, body: dict[str, Any], *, send: str = "wire", accept: str = "wire") -> dict[str, Any]:
        response = self.post(op, body, send=send, accept=accept)
        assert response.status_code == 200, f"{op}: {response.status_code} {response.text[:500]}"
        return json.loads(response.content) if accept == "json" else wire.decode(response.content)

    def reset(self, env_indices: list[int], state_ids: list[int], **formats: str) -> dict[str, Any]:
        body = {
            "generation": self.generation,
            "env_indices": np.asarray(env_indices, np.int64),
            "state_ids": np.asarray(state_ids, np.int64),
        }
        return self.call("reset", body, **formats)

    def step(self, env_indices: list[int], actions: np.ndarray, **formats: str) -> dict[str, Any]:
        body = {"generation": self.generation, "env_indices": np.asarray(env_indices, np.int64), "actions": actions}
        return self.call("step", body, **formats)

    def frame(self, env_index: int, camera: str = "render") -> bytes:
        response = self.http.get(f"/v1/envs/{env_index}/frame.png", params={"camera": camera})
        assert response.status_code == 200, response.text
        return response.content

    def metric(self, name: str, labels: dict[str, str] | None = None) -> float:
        text = self.http.get("/metrics").text
        for family in text_string_to_metric_families(text):
            for sample in family.samples:
                if sample.name == name and (labels is None or sample.labels == labels):
                    return sample.value
        return 0.0


def assignment_for(pod: str, generation: int = 0, camera: CameraConfig = CAMERA) -> Assignment:
    blocks = tuple(
        TaskBlock(task_id=task_id, env_start=i * GROUP_SIZE, num_envs=GROUP_SIZE) for i, task_id in enumerate(TASKS)
    )
    return Assignment(
        generation=generation,
        job_id="pod-tests",
        pod=pod,
        stage_id=0,
        tasks=blocks,
        camera=camera,
        render="lean",
        seed=0,
        envs_per_worker=GROUP_SIZE,
        max_episode_steps=50,
    )


def actions_for(env_indices: list[int], seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.uniform(-1, 1, size=(len(env_indices), ACTION_DIM)).astype(np.float32)


def assert_same_tree(a: Any, b: Any, where: str = "answer") -> None:
    """Exactly equal nested answers: same keys, dtypes, shapes and bytes."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), f"{where}: keys {sorted(a)} != {sorted(b)}"
        for key in a:
            assert_same_tree(a[key], b[key], f"{where}.{key}")
    elif isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray), f"{where}: {type(b).__name__} is not an array"
        assert a.dtype == b.dtype and a.shape == b.shape, f"{where}: {a.dtype}{a.shape} != {b.dtype}{b.shape}"
        assert a.tobytes() == b.tobytes(), f"{where}: values differ"
    else:
        assert list(a) == list(b) if isinstance(a, (list, tuple)) else a == b, f"{where}: {a!r} != {b!r}"


def as_arrays_like(json_answer: Any, wire_answer: Any) -> Any:
    """A JSON answer's lists turned into arrays of the wire answer's dtypes, for exact comparison."""
    if isinstance(wire_answer, dict):
        return {key: as_arrays_like(json_answer[key], wire_answer[key]) for key in json_answer}
    if isinstance(wire_answer, np.ndarray):
        return wire.from_jsonable(json_answer, like=wire_answer).reshape(wire_answer.shape)
    return json_answer


def start_pod(name: str, args: list[str], tmp: Path) -> Iterator[Pod]:
    with running(Pod(name, args, tmp / f"{name}.log")) as pod:
        yield pod


@pytest.fixture(scope="module")
def pod_a(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Pod]:
    """The pod under test, started from a job config with --tasks and --group-size."""
    tmp = tmp_path_factory.mktemp("pod_a")
    config = tmp / "job.yaml"
    job = {
        "job": {
            "job_id": "pod-tests",
            "tasks": list(TASKS),
            "camera": CAMERA.model_dump(mode="json"),
            "render": "lean",
            "envs_per_worker": GROUP_SIZE,
            "max_episode_steps": 50,
            "num_stages": 1,
        }
    }
    config.write_text(yaml.safe_dump(job))
    args = [
        "--config",
        str(config),
        "--stage",
        "0",
        "--tasks",
        ",".join(TASKS),
        "--group-size",
        str(GROUP_SIZE),
        "--max-body-bytes",
        str(BODY_LIMIT),
        "--max-envs",
        "8",
    ]
    yield from start_pod("sim-0", args, tmp)


@pytest.fixture(scope="module")
def pod_b(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Pod]:
    """The reference pod: the same envs, started from an assignment file."""
    tmp = tmp_path_factory.mktemp("pod_b")
    path = tmp / "assignment.json"
    path.write_text(assignment_for("sim-1").model_dump_json())
    yield from start_pod("sim-1", ["--assignment", str(path)], tmp)


@pytest.fixture
def fresh_pod(tmp_path: Path) -> Iterator[Pod]:
    """A pod with no assignment, waiting for one."""
    yield from start_pod("sim-2", [], tmp_path)


@pytest.fixture
def pods(pod_a: Pod, pod_b: Pod) -> tuple[Pod, Pod]:
    """Both module pods, ready, with every env reset to the same states."""
    pod_a.wait_ready()
    pod_b.wait_ready()
    env_indices, state_ids = list(range(NUM_ENVS)), [3, 4, 3, 5]
    pod_a.reset(env_indices, state_ids)
    pod_b.reset(env_indices, state_ids)
    return pod_a, pod_b


def assert_states_match(pod: Pod, reference: Pod, seed: int = 99) -> None:
    """Pod and reference step every env alike: their envs were in the same state."""
    env_indices = list(range(NUM_ENVS))
    actions = actions_for(env_indices, seed)
    assert_same_tree(pod.step(env_indices, actions), reference.step(env_indices, actions), "step after")


# --- health, readiness, info ---------------------------------------------------------------


def test_healthz_answers_alive(pod_a: Pod) -> None:
    response = pod_a.http.get("/healthz")
    assert response.status_code == 200
    assert response.json() == {"status": "alive"}


def test_readyz_is_200_with_generation_once_envs_are_built(pod_a: Pod) -> None:
    pod_a.wait_ready()
    body = pod_a.http.get("/readyz").json()
    assert body["status"] == "ready"
    assert body["num_envs"] == NUM_ENVS
    assert body["generation"] == pod_a.generation


def test_readyz_is_503_until_an_assignment_is_built(fresh_pod: Pod) -> None:
    before = fresh_pod.http.get("/readyz")
    assert before.status_code == 503
    assert "no assignment" in before.json()["detail"]
    assert fresh_pod.info()["instance"] is None
    refused = fresh_pod.post("reset", {"generation": 0, "env_indices": [], "state_ids": []}, send="json")
    assert refused.status_code == 503

    put = fresh_pod.http.put("/v1/assignment", json=assignment_for("sim-2", generation=4).model_dump(mode="json"))
    assert put.status_code == 200
    assert put.json() == {"generation": 4, "rebuilt": True}
    fresh_pod.wait_ready()
    assert fresh_pod.info()["num_envs"] == NUM_ENVS
    assert isinstance(fresh_pod.info()["instance"], str)


def test_spare_assignment_serves_zero_envs(fresh_pod: Pod) -> None:
    spare = Assignment(generation=1, pod="sim-2", stage_id=0, tasks=())
    assert fresh_pod.http.put("/v1/assignment", json=spare.model_dump(mode="json")).status_code == 200
    fresh_pod.wait_ready()
    assert fresh_pod.info()["num_envs"] == 0
    answer = fresh_pod.call("reset", {"generation": 1, "env_indices": [], "state_ids": []}, send="json", accept="json")
    assert answer["env_indices"] == []


def test_info_describes_blocks_instructions_and_spaces(pod_a: Pod) -> None:
    pod_a.wait_ready()
    info = pod_a.info()
    assert info["pod"] == "sim-0"
    assert info["stage_id"] == 0
    assert info["ready"] is True
    assert info["num_envs"] == NUM_ENVS
    assert [(t["task_id"], t["env_start"], t["num_envs"]) for t in info["tasks"]] == [
        (TASKS[0], 0, GROUP_SIZE),
        (TASKS[1], GROUP_SIZE, GROUP_SIZE),
    ]
    assert all(isinstance(t["instruction"], str) for t in info["tasks"])  # gym tasks have none
    assert info["observation_space"] is not None
    assert info["action_space"] is not None


def test_openapi_page_documents_every_endpoint(pod_a: Pod) -> None:
    paths = pod_a.http.get("/openapi.json").json()["paths"]
    assert {
        "/healthz",
        "/readyz",
        "/v1/info",
        "/v1/assignment",
        "/v1/reset",
        "/v1/step",
        "/v1/envs/{env_index}/frame.png",
        "/metrics",
    } <= set(paths)
    assert wire.CONTENT_TYPE in paths["/v1/step"]["post"]["requestBody"]["content"]


# --- data plane --------------------------------------------------------------------------------


def test_same_task_and_state_id_reset_bit_identical_on_two_pods(pod_a: Pod, pod_b: Pod) -> None:
    pod_a.wait_ready()
    pod_b.wait_ready()
    env_indices, state_ids = [0, 1, 2, 3], [7, 7, 2, 9]
    a = pod_a.reset(env_indices, state_ids)
    b = pod_b.reset(env_indices, state_ids)
    assert_same_tree(a, b, "reset")
    assert list(a["info"]["task_id"]) == [TASKS[0], TASKS[0], TASKS[1], TASKS[1]]
    # Two envs of one task reset to one state id hold the same observation.
    assert a["obs"]["proprio"][0].tobytes() == a["obs"]["proprio"][1].tobytes()


def test_reset_answers_the_observation_layout_of_the_contract(pods: tuple[Pod, Pod]) -> None:
    pod_a, _ = pods
    answer = pod_a.reset([1, 2], [0, 1])
    assert answer["env_indices"].dtype == np.int32 and answer["env_indices"].tolist() == [1, 2]
    assert answer["obs"]["images"]["render"].shape == (2, CAMERA.height, CAMERA.width, 3)
    assert answer["obs"]["images"]["render"].dtype == np.uint8
    assert answer["obs"]["proprio"].dtype == np.float32 and answer["obs"]["proprio"].shape == (2, 17)
    assert answer["info"]["success"].dtype == bool


def test_step_of_some_envs_leaves_the_others_untouched(pods: tuple[Pod, Pod]) -> None:
    pod_a, pod_b = pods
    untouched = [1, 3]
    frames_before = [pod_a.frame(i) for i in untouched]
    answer = pod_a.step([0, 2], actions_for([0, 2], seed=1))
    assert answer["env_indices"].tolist() == [0, 2]
    assert answer["reward"].shape == (2,) and answer["reward"].dtype == np.float64
    assert [pod_a.frame(i) for i in untouched] == frames_before
    actions = actions_for(untouched, seed=2)
    assert_same_tree(pod_a.step(untouched, actions), pod_b.step(untouched, actions), "untouched envs")


@pytest.mark.parametrize("chunk", [None, 3], ids=["one-action", "chunk"])
def test_a_step_that_resets_other_envs_answers_as_a_reset_and_a_step_would(
    pods: tuple[Pod, Pod], chunk: int | None
) -> None:
    pod_a, pod_b = pods
    actions = actions_for([0, 3], seed=5)
    if chunk is not None:
        actions = np.repeat(actions[:, None], chunk, axis=1)
    body = {
        "generation": pod_a.generation,
        "env_indices": np.asarray([0, 3], np.int64),
        "actions": actions,
        "reset_env_indices": np.asarray([2, 1], np.int64),
        "reset_state_ids": np.asarray([6, 7], np.int64),
    }
    answer = pod_a.call("step", body)
    assert_same_tree(answer.pop("reset"), pod_b.reset([2, 1], [6, 7]), "reset")
    assert_same_tree(answer, pod_b.step([0, 3], actions), "step")
    assert_states_match(pod_a, pod_b)


@pytest.mark.parametrize(("send", "accept"), [("json", "json"), ("json", "wire"), ("wire", "json")])
def test_json_and_wire_paths_agree_exactly(pods: tuple[Pod, Pod], send: str, accept: str) -> None:
    pod_a, pod_b = pods
    env_indices = [0, 1, 2, 3]
    checks = [
        ("reset", lambda pod, **f: pod.reset(env_indices, [1, 2, 3, 4], **f)),
        ("step", lambda pod, **f: pod.step(env_indices, actions_for(env_indices, seed=3), **f)),
    ]
    for op, call in checks:
        reference = call(pod_b)
        answer = call(pod_a, send=send, accept=accept)
        if accept == "json":
            answer = as_arrays_like(answer, reference)
        assert_same_tree(answer, reference, op)


def test_empty_env_lists_are_noops(pods: tuple[Pod, Pod]) -> None:
    pod_a, pod_b = pods
    frames_before = [pod_a.frame(i) for i in range(NUM_ENVS)]
    reset = pod_a.reset([], [])
    assert reset["env_indices"].shape == (0,)
    assert reset["obs"]["proprio"].shape == (0, 17)
    assert reset["obs"]["images"]["render"].shape == (0, CAMERA.height, CAMERA.width, 3)
    step = pod_a.step([], np.zeros((0, ACTION_DIM), np.float32))
    assert step["reward"].shape == (0,) and step["terminated"].shape == (0,)
    empty = {"generation": pod_a.generation, "env_indices": [], "actions": []}
    as_json = pod_a.call("step", empty, send="json", accept="json")
    assert as_json["env_indices"] == [] and as_json["reward"] == []
    assert [pod_a.frame(i) for i in range(NUM_ENVS)] == frames_before
    assert_states_match(pod_a, pod_b)


def test_frame_png_is_the_camera_image_of_that_env(pods: tuple[Pod, Pod]) -> None:
    pod_a, _ = pods
    observed = pod_a.reset([2], [6])["obs"]["images"]["render"][0]
    image = Image.open(io.BytesIO(pod_a.frame(2)))
    assert image.format == "PNG"
    assert image.size == (CAMERA.width, CAMERA.height)
    assert image.mode == "RGB"
    assert np.array_equal(np.asarray(image), observed)


@pytest.mark.parametrize(
    ("path", "status", "named"),
    [("/v1/envs/4/frame.png", 404, "4"), ("/v1/envs/0/frame.png?camera=agentview", 422, "agentview")],
    ids=["unknown-env", "unknown-camera"],
)
def test_frame_of_unknown_env_or_camera_is_refused(pod_a: Pod, path: str, status: int, named: str) -> None:
    pod_a.wait_ready()
    response = pod_a.http.get(path)
    assert response.status_code == status
    assert named in response.json()["detail"]


def test_metrics_count_env_steps_resets_and_latency(pods: tuple[Pod, Pod]) -> None:
    pod_a, _ = pods
    steps, resets = pod_a.metric("vecsim_pod_env_steps_total"), pod_a.metric("vecsim_pod_env_resets_total")
    latencies = pod_a.metric("vecsim_pod_step_seconds_count")
    pod_a.step([0, 1, 3], actions_for([0, 1, 3], seed=4))
    pod_a.reset([2], [0])
    assert pod_a.metric("vecsim_pod_env_steps_total") == steps + 3
    assert pod_a.metric("vecsim_pod_env_resets_total") == resets + 1
    assert pod_a.metric("vecsim_pod_step_seconds_count") == latencies + 1
    assert pod_a.metric("vecsim_pod_envs") == NUM_ENVS


def test_metrics_count_refused_requests_by_reason(pods: tuple[Pod, Pod]) -> None:
    pod_a, _ = pods
    labels = {"reason": "stale_generation"}
    before = pod_a.metric("vecsim_pod_refused_requests_total", labels)
    stale = {"generation": pod_a.generation + 1, "env_indices": [0], "actions": [[0.0] * ACTION_DIM]}
    assert pod_a.post("step", stale, send="json").status_code == 409
    assert pod_a.metric("vecsim_pod_refused_requests_total", labels) == before + 1


# --- bad input: the right 4xx, and every env exactly as it was --------------------------------


def _bad_requests() -> list[Any]:
    """(id, build(generation) -> (path, content, headers), status, words the detail must name)."""
    wire_h = {"Content-Type": wire.CONTENT_TYPE}
    json_h = {"Content-Type": JSON_TYPE}

    def step_json(**fields: Any) -> Any:
        def build(gen: int) -> tuple[str, bytes, dict[str, str]]:
            body = {"generation": gen, "env_indices": [0, 2], "actions": [[0.1] * ACTION_DIM] * 2}
            body.update({k: (v(gen) if callable(v) else v) for k, v in fields.items()})
            return "/v1/step", json.dumps({k: v for k, v in body.items() if v is not None}).encode(), json_h

        return build

    def step_wire(env_indices: list[int], actions: np.ndarray) -> Any:
        def build(gen: int) -> tuple[str, bytes, dict[str, str]]:
            body = {"generation": gen, "env_indices": np.asarray(env_indices, np.int64), "actions": actions}
            return "/v1/step", wire.encode(body), wire_h

        return build

    def reset_json(**fields: Any) -> Any:
        def build(gen: int) -> tuple[str, bytes, dict[str, str]]:
            body = {"generation": gen, "env_indices": [0, 2], "state_ids": [1, 1]}
            body.update({k: (v(gen) if callable(v) else v) for k, v in fields.items()})
            return "/v1/reset", json.dumps(body).encode(), json_h

        return build

    def raw(path: str, content: bytes, headers: dict[str, str]) -> Any:
        return lambda gen: (path, content, headers)

    nan = np.full((2, ACTION_DIM), 0.1, np.float32)
    nan[1, 3] = np.nan
    inf = np.full((2, ACTION_DIM), 0.1, np.float32)
    inf[0, 0] = np.inf
    big = np.zeros((BODY_LIMIT // 4 // ACTION_DIM + 1, ACTION_DIM), np.float32)
    return [
        pytest.param(step_json(generation=lambda g: g + 7), 409, ["generation"], id="step-stale-generation"),
        pytest.param(reset_json(generation=lambda g: g + 7), 409, ["generation"], id="reset-stale-generation"),
        pytest.param(step_json(env_indices=[0, 4]), 404, ["4", "0..3"], id="unknown-env"),
        pytest.param(step_json(env_indices=[-1, 0]), 404, ["-1"], id="negative-env"),
        pytest.param(reset_json(env_indices=[9, 0]), 404, ["9"], id="reset-unknown-env"),
        pytest.param(step_json(env_indices=[2, 2]), 422, ["env_indices", "2"], id="duplicate-env"),
        pytest.param(step_json(actions=[[0.1] * (ACTION_DIM + 1)] * 2), 422, ["actions"], id="wrong-action-dim"),
        pytest.param(step_json(actions=[[0.1] * ACTION_DIM] * 3), 422, ["actions"], id="more-actions-than-envs"),
        pytest.param(step_json(actions=[[0.1] * ACTION_DIM, [0.1] * 2]), 422, ["actions"], id="ragged-actions"),
        pytest.param(step_json(actions=[["a"] * ACTION_DIM] * 2), 422, ["actions"], id="string-action"),
        pytest.param(step_wire([0, 2], nan), 422, ["actions", "2"], id="nan-action"),
        pytest.param(
            step_json(actions=[[0.1] * ACTION_DIM, ["NaN"] * ACTION_DIM]),
            422,
            ["actions", "2"],
            id="nan-action-as-json-token",
        ),
        pytest.param(step_wire([0, 2], inf), 422, ["actions", "0"], id="inf-action"),
        pytest.param(step_json(actions=[[1e39] * ACTION_DIM] * 2), 422, ["actions"], id="action-beyond-float32"),
        pytest.param(reset_json(seeds=[1, 2]), 422, ["state_ids", "seeds"], id="state-ids-and-seeds"),
        pytest.param(reset_json(state_ids=None, seeds=[1, -1]), 422, ["seeds", "-1"], id="negative-seed"),
        pytest.param(reset_json(state_ids=None, seeds=[1, "x"]), 422, ["seed"], id="string-seed"),
        pytest.param(reset_json(state_ids=None, seeds=[1]), 422, ["seeds"], id="fewer-seeds-than-envs"),
        pytest.param(
            reset_json(state_ids=None, seeds=[1, 2], options=[3]), 422, ["options"], id="options-not-an-object"
        ),
        pytest.param(step_wire([0, 2], np.zeros((2, ACTION_DIM, 1), np.float32)), 422, ["actions"], id="3d-actions"),
        pytest.param(step_json(actions=None), 422, ["actions"], id="missing-actions"),
        pytest.param(
            step_json(reset_env_indices=[1, 2], reset_state_ids=[1, 1]),
            422,
            ["reset_env_indices", "2"],
            id="refill-env-also-stepped",
        ),
        pytest.param(
            step_json(reset_env_indices=[1], reset_state_ids=[1, 1]),
            422,
            ["reset_state_ids"],
            id="refill-state-ids-of-other-length",
        ),
        pytest.param(
            step_json(reset_env_indices=[1], reset_state_ids=[999]),
            422,
            ["reset_state_ids", "999"],
            id="refill-state-id-out-of-range",
        ),
        pytest.param(
            step_json(reset_env_indices=[9], reset_state_ids=[1]),
            404,
            ["reset_env_indices", "9"],
            id="refill-unknown-env",
        ),
        pytest.param(
            step_json(actions=[[0.1] * ACTION_DIM, ["NaN"] * ACTION_DIM], reset_env_indices=[1], reset_state_ids=[1]),
            422,
            ["actions", "2"],
            id="refill-with-a-nan-action",
        ),
        pytest.param(step_json(env_indices=[0.0, 2.0]), 422, ["env_indices"], id="float-env-ids"),
        pytest.param(step_json(generation="3"), 422, ["generation"], id="string-generation"),
        pytest.param(step_json(extra=1), 422, ["extra"], id="unknown-field"),
        pytest.param(reset_json(state_ids=[1, -1]), 422, ["state_ids"], id="negative-state-id"),
        pytest.param(reset_json(state_ids=[1]), 422, ["state_ids"], id="fewer-state-ids-than-envs"),
        pytest.param(raw("/v1/step", b"{not json", json_h), 400, ["JSON"], id="malformed-json"),
        pytest.param(raw("/v1/step", b"[1, 2]", json_h), 422, ["object"], id="json-not-an-object"),
        pytest.param(
            raw("/v1/step", b"VSW1\xff\xff\xff\xffgarbage", wire_h), 400, [wire.CONTENT_TYPE], id="malformed-wire"
        ),
        pytest.param(
            raw("/v1/step", b"generation=1", {"Content-Type": "application/x-www-form-urlencoded"}),
            415,
            ["Content-Type"],
            id="form-body",
        ),
        pytest.param(step_wire(list(range(len(big))), big), 413, ["limit"], id="body-over-limit"),
    ]


@pytest.mark.parametrize(("build", "status", "named"), _bad_requests())
def test_bad_request_is_refused_and_changes_nothing(
    pods: tuple[Pod, Pod], build: Any, status: int, named: list[str]
) -> None:
    pod_a, pod_b = pods
    generation = pod_a.generation
    frames_before = [pod_a.frame(i) for i in range(NUM_ENVS)]
    path, content, headers = build(generation)
    response = pod_a.http.post(path, content=content, headers=headers)
    assert response.status_code == status, response.text
    detail = response.json()["detail"]
    assert isinstance(detail, str)
    for word in named:
        assert word in detail, f"{word!r} not named in {detail!r}"
    assert pod_a.generation == generation
    assert [pod_a.frame(i) for i in range(NUM_ENVS)] == frames_before
    assert_states_match(pod_a, pod_b)


def test_streamed_body_over_the_limit_is_413(pods: tuple[Pod, Pod]) -> None:
    pod_a, pod_b = pods
    chunks = iter([b"{" + b" " * BODY_LIMIT, b"}"])  # no Content-Length: the bytes read count
    response = pod_a.http.post("/v1/step", content=chunks, headers={"Content-Type": JSON_TYPE})
    assert response.status_code == 413
    assert_states_match(pod_a, pod_b)


def test_assignment_body_over_the_limit_is_413(pods: tuple[Pod, Pod]) -> None:
    pod_a, pod_b = pods
    generation = pod_a.generation
    padded = assignment_for("sim-0", generation=generation + 1).model_dump_json() + " " * BODY_LIMIT
    response = pod_a.http.put("/v1/assignment", content=padded, headers={"Content-Type": JSON_TYPE})
    assert response.status_code == 413
    assert pod_a.generation == generation
    assert_states_match(pod_a, pod_b)


# --- assignments -------------------------------------------------------------------------------


def put_assignment(pod: Pod, assignment: Assignment) -> httpx.Response:
    return pod.http.put("/v1/assignment", json=assignment.model_dump(mode="json"))


def test_new_generation_with_same_content_is_adopted_without_rebuild(pods: tuple[Pod, Pod]) -> None:
    pod_a, pod_b = pods
    old, instance = pod_a.generation, pod_a.info()["instance"]
    response = put_assignment(pod_a, assignment_for("sim-0", generation=old + 1))
    assert response.status_code == 200
    assert response.json() == {"generation": old + 1, "rebuilt": False}
    assert pod_a.http.get("/readyz").status_code == 200
    stale = pod_a.post("step", {"generation": old, "env_indices": [0], "actions": [[0.0] * ACTION_DIM]}, send="json")
    assert stale.status_code == 409
    assert str(old) in stale.json()["detail"] and str(old + 1) in stale.json()["detail"]
    # The envs kept their state: they were not rebuilt.
    assert pod_a.info()["instance"] == instance
    assert_states_match(pod_a, pod_b)


def test_same_assignment_twice_is_idempotent(pods: tuple[Pod, Pod]) -> None:
    pod_a, pod_b = pods
    current = assignment_for("sim-0", generation=pod_a.generation)
    response = put_assignment(pod_a, current)
    assert response.status_code == 200
    assert response.json() == {"generation": current.generation, "rebuilt": False}
    assert_states_match(pod_a, pod_b)


def _refused_assignments() -> list[Any]:
    """(id, build(current generation) -> Assignment, status, words the detail must name)."""
    other_tasks = (TaskBlock(task_id=TASKS[0], env_start=0, num_envs=1),)
    too_many = (TaskBlock(task_id=TASKS[0], env_start=0, num_envs=9),)
    unknown = (TaskBlock(task_id="gym/NoSuchEnv-v0", env_start=0, num_envs=1),)
    return [
        pytest.param(
            lambda g: assignment_for("sim-0", generation=g).model_copy(update={"tasks": other_tasks}),
            409,
            ["generation"],
            id="same-generation-other-content",
        ),
        pytest.param(lambda g: assignment_for("sim-9", generation=g + 1), 422, ["sim-9", "sim-0"], id="another-pod"),
        pytest.param(
            lambda g: assignment_for("sim-0", generation=g + 1).model_copy(update={"tasks": too_many}),
            422,
            ["9", "8"],
            id="over-max-envs",
        ),
        pytest.param(
            lambda g: assignment_for("sim-0", generation=g + 1).model_copy(update={"tasks": unknown}),
            422,
            ["gym/NoSuchEnv-v0"],
            id="unknown-task",
        ),
    ]


@pytest.mark.parametrize(("build", "status", "named"), _refused_assignments())
def test_refused_assignment_changes_nothing(pods: tuple[Pod, Pod], build: Any, status: int, named: list[str]) -> None:
    pod_a, pod_b = pods
    generation = pod_a.generation
    response = put_assignment(pod_a, build(generation))
    assert response.status_code == status, response.text
    for word in named:
        assert word in response.json()["detail"]
    assert pod_a.generation == generation
    assert pod_a.http.get("/readyz").status_code == 200
    assert_states_match(pod_a, pod_b)


@pytest.mark.parametrize(
    ("fields", "named"),
    [
        ({"stage_id": 0}, "pod"),
        ({"pod": "sim-0", "stage_id": 0, "tasks": [{"task_id": TASKS[0], "env_start": 1, "num_envs": 2}]}, "tasks"),
        ({"pod": "sim-0", "stage_id": 0, "camera": {"names": ["render"], "height": 4, "width": 16}}, "camera"),
    ],
    ids=["missing-pod", "blocks-not-contiguous", "camera-too-small"],
)
def test_malformed_assignment_is_422_naming_the_field(
    pods: tuple[Pod, Pod], fields: dict[str, Any], named: str
) -> None:
    pod_a, pod_b = pods
    generation = pod_a.generation
    response = pod_a.http.put("/v1/assignment", json={"generation": generation + 1, **fields})
    assert response.status_code == 422
    assert named in response.json()["detail"]
    assert pod_a.generation == generation
    assert_states_match(pod_a, pod_b)


def test_older_assignment_generation_is_409(pods: tuple[Pod, Pod]) -> None:
    pod_a, _ = pods
    newer = pod_a.generation + 1
    assert put_assignment(pod_a, assignment_for("sim-0", generation=newer)).status_code == 200
    response = put_assignment(pod_a, assignment_for("sim-0", generation=newer - 1))
    assert response.status_code == 409
    assert str(newer - 1) in response.json()["detail"] and str(newer) in response.json()["detail"]
    assert pod_a.generation == newer


# --- failures and recovery ---------------------------------------------------------------------


def test_failed_build_leaves_the_pod_unready_saying_why_until_a_new_assignment(fresh_pod: Pod) -> None:
    # Pendulum has Box spaces but cannot render at a given size: the workers fail to build it.
    unbuildable = assignment_for("sim-2", generation=1).model_copy(
        update={"tasks": (TaskBlock(task_id="gym/Pendulum-v1", env_start=0, num_envs=1),)}
    )
    response = put_assignment(fresh_pod, unbuildable)
    assert response.status_code == 200 and response.json()["rebuilt"] is True
    wait_until(lambda: "failed" in fresh_pod.http.get("/readyz").text, "the build to fail")
    readyz = fresh_pod.http.get("/readyz")
    assert readyz.status_code == 503
    assert "gym/Pendulum-v1" in readyz.json()["detail"]
    assert fresh_pod.info()["ready"] is False

    assert put_assignment(fresh_pod, assignment_for("sim-2", generation=2)).status_code == 200
    fresh_pod.wait_ready()
    assert fresh_pod.info()["num_envs"] == NUM_ENVS


@pytest.mark.parametrize("camera", [CAMERA, NO_CAMERA], ids=["worker-thread", "event-loop"])
@pytest.mark.slow
def test_dead_sim_worker_gives_503_then_the_pod_rebuilds(fresh_pod: Pod, camera: CameraConfig) -> None:
    assignment = assignment_for("sim-2", generation=1, camera=camera)
    assert put_assignment(fresh_pod, assignment).status_code == 200
    fresh_pod.wait_ready()
    instance = fresh_pod.info()["instance"]
    # The env workers are the children of the pod's multiprocessing forkserver.
    servers = [p for p in psutil.Process(fresh_pod.proc.pid).children() if "forkserver" in " ".join(p.cmdline())]
    workers = [worker for server in servers for worker in server.children()]
    assert workers, "the pod runs its envs in worker processes"
    for worker in workers:
        worker.kill()
    response = fresh_pod.post(
        "step", {"generation": 1, "env_indices": [0], "actions": [[0.0] * ACTION_DIM]}, send="json"
    )
    assert response.status_code == 503
    assert "crash" in response.json()["detail"]
    fresh_pod.wait_ready()
    assert fresh_pod.info()["instance"] not in (None, instance)
    reset = {"generation": 1, "env_indices": [0, 3], "state_ids": [0, 0]}
    answer = fresh_pod.call("reset", reset, send="json", accept="json")
    assert answer["env_indices"] == [0, 3]


@pytest.mark.parametrize(
    ("tasks", "camera", "on_loop"),
    [
        (TASKS, NO_CAMERA, True),
        (TASKS, CAMERA, False),
        (("tiny/lift",), NO_CAMERA, False),
        ((), NO_CAMERA, True),
    ],
    ids=["gym-no-camera", "gym-camera", "robot", "spare"],
)
def test_only_cheap_scenes_are_stepped_on_the_event_loop(
    tasks: tuple[str, ...], camera: CameraConfig, on_loop: bool
) -> None:
    blocks = tuple(TaskBlock(task_id=t, env_start=i * GROUP_SIZE, num_envs=GROUP_SIZE) for i, t in enumerate(tasks))
    assignment = Assignment(generation=0, job_id="pod-tests", pod="sim-0", stage_id=0, tasks=blocks, camera=camera)
    assert steps_on_event_loop(assignment) is on_loop


def test_pod_stepping_on_its_event_loop_simulates_exactly_as_on_its_worker_thread(fresh_pod: Pod, pod_b: Pod) -> None:
    assert put_assignment(fresh_pod, assignment_for("sim-2", generation=0, camera=NO_CAMERA)).status_code == 200
    fresh_pod.wait_ready()
    pod_b.wait_ready()
    env_indices = list(range(NUM_ENVS))
    answers = []
    for pod in (fresh_pod, pod_b):
        first = pod.reset(env_indices, [1, 2, 1, 3])
        steps = [pod.step(env_indices, actions_for(env_indices, seed)) for seed in range(3)]
        answers.append((first, steps))
    (cheap_reset, cheap_steps), (reference_reset, reference_steps) = answers
    # Without cameras the observation is the env's own float64 Box; with them, float32 proprio.
    assert isinstance(cheap_reset["obs"], np.ndarray) and cheap_reset["obs"].dtype == np.float64
    assert_same_tree(cheap_reset["obs"].astype(np.float32), reference_reset["obs"]["proprio"], "reset obs.proprio")
    for i, (cheap, reference) in enumerate(zip(cheap_steps, reference_steps)):
        for key in ("env_indices", "reward", "terminated", "truncated"):
            assert_same_tree(cheap[key], reference[key], f"step {i} {key}")
        assert_same_tree(cheap["obs"].astype(np.float32), reference["obs"]["proprio"], f"step {i} obs.proprio")


# --- the command line --------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("args", "named"),
    [
        (["--tasks", ",".join(TASKS), "--group-size", "4", "--max-envs", "6"], "8 envs"),
        (["--tasks", "gym/NoSuchEnv-v0"], "gym/NoSuchEnv-v0"),
        (["--assignment", "/nonexistent/assignment.json"], "/nonexistent/assignment.json"),
    ],
    ids=["over-max-envs", "unknown-task", "missing-assignment-file"],
)
def test_cli_refuses_an_unusable_standalone_assignment(args: list[str], named: str) -> None:
    done = subprocess.run(
        [sys.executable, "-m", "service.cli", "pod", "--port", str(free_port()), *args],
        capture_output=True,
        text=True,
        timeout=60,
        env={**os.environ, "POD_NAME": "sim-5"},
    )
    assert done.returncode == 2
    assert named in done.stderr
