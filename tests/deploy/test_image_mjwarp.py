"""The mjwarp engine's pod image, built and run: ``scripts/build_image.sh --engine mjwarp`` builds
the Dockerfile's ``mjwarp`` target (the CPU image's layers, a venv of the ``mjwarp`` extra, the
LIBERO scenes the CPU venv exported at build time), and its own entrypoint and command run in it
with ``buildah run`` on loopback, with the volumes and the environment the gpu-mjwarp overlay
gives the sim container.

This machine has no GPU: the pod must start, serve what it knows from the scenes, and answer
not-ready naming the missing CUDA driver. Nothing stands in for the GPU. Shares the CPU image's
build cache (``VECSIM_IMAGE_CACHE``), so after tests/deploy/test_image.py only the mjwarp layers
build. Needs root; select with ``-m image``.
"""

from __future__ import annotations

import json
import os
import re
import tomllib
from collections.abc import Iterator
from typing import Any

import httpx
import pytest
import yaml
from support import ROOT
from support.images import (
    IMAGE_MARKS,
    READY_TIMEOUT_S,
    VERSION,
    build_image,
    buildah,
    failed_detail,
    image_env,
    image_uid,
    pod_argv,
    run_once,
    running,
    working_container,
    writable_volumes,
)
from support.k8s_manifests import build as kustomize_build
from support.service_procs import free_port, wait_until

TAG = f"vecsim-mjwarp:{VERSION}"
JOB = "/app/configs/libero_10_mjwarp.yaml"
ENVS = 2

pytestmark = IMAGE_MARKS


@pytest.fixture(scope="module")
def image() -> dict[str, Any]:
    return build_image(TAG, "--engine", "mjwarp")


@pytest.fixture(scope="module")
def container(image) -> Iterator[str]:
    with working_container(TAG, f"vecsim-mjwarp-test-{os.getpid()}") as name:
        yield name


def _pins(extra: str) -> dict[str, str]:
    """``name -> version`` of the ``==`` pins of a pyproject extra."""
    requirements = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"][extra]
    return dict(r.split("==") for r in requirements if "==" in r and "[" not in r)


def _default_tasks() -> list[str]:
    """The LIBERO tasks the Dockerfile's mjwarp target exports unless told otherwise."""
    return re.search(r'^ARG MJWARP_TASKS="([^"]*)"', (ROOT / "Dockerfile").read_text(), re.M).group(1).split()


def _python_json(container: str, python: str, script: str, *args: str) -> Any:
    """Run ``script`` with ``python`` in the container, ``args`` as its ``sys.argv[1:]``; the JSON
    it prints last."""
    done = run_once(container, [python, "-c", script, *args], timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


# The interpreter, and the version of each named distribution installed beside it.
_VERSIONS = """
import importlib.metadata as m, json, sys
versions = {}
for name in sys.argv[1:]:
    try:
        versions[name] = m.version(name)
    except m.PackageNotFoundError:
        pass
print(json.dumps({"python": sys.executable, "versions": versions}))
"""

# Each scene of the tasks named, as the engine finds and reads it, loaded by the venv's mujoco,
# and the spaces the engine's assignment check answers for all of them.
_SCENES = """
import json, sys, mujoco
from vecsim.config import Assignment, CameraConfig, LiberoProtocol, TaskBlock
from vecsim.engine.mjwarp.engine import spaces
from vecsim.engine.mjwarp.scene import default_root, load_scene, scene_dir
tasks = sys.argv[1:]
found = {}
for task in tasks:
    scene = load_scene(scene_dir(task, LiberoProtocol()))
    model = mujoco.MjModel.from_xml_path(str(scene.xml))
    found[task] = {
        "manifest_task": scene.manifest["task_id"],
        "sizes": {name: getattr(model, name) for name in scene.manifest["sizes"]},
        "manifest_sizes": scene.manifest["sizes"],
        "exported_with": scene.manifest["exported_with"],
        "rows": sorted({len(v) for v in scene.states.values()}),
        "num_states": scene.num_states,
    }
blocks = tuple(TaskBlock(task_id=t, env_start=2 * i, num_envs=2) for i, t in enumerate(tasks))
camera = CameraConfig(names=("agentview", "robot0_eye_in_hand"), height=64, width=64)
assignment = Assignment(generation=1, pod="sim-0", stage_id=0, engine="mjwarp", tasks=blocks, camera=camera)
observation, action = spaces(assignment)
root = default_root()
print(json.dumps({"root": str(root), "dirs": sorted(p.name for p in root.iterdir()), "scenes": found,
                  "observation": sorted(observation.spaces), "action": list(action.shape)}))
"""


# -- what the image is ---------------------------------------------------------------------------


def test_the_gpu_mjwarp_overlay_names_the_tag_the_build_produces(image):
    (sts,) = [o for o in kustomize_build("gpu-mjwarp") if o["kind"] == "StatefulSet"]
    (sim,) = sts["spec"]["template"]["spec"]["containers"]
    assert sim["image"].rsplit("/", 1)[-1] == TAG
    names = buildah("images", "--format", "{{.Name}}:{{.Tag}}").split()
    assert any(name.rsplit("/", 1)[-1] == TAG for name in names), names


def test_the_pod_venv_holds_the_mjwarp_extras_pins_and_no_cpu_stack(container, image):
    pins = _pins("mjwarp")
    found = _python_json(container, "python", _VERSIONS, *pins, "robosuite", "libero", "torch")
    assert found["python"].startswith(image_env(image)["VECSIM_MJWARP_VENV"] + "/"), found
    assert found["versions"] == pins, found


def test_the_cpu_venv_beside_it_keeps_the_cpu_pods_pins(container, image):
    pins = {name: version for name, version in _pins("pod").items() if name in ("mujoco", "robosuite")}
    python = f"{image_env(image)['VECSIM_VENV']}/bin/python"
    found = _python_json(container, python, _VERSIONS, *pins, "mujoco-warp", "warp-lang")
    assert found["versions"] == pins, found


def test_the_images_scenes_load_in_the_pod_venv_and_pass_the_engines_checks(container, image):
    tasks = _default_tasks()
    assert "libero_10/0" in tasks
    found = _python_json(container, "python", _SCENES, *tasks)
    assert found["root"] == image_env(image)["VECSIM_MJWARP_SCENES"]
    assert len(found["dirs"]) == len(tasks), found["dirs"]
    cpu = _pins("pod")
    for task, scene in found["scenes"].items():
        assert scene["manifest_task"] == task
        assert scene["sizes"] == scene["manifest_sizes"], task  # mujoco 4 reads the model mujoco 3.3 wrote
        assert scene["exported_with"] == {"mujoco": cpu["mujoco"], "robosuite": cpu["robosuite"]}, task
        assert scene["rows"] == [scene["num_states"]] and scene["num_states"] > 0, task
    assert {"images", "state"} <= set(found["observation"]) and found["action"], found


def test_warps_kernel_cache_is_on_the_pods_cache_volume(image):
    # The root filesystem is read-only in the manifests; the cache (an emptyDir) is writable.
    env = image_env(image)
    assert env["WARP_CACHE_PATH"].startswith(env["XDG_CACHE_HOME"] + "/")


# -- a pod in the image, on a machine without a GPU ----------------------------------------------


def _overlay_env() -> dict[str, str]:
    """The plain values the gpu-mjwarp overlay sets on the sim container (not the downward API's)."""
    (sts,) = [o for o in kustomize_build("gpu-mjwarp") if o["kind"] == "StatefulSet"]
    (sim,) = sts["spec"]["template"]["spec"]["containers"]
    return {item["name"]: item["value"] for item in sim["env"] if "value" in item and "$(" not in item["value"]}


def test_pod_of_an_mjwarp_job_without_a_gpu_serves_its_tasks_and_answers_not_ready_naming_cuda(
    container, image, tmp_path
):
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    env = {**_overlay_env(), "VECSIM_HOST": "127.0.0.1", "VECSIM_PORT": str(port)}
    argv = pod_argv(image, "--config", JOB, "--group-size", str(ENVS))
    with running(container, argv, env, writable_volumes(tmp_path, image), tmp_path / "pod.log") as proc:
        detail = wait_until(lambda: failed_detail(url, proc), "the pod's build to fail", READY_TIMEOUT_S, 1.0)
        assert "CUDA" in detail and "libcuda.so.1" in detail, detail
        # Alive, so that the readiness probe (not liveness) keeps it out of service, and it says
        # what it would serve: read from the image's scenes, with no LIBERO in its venv.
        assert httpx.get(f"{url}/healthz", timeout=5).status_code == 200
        info = httpx.get(f"{url}/v1/info", timeout=10).json()
        assert [task["task_id"] for task in info["tasks"]] == yaml.safe_load(
            (ROOT / "configs" / "libero_10_mjwarp.yaml").read_text()
        )["job"]["tasks"]
        assert all(task["num_states"] > 0 and task["instruction"] for task in info["tasks"]), info
        # The pod is the mjwarp venv's `vecsim`, run as the image's user.
        script = f"{image_env(image)['VECSIM_MJWARP_VENV']}/bin/vecsim"
        servers = [p for p in proc.processes() if p.cmdline()[1:2] == [script]]
        assert servers, [p.cmdline() for p in proc.processes()]
        assert {p.uids().real for p in servers} == {image_uid(image)}
