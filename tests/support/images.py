"""The pod images as the image tests build and run them: ``scripts/build_image.sh`` into the
cached buildah store (``~/.cache/vecsim/image``, ``VECSIM_IMAGE_CACHE``), then commands in a
working container of an image with ``buildah run``, on loopback, with the volumes the manifests
mount."""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import subprocess
import time
import tomllib
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import httpx
import psutil
import pytest

from . import ROOT
from .service_procs import log_tail

log = logging.getLogger(__name__)

CACHE = Path(os.environ.get("VECSIM_IMAGE_CACHE", Path.home() / ".cache" / "vecsim" / "image"))
VERSION = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
# The store scripts/build_image.sh builds into (it writes the storage config on its first run).
BUILDAH = ("env", f"CONTAINERS_STORAGE_CONF={CACHE / 'storage.conf'}", "buildah")
BUILD_TIMEOUT_S = 1800
# The marks of every module that builds an image: slow, root only, the build's own time bound.
IMAGE_MARKS = [
    pytest.mark.image,
    pytest.mark.slow,
    pytest.mark.timeout(BUILD_TIMEOUT_S + 600),
    pytest.mark.skipif(os.geteuid() != 0, reason="building the image needs root (debootstrap, buildah chroot)"),
]
START_TIMEOUT_S = 120
READY_TIMEOUT_S = 300


def buildah(*args: str, timeout: float = 600) -> str:
    done = subprocess.run([*BUILDAH, *args], capture_output=True, text=True, timeout=timeout)
    assert done.returncode == 0, f"buildah {' '.join(args)}: {done.stderr[-2000:]}"
    return done.stdout


def build_image(tag: str, *flags: str) -> dict[str, Any]:
    """Build ``tag`` with ``scripts/build_image.sh [flags] tag`` (or find every layer cached) and
    return its Docker config."""
    started = time.monotonic()
    done = subprocess.run(
        [str(ROOT / "scripts" / "build_image.sh"), *flags, tag],
        capture_output=True,
        text=True,
        timeout=BUILD_TIMEOUT_S,
    )
    assert done.returncode == 0, f"scripts/build_image.sh failed:\n{done.stderr[-4000:]}"
    assert done.stdout.strip().splitlines()[-1] == tag
    log.info("scripts/build_image.sh %s took %.0f s", " ".join(flags), time.monotonic() - started)
    return json.loads(buildah("inspect", "--type", "image", tag))["Docker"]["config"]


@contextlib.contextmanager
def working_container(tag: str, name: str) -> Iterator[str]:
    """A working container ``name`` of image ``tag``, removed afterwards."""
    if _exists(name):  # left by a run that was killed
        buildah("rm", name, timeout=120)
    buildah("from", "--pull-never", "--name", name, tag)
    try:
        yield name
    finally:
        buildah("rm", name, timeout=300)


def _exists(name: str) -> bool:
    return subprocess.run([*BUILDAH, "inspect", "--type", "container", name], capture_output=True).returncode == 0


def owned_dir(path: Path, uid: int, mode: int = 0o755) -> Path:
    path.mkdir(parents=True, exist_ok=True)
    os.chown(path, uid, uid)
    path.chmod(mode)
    return path


def image_uid(image: Mapping[str, Any]) -> int:
    return int(image["User"].split(":")[0])


def image_env(image: Mapping[str, Any]) -> dict[str, str]:
    """The variables the image's ENV sets."""
    return dict(item.split("=", 1) for item in image["Env"])


def writable_volumes(base: Path, image: Mapping[str, Any]) -> dict[Path, str]:
    """What the manifests mount writable for the pod: /tmp and the cache (emptyDirs)."""
    uid = image_uid(image)
    return {
        owned_dir(base / "tmp", uid, 0o1777): "/tmp",
        owned_dir(base / "cache", uid): image_env(image)["XDG_CACHE_HOME"],
    }


def pod_argv(image: Mapping[str, Any], *extra: str) -> list[str]:
    """The image's entrypoint and command (`vecsim pod`), standalone flags after it."""
    assert image["Cmd"] == ["pod"]
    return [*image["Entrypoint"], *image["Cmd"], *extra]


class InContainer:
    """One command running in the container under ``buildah run`` (its own session, so that
    stopping it ends buildah and everything it started)."""

    def __init__(
        self, container: str, argv: Sequence[str], env: Mapping[str, str], volumes: Mapping[Path, str], log_path: Path
    ):
        flags = [f for k, v in env.items() for f in ("--env", f"{k}={v}")]
        flags += [f for host, inside in volumes.items() for f in ("--volume", f"{host}:{inside}")]
        self.log_path = log_path
        with log_path.open("ab") as out:
            self.proc = subprocess.Popen(
                [*BUILDAH, "run", "--isolation", "chroot", *flags, container, "--", *argv],
                stdout=out,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )

    def processes(self) -> list[psutil.Process]:
        with contextlib.suppress(psutil.NoSuchProcess):
            return psutil.Process(self.proc.pid).children(recursive=True)
        return []

    def stop(self) -> None:
        survivors = self.processes()
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.proc.pid, signal.SIGTERM)
        try:
            self.proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(timeout=30)
        for process in survivors:  # started in a session of their own by the chroot runtime
            with contextlib.suppress(psutil.NoSuchProcess):
                process.kill()

    def log_text(self) -> str:
        return log_tail(self.log_path, 6000)


@contextlib.contextmanager
def running(
    container: str, argv: Sequence[str], env: Mapping[str, str], volumes: Mapping[Path, str], log_path: Path
) -> Iterator[InContainer]:
    proc = InContainer(container, argv, env, volumes, log_path)
    try:
        yield proc
    finally:
        proc.stop()


def run_once(
    container: str, argv: Sequence[str], env: Mapping[str, str] = {}, timeout: float = 120
) -> subprocess.CompletedProcess[str]:
    flags = [f for k, v in env.items() for f in ("--env", f"{k}={v}")]
    return subprocess.run(
        [*BUILDAH, "run", "--isolation", "chroot", *flags, container, "--", *argv],
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def failed_detail(url: str, proc: InContainer) -> str | None:
    """The pod's /readyz detail once its build has failed (None before)."""
    assert proc.proc.poll() is None, f"the pod exited with {proc.proc.returncode}:\n{proc.log_text()}"
    with contextlib.suppress(httpx.HTTPError):
        response = httpx.get(f"{url}/readyz", timeout=5)
        assert response.status_code == 503, f"the pod turned ready: {response.text}"
        detail = response.json()["detail"]
        return detail if "failed" in detail else None
    return None
