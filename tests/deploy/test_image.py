"""The pod image, built and run: ``scripts/build_image.sh`` builds the repository's Dockerfile
(debootstrap base, ``buildah bud``), and the image's own entrypoint, command and HEALTHCHECK run
in it with ``buildah run`` on loopback, as the Kubernetes manifests run them.

The build is cached under ``~/.cache/vecsim/image`` (``VECSIM_IMAGE_CACHE``): a fresh machine
builds everything (minutes), a rerun rebuilds only the layers the change touched. Needs root
(debootstrap, buildah's chroot isolation); ``scripts/setup.sh`` installs buildah and debootstrap.
Select with ``-m image``.
"""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Iterator

import httpx
import numpy as np
import pytest
import yaml
from support import ROOT
from support.images import (
    IMAGE_MARKS,
    READY_TIMEOUT_S,
    START_TIMEOUT_S,
    VERSION,
    InContainer,
    build_image,
    buildah,
    failed_detail,
    image_env,
    image_uid,
    owned_dir,
    pod_argv,
    run_once,
    running,
    working_container,
    writable_volumes,
)
from support.service_procs import free_port, wait_until
from support.wire_http import wire_answer


TAG = f"vecsim:{VERSION}"
IMAGE_TOKEN = "image-test-token"  # the token the image tests start the pod and controller with
TASK = "tiny/lift"
ENVS = 2

pytestmark = IMAGE_MARKS


@pytest.fixture(scope="module")
def image() -> dict:
    """Build the image (or find every layer cached) and return its Docker config."""
    return build_image(TAG)


@pytest.fixture(scope="module")
def container(image) -> Iterator[str]:
    """One working container of the image; every command below runs in it."""
    with working_container(TAG, f"vecsim-test-{os.getpid()}") as name:
        yield name


def _standalone(port: int) -> tuple[str, ...]:
    return ("--config", "/app/configs/tiny.yaml", "--tasks", TASK, "--group-size", str(ENVS), "--port", str(port))


@pytest.fixture(scope="module")
def pod(container, image, tmp_path_factory) -> Iterator[tuple[str, InContainer]]:
    port = free_port()
    base = tmp_path_factory.mktemp("pod")
    env = {"VECSIM_HOST": "127.0.0.1", "VECSIM_PORT": str(port), "VECSIM_TOKEN": IMAGE_TOKEN}
    url = f"http://127.0.0.1:{port}"
    with running(
        container, pod_argv(image, *_standalone(port)), env, writable_volumes(base, image), base / "pod.log"
    ) as proc:
        wait_until(
            lambda: _ready(url, proc), f"the pod in the image to be ready\n{proc.log_text()}", READY_TIMEOUT_S, 1.0
        )
        yield url, proc


def _ready(url: str, proc: InContainer) -> bool:
    assert proc.proc.poll() is None, f"the pod exited with {proc.proc.returncode}:\n{proc.log_text()}"
    with contextlib.suppress(httpx.HTTPError):
        return httpx.get(f"{url}/readyz", timeout=5).status_code == 200
    return False


# -- what the image is ---------------------------------------------------------------------------


def test_manifests_name_the_tag_the_build_produces(image):
    kustomization = yaml.safe_load((ROOT / "k8s" / "base" / "kustomization.yaml").read_text())
    (pinned,) = [entry for entry in kustomization["images"] if entry["name"] == "vecsim"]
    assert f"vecsim:{pinned['newTag']}" == TAG
    names = buildah("images", "--format", "{{.Name}}:{{.Tag}}").split()
    assert any(name.rsplit("/", 1)[-1] == TAG for name in names), names


def test_image_holds_the_cpu_torch_and_no_cuda_packages(container):
    done = run_once(container, ["python", "-c", "import torch; print(torch.__version__, torch.version.cuda)"])
    assert done.returncode == 0, done.stderr
    version, cuda = done.stdout.split()
    assert version.startswith("2.13.0") and cuda == "None", done.stdout
    listed = run_once(container, ["python", "-m", "pip", "list", "--format", "json"])
    names = {entry["name"].lower() for entry in json.loads(listed.stdout)}
    assert not {name for name in names if name.startswith("nvidia-")}, names
    assert {"mujoco", "robosuite", "libero", "vecsim"} <= names
    # No video packages (pytest is there: bddl declares it; matplotlib: LIBERO's env imports it).
    assert not names & {"imageio", "imageio-ffmpeg"}


def test_image_holds_what_a_libero_env_imports_and_reads(container):
    # What a pod of the job k8s/ deploys (configs/libero_10.yaml) imports to build a LIBERO env,
    # and a task file it reads. (The mjwarp image's build, tests/deploy/test_image_mjwarp.py, runs
    # whole LIBERO envs in this same venv when it exports their scenes.)
    script = (
        "import os; from vecsim.engine.tasks._libero import libero_benchmark; "
        "bddl = libero_benchmark('libero_10').get_task_bddl_file_path(0); "
        "from libero.libero.envs import OffScreenRenderEnv; print(os.path.isfile(bddl))"
    )
    done = run_once(container, ["python", "-c", script], timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.strip().splitlines()[-1] == "True", done.stdout[-2000:]


# -- a pod in the image --------------------------------------------------------------------------


def test_pod_runs_as_the_images_non_root_uid(pod, image):
    _, proc = pod
    uid = image_uid(image)
    assert uid != 0
    servers = [p for p in proc.processes() if "vecsim" in " ".join(p.cmdline()) and "buildah" not in p.name()]
    assert servers, [p.cmdline() for p in proc.processes()]
    assert {p.uids().real for p in servers} == {uid}, [(p.cmdline(), p.uids()) for p in servers]


def test_pod_resets_steps_and_takes_a_chunk_of_a_robosuite_task_rendered_by_mesa(pod):
    url, _ = pod
    info = httpx.get(f"{url}/v1/info", timeout=10).json()
    assert [task["task_id"] for task in info["tasks"]] == [TASK] and info["num_envs"] == ENVS
    generation = info["generation"]
    indices = np.arange(ENVS)
    reset = wire_answer(
        url,
        "reset",
        {"generation": generation, "env_indices": indices, "state_ids": np.zeros(ENVS, np.int64)},
        IMAGE_TOKEN,
        timeout=120,
    )
    images = reset["obs"]["images"]
    assert images, reset["obs"].keys()
    for camera, frames in images.items():
        assert frames.shape[0] == ENVS and frames.dtype == np.uint8
        assert frames.std() > 0, f"camera {camera} rendered a blank frame"
    action_dim = info["action_space"]["shape"][-1]
    step = wire_answer(
        url,
        "step",
        {"generation": generation, "env_indices": indices, "actions": np.zeros((ENVS, action_dim), np.float32)},
        IMAGE_TOKEN,
        timeout=120,
    )
    assert step["reward"].shape == (ENVS,)
    assert not step.get("errors"), step.get("errors")
    chunk = np.random.default_rng(0).uniform(-1, 1, (ENVS, 3, action_dim)).astype(np.float32)
    answer = wire_answer(
        url, "step", {"generation": generation, "env_indices": indices, "actions": chunk}, IMAGE_TOKEN, timeout=120
    )
    assert answer["reward"].shape == (ENVS, 3)
    assert answer["num_steps"].tolist() == [3] * ENVS
    assert not answer.get("errors"), answer.get("errors")


def test_images_healthcheck_command_succeeds_against_the_pod(pod, image, container):
    url = pod[0]
    test = image["Healthcheck"]["Test"]
    assert test[0] == "CMD"
    port = url.rsplit(":", 1)[1]
    assert run_once(container, test[1:], {"VECSIM_PORT": port}).returncode == 0
    # ... and fails where nothing answers: the check means something.
    assert run_once(container, test[1:], {"VECSIM_PORT": str(free_port())}).returncode != 0


# -- the controller in the image -----------------------------------------------------------------


def test_controller_command_starts_and_passes_the_healthcheck(container, image, tmp_path):
    port = free_port()
    argv = [
        *image["Entrypoint"],
        "controller",
        "--config",
        "/app/configs/tiny.yaml",
        "--host",
        "127.0.0.1",
        "--port",
        str(port),
    ]
    env = {"VECSIM_PORT": str(port), "VECSIM_TOKEN": IMAGE_TOKEN}
    with running(container, argv, env, writable_volumes(tmp_path, image), tmp_path / "controller.log") as proc:

        def healthy() -> bool:
            assert proc.proc.poll() is None, f"the controller exited:\n{proc.log_text()}"
            with contextlib.suppress(httpx.HTTPError):
                return httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=5).status_code == 200
            return False

        wait_until(healthy, "the controller in the image to answer /healthz", START_TIMEOUT_S, 1.0)
        assert run_once(container, image["Healthcheck"]["Test"][1:], {"VECSIM_PORT": str(port)}).returncode == 0


# -- bad configuration in the container: the pod exits, or answers not-ready, naming the cause ----


def _pod_env(port: int, **extra: str) -> dict[str, str]:
    return {"VECSIM_HOST": "127.0.0.1", "VECSIM_PORT": str(port), **extra}


def test_pod_with_an_unwritable_cache_answers_not_ready_naming_the_cache(container, image, tmp_path):
    port = free_port()
    cache = image_env(image)["XDG_CACHE_HOME"]
    volumes = {
        owned_dir(tmp_path / "tmp", image_uid(image), 0o1777): "/tmp",
        owned_dir(tmp_path / "cache", 0, 0o755): cache,  # root's: the pod's uid cannot write it
    }
    url = f"http://127.0.0.1:{port}"
    with running(container, pod_argv(image, *_standalone(port)), _pod_env(port), volumes, tmp_path / "pod.log") as proc:
        detail = wait_until(lambda: failed_detail(url, proc), "the pod's build to fail", READY_TIMEOUT_S, 1.0)
        assert "Permission denied" in detail and cache in detail, detail
        # Alive, so that the readiness probe (not liveness) keeps it out of service.
        assert httpx.get(f"{url}/healthz", timeout=5).status_code == 200


def test_pod_set_up_for_a_gpu_on_a_node_without_one_answers_not_ready_naming_egl(container, image, tmp_path):
    # What the gpu-cluster overlay sets on the container, on this machine without NVIDIA's driver.
    overlay = yaml.safe_load((ROOT / "k8s" / "overlays" / "gpu-cluster" / "sim-gpu.yaml").read_text())
    (sim,) = overlay["spec"]["template"]["spec"]["containers"]
    gpu_env = {item["name"]: item["value"] for item in sim["env"]}
    assert "__EGL_VENDOR_LIBRARY_FILENAMES" in gpu_env
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    volumes = writable_volumes(tmp_path, image)
    with running(
        container, pod_argv(image, *_standalone(port)), _pod_env(port, **gpu_env), volumes, tmp_path / "pod.log"
    ) as proc:
        detail = wait_until(lambda: failed_detail(url, proc), "the pod's build to fail", READY_TIMEOUT_S, 1.0)
        assert "EGL" in detail, detail


def test_pod_without_the_token_secret_serves_and_warns_naming_vecsim_token(container, image, tmp_path):
    # The manifests mark the Secret optional: without it VECSIM_TOKEN is unset and the pod
    # starts with checking off, saying so (docs/kubernetes.md, The shared token).
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    log_path = tmp_path / "pod.log"
    with running(container, pod_argv(image), _pod_env(port), writable_volumes(tmp_path, image), log_path) as proc:

        def answering() -> bool:
            assert proc.proc.poll() is None, f"the pod exited:\n{proc.log_text()}"
            with contextlib.suppress(httpx.HTTPError):
                return httpx.get(f"{url}/healthz", timeout=5).status_code == 200
            return False

        wait_until(answering, "the pod to answer /healthz", START_TIMEOUT_S, 1.0)
        warnings = [line for line in log_path.read_text().splitlines() if " WARNING " in line]
        assert any("VECSIM_TOKEN" in line for line in warnings), proc.log_text()
        assert "no assignment" in httpx.get(f"{url}/readyz", timeout=5).json()["detail"]


def test_pod_given_a_token_secret_with_a_trailing_newline_exits_naming_vecsim_token(container, image, tmp_path):
    # What `kubectl create secret --from-file` of a file ending in a newline hands the container.
    port = free_port()
    env = _pod_env(port, VECSIM_TOKEN="s3cret\n")
    with running(container, pod_argv(image), env, writable_volumes(tmp_path, image), tmp_path / "pod.log") as proc:
        returncode = proc.proc.wait(timeout=START_TIMEOUT_S)
        assert returncode == 2, proc.log_text()
        assert "VECSIM_TOKEN" in proc.log_text()
